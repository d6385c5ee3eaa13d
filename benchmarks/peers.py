"""Against the peers on their own kind of data (issue #32 item 7): a wide-baseline, noisy,
dark-speckled capture, ours against TSDF depth fusion and bicubic.

The real capture (a plaster bust, 2 MP colour, depth at SF 4, 20 frames, fixed room light, wide
baseline) is not here; its rendered analogue is: the bunny in a pale stone with dark speckles
(``albedo="speckled"``), the D415-like sensor (disparity terraces, depth noise growing with z^2,
holes, flying pixels, sRGB 8-bit colour with shot noise, gain drift), an orbit reaching 30 degrees
from the reference (``orbit_deg=30``), 20 frames, lit by room light (fixed in the scene) and by the
LED. Scored as the issue scores, in the reference view: depth RMSE against the true depth; normal
error against the true normals and against "sensor-like" normals (the true depth smoothed by a
Gaussian of 4 px, normalised over the object, as the issue smooths its scanner's depth); the normal
error over the darkest quarter of the albedo and the correlation of the depth error's high-pass with
the albedo's (Gaussians of 3 px) say whether colour leaked into shape. Pixels: the object 4 px
inside its silhouette where every method has depth.

Methods: bicubic; :func:`o3d_mvps.baselines.tsdf_fusion` with 4 mm and 2 mm voxels (true poses,
and 4 mm with the registration's poses); ours with registered poses (``refine(capture)``) and with
the true poses given. Writes ``peers.json``, ``peers.md`` and ``peers.png`` (normal error maps).
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np
from scipy import ndimage

from o3d_mvps import RefineOptions, refine, synthetic
from o3d_mvps.baselines import bicubic, tsdf_fusion
from o3d_mvps.fileio import json_text
from o3d_mvps.metrics import _masked_lowpass, depth_rmse_mm, normal_mae_deg
from o3d_mvps.model.normals import perspective_normals

from .plots import error_maps

FULL = {"size": (640, 480), "scale_factor": 4, "frames": 20}
QUICK = {"size": (160, 120), "scale_factor": 4, "frames": 8}
ORBIT_DEG = 30.0
SENSOR_SMOOTHING_PX = 4.0  # the Gaussian on the scanner's normals
HIGH_PASS_PX = 3.0
INNER_PX = 4
LIGHTS = ("room", "led")
PICTURE_METHODS = ("bicubic", "tsdf 4 mm", "tsdf 2 mm", "ours, given poses")


def add_arguments(parser) -> None:
    parser.add_argument("--light", default="both", choices=(*LIGHTS, "both"),
                        help="room light, the LED, or both (default)")


def render(case: dict, light: str, seed: int = 0):
    """The wide-baseline, speckled, D415-like capture of the bunny under ``light``."""
    return synthetic.render_capture("bunny", frames=case["frames"], size=case["size"],
                                    scale_factor=case["scale_factor"], light=light, sensor="d415",
                                    albedo="speckled", orbit_deg=ORBIT_DEG, seed=seed)


def lowpass(values: np.ndarray, mask: np.ndarray, sigma_px: float) -> np.ndarray:
    """(H, W) Gaussian low-pass of ``values`` normalised over ``mask`` (0 off it)."""
    out = np.zeros(values.shape)
    out[mask] = _masked_lowpass(values, mask, sigma_px)
    return out


def sensor_like_normals(capture) -> np.ndarray:
    """(H, W, 3) normals of the true depth smoothed by a Gaussian of 4 px over the object."""
    truth = np.asarray(capture.groundtruth.depth, np.float64)
    mask = truth > 0
    return perspective_normals(lowpass(truth, mask, SENSOR_SMOOTHING_PX), capture.color_K(), mask)[0]


def scores(depth: np.ndarray, capture, pixels: np.ndarray, dark: np.ndarray, smoothed: np.ndarray) -> dict:
    """Depth RMSE (mm), normal MAE (deg) against the true and the sensor-like normals, over the
    darkest albedo quarter, and the depth error's high-pass correlation with the albedo's."""
    gt, K = capture.groundtruth, capture.color_K()
    truth = np.asarray(gt.depth, np.float64)
    normals = perspective_normals(depth, K, depth > 0)[0]
    albedo = np.asarray(gt.albedo, np.float64).mean(axis=2)
    error = np.where(pixels, depth - truth, 0.0)
    high = (error - lowpass(error, pixels, HIGH_PASS_PX))[pixels]
    high_albedo = (albedo - lowpass(albedo, pixels, HIGH_PASS_PX))[pixels]
    true_normals = np.asarray(gt.normals, np.float64)
    return {"rmse_mm": depth_rmse_mm(depth, truth, pixels),
            "mae_deg": normal_mae_deg(normals, true_normals, pixels),
            "mae_sensor_like_deg": normal_mae_deg(normals, smoothed, pixels),
            "mae_dark_deg": normal_mae_deg(normals, true_normals, dark),
            "high_pass_mm": 1000 * float(np.std(high)),
            "correlation": float(np.corrcoef(high, high_albedo)[0, 1])}


def error_map(depth: np.ndarray, capture, pixels: np.ndarray) -> np.ndarray:
    """(H, W) degrees between the depth's normals and the true ones, NaN off ``pixels``."""
    normals = perspective_normals(depth, capture.color_K(), depth > 0)[0]
    cos = np.clip(np.sum(normals * np.asarray(capture.groundtruth.normals, np.float64), axis=2), -1.0, 1.0)
    return np.where(pixels, np.degrees(np.arccos(cos)), np.nan)


def light_rows(case: dict, light: str) -> tuple[list[dict], dict]:
    """Every method's scores on one light's capture, and the pictured methods' error maps."""
    capture = render(case, light)
    gt = capture.groundtruth
    results, seconds = {}, {}

    def timed(name, make):
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            results[name] = make()
        seconds[name] = time.perf_counter() - t

    timed("bicubic", lambda: bicubic(capture))
    timed("tsdf 4 mm", lambda: tsdf_fusion(capture, 0.004, poses=gt.poses))
    timed("tsdf 2 mm", lambda: tsdf_fusion(capture, 0.002, poses=gt.poses))
    timed("ours, registered poses", lambda: refine(capture, RefineOptions(progress=False, drop_depth_outliers=True)))
    registered = results["ours, registered poses"]
    used = [row["index"] for row in registered.info["frames_report"] if row["used"]]  # frames it kept
    timed("tsdf 4 mm, ours' refined poses", lambda: tsdf_fusion(capture.select(used), 0.004,
                                                                 poses=registered.poses.numpy()))
    timed("ours, given poses", lambda: refine(capture, RefineOptions(progress=False, drop_depth_outliers=True), initial_poses=gt.poses))
    truth = np.asarray(gt.depth, np.float64)
    pixels = truth > 0
    for r in results.values():
        pixels &= r.mask_array() & (r.depth_array() > 0)
    pixels = ndimage.binary_erosion(pixels, iterations=INNER_PX)
    albedo = np.asarray(gt.albedo, np.float64).mean(axis=2)
    dark = pixels & (albedo <= np.percentile(albedo[pixels], 25))
    smoothed = sensor_like_normals(capture)
    rows = [{"method": name, **scores(r.depth_array().astype(np.float64), capture, pixels, dark, smoothed),
             "wall_s": seconds[name], "pixels": int(pixels.sum())} for name, r in results.items()]
    maps = {name: error_map(results[name].depth_array().astype(np.float64), capture, pixels)
            for name in PICTURE_METHODS}
    return rows, maps


def markdown(case: dict, scenes: list[dict]) -> str:
    lines = [f"# Against depth fusion: bunny, dark-speckled stone, D415-like sensor, {case['size'][0]}x"
             f"{case['size'][1]}, SF {case['scale_factor']}, {case['frames']} frames, orbit to {ORBIT_DEG:g} deg",
             "", "Reference view, object 4 px inside the silhouette. MAE sensor-like: against the true depth's "
             "normals smoothed by a Gaussian of 4 px. Dark: the darkest quarter of the albedo. High-pass: standard "
             "deviation of the depth error minus its Gaussian (3 px); correlation: of that with the albedo's "
             "high-pass. Wall s: seconds on a loaded 2-core machine (shared with other jobs).", ""]
    for scene in scenes:
        lines += [f"## {scene['light']} light", "",
                  "| method | depth RMSE mm | MAE deg | MAE sensor-like deg | MAE dark deg | high-pass mm | "
                  "correlation | wall s |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in scene["rows"]:
            lines.append(f"| {r['method']} | {r['rmse_mm']:.2f} | {r['mae_deg']:.2f} | {r['mae_sensor_like_deg']:.2f} | "
                         f"{r['mae_dark_deg']:.2f} | {r['high_pass_mm']:.3f} | {r['correlation']:.3f} | "
                         f"{r['wall_s']:.1f} |")
        lines.append("")
    return "\n".join(lines)


def crop(maps: dict, margin: int = 4) -> dict:
    rows, cols = np.nonzero(np.isfinite(next(iter(maps.values()))))
    box = (slice(max(rows.min() - margin, 0), rows.max() + margin + 1),
           slice(max(cols.min() - margin, 0), cols.max() + margin + 1))
    return {name: m[box] for name, m in maps.items()}


def run(args) -> None:
    case = QUICK if args.quick else FULL
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lights = LIGHTS if args.light == "both" else (args.light,)
    scenes = []
    for light in lights:
        rows, maps = light_rows(case, light)
        scenes.append({"light": light, "rows": rows})
        error_maps(out / ("peers.png" if light == "room" else f"peers_{light}.png"), crop(maps), vmax=30.0,
                   title=f"Normal error, {light} light (speckled bunny, D415-like, {case['frames']} frames)")
    result = {"mesh": "bunny", "size": list(case["size"]), "scale_factor": case["scale_factor"],
              "frames": case["frames"], "orbit_deg": ORBIT_DEG, "sensor": "d415", "albedo": "speckled",
              "scenes": scenes}
    (out / "peers.json").write_text(json_text(result, "peers study"))
    (out / "peers.md").write_text(markdown(case, scenes) + "\n")
