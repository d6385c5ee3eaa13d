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
from o3d_mvps.model.camera import backproject
from o3d_mvps.model.normals import perspective_normals
from o3d_mvps.model.warping import visible, warp

from .plots import error_maps

FULL = {"size": (640, 480), "scale_factor": 4, "frames": 20}
QUICK = {"size": (160, 120), "scale_factor": 4, "frames": 8}
ORBIT_DEG = 30.0
SENSOR_SMOOTHING_PX = 4.0  # the Gaussian on the scanner's normals
HIGH_PASS_PX = 3.0
INNER_PX = 4
LIGHTS = ("room", "led")
PICTURE_METHODS = ("bicubic", "tsdf 4 mm", "tsdf 2 mm", "ours, given poses")
#: the error study's rim band: object pixels within this many pixels of the true silhouette
RIM_PX = 12
#: the error study's methods (those present), against the smoothed sensor (bicubic, 4 px)
STUDY_METHODS = ("ours, given poses", "tsdf 4 mm", "true depth")


#: the methods (``--methods`` names them by these keys), in the tables' order
METHODS = {"bicubic": "bicubic", "tsdf4": "tsdf 4 mm", "tsdf2": "tsdf 2 mm", "ours-registered": "ours, registered poses",
           "tsdf4-refined": "tsdf 4 mm, ours' refined poses", "ours-given": "ours, given poses"}
#: the methods whose depth is also scored smoothed by the sensor-like Gaussian (detail against error)
SMOOTHED_METHODS = ("tsdf 4 mm", "ours, given poses")
SMOOTHED = ", smoothed 4 px"


def add_arguments(parser) -> None:
    parser.add_argument("--light", default="both", choices=(*LIGHTS, "both"),
                        help="room light, the LED, or both (default)")
    parser.add_argument("--methods", default="all",
                        help="comma-separated methods to run (default all): " + ", ".join(METHODS)
                             + "; tsdf4-refined needs ours-registered")


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
            "correlation": float(np.corrcoef(high, high_albedo)[0, 1]) if np.std(high) > 0 else 0.0}


def error_map(depth: np.ndarray, capture, pixels: np.ndarray) -> np.ndarray:
    """(H, W) degrees between the depth's normals and the true ones, NaN off ``pixels``."""
    normals = perspective_normals(depth, capture.color_K(), depth > 0)[0]
    cos = np.clip(np.sum(normals * np.asarray(capture.groundtruth.normals, np.float64), axis=2), -1.0, 1.0)
    return np.where(pixels, np.degrees(np.arccos(cos)), np.nan)


def smoothed_depth(depth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W) ``depth`` smoothed over ``mask`` by the Gaussian that makes the sensor-like normals."""
    return lowpass(depth, mask & (depth > 0), SENSOR_SMOOTHING_PX)


def selected_methods(methods: str) -> list[str]:
    """The table names of ``--methods`` (comma-separated keys of :data:`METHODS`, or "all");
    ValueError naming a key that is not one."""
    if methods == "all":
        return list(METHODS.values())
    keys = [k.strip() for k in methods.split(",") if k.strip()]
    unknown = [k for k in keys if k not in METHODS]
    if unknown or not keys:
        raise ValueError(f"--methods {methods!r}: unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
    if "tsdf4-refined" in keys and "ours-registered" not in keys:
        raise ValueError("--methods: tsdf4-refined fuses with ours-registered's poses; add ours-registered")
    return [name for key, name in METHODS.items() if key in keys]


def light_rows(case: dict, light: str, methods: list[str] | None = None) -> tuple[list[dict], dict, dict]:
    """Every method's scores on one light's capture (and the true depth's, and the smoothed depth
    of :data:`SMOOTHED_METHODS`), the pictured methods' error maps, and the arrays the error study
    reads (:func:`error_sources`)."""
    methods = list(METHODS.values()) if methods is None else methods
    capture = render(case, light)
    gt = capture.groundtruth
    results, seconds = {}, {}
    options = RefineOptions(progress=False)  # the reference's flying pixels replaced (the default)

    def timed(name, make):
        if name not in methods:
            return
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            results[name] = make()
        seconds[name] = time.perf_counter() - t

    def refined_poses_fusion():
        registered = results["ours, registered poses"]
        used = [row["index"] for row in registered.info["frames_report"] if row["used"]]  # frames it kept
        return tsdf_fusion(capture.select(used), 0.004, poses=registered.poses.numpy())

    timed("bicubic", lambda: bicubic(capture))
    timed("tsdf 4 mm", lambda: tsdf_fusion(capture, 0.004, poses=gt.poses))
    timed("tsdf 2 mm", lambda: tsdf_fusion(capture, 0.002, poses=gt.poses))
    timed("ours, registered poses", lambda: refine(capture, options))
    timed("tsdf 4 mm, ours' refined poses", refined_poses_fusion)
    timed("ours, given poses", lambda: refine(capture, options, initial_poses=gt.poses))
    truth = np.asarray(gt.depth, np.float64)
    pixels = truth > 0
    for r in results.values():
        pixels &= r.mask_array() & (r.depth_array() > 0)
    pixels = ndimage.binary_erosion(pixels, iterations=INNER_PX)
    albedo = np.asarray(gt.albedo, np.float64).mean(axis=2)
    dark = pixels & (albedo <= np.percentile(albedo[pixels], 25))
    smoothed = sensor_like_normals(capture)
    depths = {"true depth": truth}
    for name, r in results.items():
        depths[name] = r.depth_array().astype(np.float64)
        if name in SMOOTHED_METHODS:
            depths[name + SMOOTHED] = smoothed_depth(depths[name], r.mask_array())
    rows = [{"method": name, **scores(depth, capture, pixels, dark, smoothed),
             "wall_s": seconds.get(name.removesuffix(SMOOTHED), 0.0), "pixels": int(pixels.sum())}
            for name, depth in depths.items()]
    maps = {name: error_map(depths[name], capture, pixels) for name in PICTURE_METHODS if name in depths}
    return rows, maps, {"capture": capture, "depths": depths, "pixels": pixels, "sensor_like": smoothed}


def frames_seeing(capture) -> np.ndarray:
    """(H, W) how many frames (the reference included) see each pixel of the true surface: in
    view, facing the camera and not hidden by the surface itself
    (:func:`o3d_mvps.model.warping.visible`, the solver's occlusion test), true poses."""
    gt, K = capture.groundtruth, capture.color_K()
    truth = np.asarray(gt.depth, np.float64)
    mask = truth > 0
    points = backproject(truth, K)[mask]
    normals = np.asarray(gt.normals, np.float64)[mask]
    count = np.zeros(truth.shape, int)
    for T in np.asarray(gt.poses, np.float64):
        q, u, v, Z = warp(points, T, K)
        facing = np.einsum("ij,ij->i", normals @ T[:3, :3].T, q) < 0
        count[mask] += visible(u, v, Z, truth.shape) & facing
    return count


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=2), -1.0, 1.0)))


def error_sources(arrays: dict) -> tuple[dict, dict]:
    """Where the normal error against the sensor-like normals comes from (the study of
    :func:`light_rows`'s ``arrays``): per region (all, the rim band of :data:`RIM_PX`, the inner
    pixels, the darkest albedo quarter, the quarter with the steepest albedo (speckle rims: the
    parallax's evidence), the pixels seen by fewer frames than the median pixel) and per method of
    :data:`STUDY_METHODS`: the MAE (deg) against the sensor-like normals, its low-frequency part
    (the method's depth smoothed by the same Gaussian against them) and high-frequency part (the
    method against its own smoothed depth), the MAE against the true normals, and that of the
    smoothed sensor (bicubic smoothed by 4 px; "no region noisier than the sensor's smoothed
    surface"). Also the correlation over the pixels of the high-frequency part with the albedo's
    gradient and with the albedo's darkness. Returns (the JSON-ready study, (H, W) maps in degrees
    for the figure, NaN off the pixels)."""
    capture, depths, pixels, sensor_like = arrays["capture"], arrays["depths"], arrays["pixels"], arrays["sensor_like"]
    K = capture.color_K()
    gt = capture.groundtruth
    truth = np.asarray(gt.depth, np.float64)
    true_normals = np.asarray(gt.normals, np.float64)
    albedo = np.asarray(gt.albedo, np.float64).mean(axis=2)
    gradient = np.hypot(*np.gradient(ndimage.gaussian_filter(albedo, 1.0)))
    seen = frames_seeing(capture)
    rim = pixels & (ndimage.distance_transform_edt(truth > 0) <= RIM_PX)
    regions = {"all": pixels, f"rim band ({RIM_PX} px)": rim, "inner": pixels & ~rim,
               "darkest albedo quarter": pixels & (albedo <= np.percentile(albedo[pixels], 25)),
               "steepest albedo quarter": pixels & (gradient >= np.percentile(gradient[pixels], 75)),
               "seen by fewer frames than the median pixel": pixels & (seen < np.median(seen[pixels]))}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cubic = bicubic(capture)
    sensor = smoothed_depth(cubic.depth_array().astype(np.float64), cubic.mask_array())
    sensor_error = _angle(perspective_normals(sensor, K, sensor > 0)[0], true_normals)
    study = {"regions": {name: int(r.sum()) for name, r in regions.items()},
             "frames_seeing_percentiles": {str(q): float(np.percentile(seen[pixels], q)) for q in (5, 10, 50)},
             "smoothed_sensor_mae_deg": {name: float(sensor_error[r].mean()) for name, r in regions.items()},
             "methods": {}}
    maps = {"true normals vs sensor-like": _angle(true_normals, sensor_like)}
    for name in STUDY_METHODS:
        if name not in depths:
            continue
        depth = depths[name]
        normals = perspective_normals(depth, K, depth > 0)[0]
        smooth = smoothed_depth(depth, depth > 0)
        smooth_normals = perspective_normals(smooth, K, smooth > 0)[0]
        parts = {"sensor_like": _angle(normals, sensor_like), "low": _angle(smooth_normals, sensor_like),
                 "high": _angle(normals, smooth_normals), "true": _angle(normals, true_normals)}
        study["methods"][name] = {
            "by_region": {region: {part: float(e[r].mean()) for part, e in parts.items()} for region, r in regions.items()},
            "high_vs_albedo_gradient": float(np.corrcoef(parts["high"][pixels], gradient[pixels])[0, 1]),
            "high_vs_albedo_darkness": float(np.corrcoef(parts["high"][pixels], -albedo[pixels])[0, 1])}
        if name != "true depth":
            maps[f"{name}: vs sensor-like"] = parts["sensor_like"]
            maps[f"{name}: low-frequency part"] = parts["low"]
        if name == "ours, given poses":
            maps[f"{name}: vs truth"] = parts["true"]
    return study, {label: np.where(pixels, m, np.nan) for label, m in maps.items()}


def study_markdown(light: str, study: dict) -> list[str]:
    """The error study's table for one light (:func:`error_sources`)."""
    lines = [f"### Where the sensor-like error comes from, {light} light", "",
             "MAE against the sensor-like normals = its low-frequency part (the depth smoothed by the same "
             "4 px Gaussian, against them) + its high-frequency part (the depth against its own smoothing), "
             "roughly; true: against the true normals; smoothed sensor: bicubic smoothed by 4 px, against the true "
             "normals. Frames seeing a pixel (5th/10th/50th percentile): "
             + "/".join(f"{v:g}" for v in study["frames_seeing_percentiles"].values()) + ".", "",
             "| region | pixels | smoothed sensor, true | "
             + " | ".join(f"{m}: sensor-like / low / high / true" for m in study["methods"]) + " |",
             "|---|---:|---:|" + "---:|" * len(study["methods"])]
    for region, count in study["regions"].items():
        cells = [f"{m['by_region'][region]['sensor_like']:.2f} / {m['by_region'][region]['low']:.2f} / "
                 f"{m['by_region'][region]['high']:.2f} / {m['by_region'][region]['true']:.2f}"
                 for m in study["methods"].values()]
        lines.append(f"| {region} | {count} | {study['smoothed_sensor_mae_deg'][region]:.2f} | " + " | ".join(cells) + " |")
    lines += ["", "Correlation of the high-frequency part with the albedo's gradient / darkness: "
              + "; ".join(f"{name} {m['high_vs_albedo_gradient']:.3f} / {m['high_vs_albedo_darkness']:.3f}"
                          for name, m in study["methods"].items()) + ".", ""]
    return lines


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
        if scene.get("study", {}).get("methods"):
            lines += study_markdown(scene["light"], scene["study"])
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
    methods = selected_methods(args.methods)
    scenes = []
    for light in lights:
        rows, maps, arrays = light_rows(case, light, methods)
        study, study_maps = error_sources(arrays)
        scenes.append({"light": light, "rows": rows, "study": study})
        suffix = "" if light == "room" else f"_{light}"
        if maps:
            error_maps(out / f"peers{suffix}.png", crop(maps), vmax=30.0,
                       title=f"Normal error, {light} light (speckled bunny, D415-like, {case['frames']} frames)")
        error_maps(out / f"peers_sources{suffix}.png", crop(study_maps), vmax=30.0,
                   title=f"Normal error against the sensor-like normals and its parts, {light} light")
    result = {"mesh": "bunny", "size": list(case["size"]), "scale_factor": case["scale_factor"],
              "frames": case["frames"], "orbit_deg": ORBIT_DEG, "sensor": "d415", "albedo": "speckled",
              "scenes": scenes}
    (out / "peers.json").write_text(json_text(result, "peers study"))
    (out / "peers.md").write_text(markdown(case, scenes) + "\n")
