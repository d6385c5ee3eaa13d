"""The sensor's 1 mm depth steps in a scene: does the refined depth band along them?

A rendered scene (:func:`o3d_mvps.synthetic.render_ring` with ``surroundings=True``: the object
on a table in front of a wall, automatic masks, 20 frames 18 degrees apart; no noise, so the
depth's 1 mm quantisation steps are the iso-depth lines), lit by room light and by the LED
(``--light room|led|both``, default both), is refined with the true poses, without the
smoothness term (``smoothness=0``, the model before it) and with the light's default; against
bicubic upsampling and the smooth fit of the sensor depth (:func:`o3d_mvps.baselines.smooth_fit`,
what the refinement falls back to where the photometric terms say nothing).

Banding is measured by the *quantisation phase* of each colour pixel: where its true depth lies
between two of the sensor's levels, ``frac(z / step + 1/2)`` (0 and 1 on an iso-depth line, where
the sensor's reading jumps; 1/2 mid-terrace). Pixels within 1/8 of a step of an iso-depth line
are "on the lines", the rest "elsewhere"; a ratio of their mean normal errors above 1 means the
steps show through. Every slope spreads its pixels evenly over the phase, so the ratio does not
confuse steep parts (more steps, larger errors) with banding, as counting the pixels beside a
sensor step did (that measure is kept as ``mae_beside_steps_deg``). Writes ``room.json`` (one
entry per light under ``"scenes"``), ``room.md`` (a section per light) and the normal error maps
``room_banding.png`` (room light) and ``room_banding_led.png`` (LED), drawn from the maps
saved in ``room_maps.npz`` (``python -m benchmarks summary`` redraws them).
"""

from __future__ import annotations

import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy import ndimage

from o3d_mvps import RefineOptions, refine
from o3d_mvps.baselines import bicubic, smooth_fit
from o3d_mvps.capture import read_capture, write_capture
from o3d_mvps.fileio import json_text
from o3d_mvps.metrics import evaluation_mask
from o3d_mvps.model.resampling import repeat_pixels
from o3d_mvps.synthetic import DEPTH_SCALE, render_ring

from .plots import error_maps

FULL = {"size": (640, 480), "scale_factor": 4, "frames": 20}
QUICK = {"size": (160, 120), "scale_factor": 4, "frames": 12}
ON_LINE = 0.125  # phase distance (steps) from an iso-depth line that counts as "on the line"
PHASE_BINS = 8
RIM_PX = 12  # colour pixels from the evaluated region's edge that count as the rim (silhouette errors)
LIGHTS = ("room", "led")
TITLES = {"room": "Room light", "led": "LED"}
PICTURES = {"room": "room_banding.png", "led": "room_banding_led.png"}
MAPS = "room_maps.npz"  # the pictures' error maps, cropped to the object


def add_arguments(parser) -> None:
    parser.add_argument("--mesh", default="bunny", choices=("bunny", "armadillo"))
    parser.add_argument("--light", default="both", choices=(*LIGHTS, "both"),
                        help="what lights the scene: room light, the LED, or both (default)")


def step_pixels(depth_lr: np.ndarray, scale_factor: int) -> np.ndarray:
    """(H, W) bool: colour pixels of depth pixels whose depth differs from a 4-neighbour's (valid both)."""
    z = depth_lr
    step = np.zeros(z.shape, bool)
    for axis in (0, 1):
        a, b = np.swapaxes(z, 0, axis)[:-1], np.swapaxes(z, 0, axis)[1:]
        differs = (a > 0) & (b > 0) & (a != b)
        s = np.swapaxes(step, 0, axis)
        s[:-1] |= differs
        s[1:] |= differs
    return repeat_pixels(step, scale_factor)


def quantisation_phase(depth: np.ndarray, step: float = 1.0 / DEPTH_SCALE) -> np.ndarray:
    """(H, W) in [0, 1): where a true depth (m) lies between two sensor levels (0 = on an iso-depth line)."""
    return np.mod(depth / step + 0.5, 1.0)


def phase_profile(error: np.ndarray, phase: np.ndarray, bins: int = PHASE_BINS) -> list[float]:
    """Mean error (deg) of the evaluated pixels in each of ``bins`` equal phase bins."""
    common = np.isfinite(error)
    index = np.minimum((phase[common] * bins).astype(int), bins - 1)
    sums = np.bincount(index, weights=error[common], minlength=bins)
    counts = np.bincount(index, minlength=bins)
    return [float(s / c) if c else float("nan") for s, c in zip(sums, counts)]


def banding(error: np.ndarray, true_depth: np.ndarray) -> tuple[float, float, float]:
    """Mean normal error (deg) on the iso-depth lines (within :data:`ON_LINE` of a step in
    quantisation phase), elsewhere, and their ratio (> 1: the steps show through), over the
    finite pixels of an (H, W) error map, given the (H, W) true depth in metres."""
    phase = quantisation_phase(true_depth)
    on_line = np.minimum(phase, 1.0 - phase) < ON_LINE
    common = np.isfinite(error)
    on, off = float(np.mean(error[common & on_line])), float(np.mean(error[common & ~on_line]))
    return on, off, on / off


def angular_error(refinement, groundtruth) -> np.ndarray:
    """(H, W) degrees between the refinement's normals and the true ones (NaN off the evaluated pixels)."""
    common = evaluation_mask(refinement, groundtruth)
    n, g = refinement.normals_array(), np.asarray(groundtruth.normals, dtype=np.float64)
    cos = np.clip(np.sum(n * g, axis=2), -1.0, 1.0)
    return np.where(common, np.degrees(np.arccos(cos)), np.nan)


def row(name: str, refinement, capture, steps: np.ndarray, seconds: float | None = None) -> tuple[dict, np.ndarray]:
    """Scores of one method and its (H, W) error map."""
    error = angular_error(refinement, capture.groundtruth)
    common = np.isfinite(error)
    depth = refinement.depth_array()
    rmse = 1000 * float(np.sqrt(np.mean((depth[common] - capture.groundtruth.depth[common]) ** 2)))
    true_depth = np.asarray(capture.groundtruth.depth, dtype=np.float64)
    mean_on, mean_off, ratio = banding(error, true_depth)
    beside = error[common & steps]
    interior = ndimage.binary_erosion(common, iterations=RIM_PX)
    return {"method": name, "mae_deg": float(np.mean(error[common])), "rmse_mm": rmse,
            "mae_interior_deg": float(np.mean(error[interior])), "mae_rim_deg": float(np.mean(error[common & ~interior])),
            "mae_on_lines_deg": mean_on, "mae_elsewhere_deg": mean_off, "banding_ratio": ratio,
            "mae_by_phase_deg": phase_profile(error, quantisation_phase(true_depth)),
            "mae_beside_steps_deg": float(np.mean(beside)) if beside.size else None,
            "pixels": int(common.sum()), "seconds": seconds}, error


def scene_rows(mesh: str, case: dict, light: str) -> tuple[list[dict], dict]:
    """The rows of one light's scene and the methods' (H, W) error maps."""
    capture, _ = render_ring(mesh, frames=case["frames"], size=case["size"], scale_factor=case["scale_factor"],
                             light=light, surroundings=True, noise=False)
    with tempfile.TemporaryDirectory() as tmp:  # through the folder, so the automatic masks are used
        write_capture(capture, Path(tmp) / "capture")
        capture = read_capture(Path(tmp) / "capture")
    steps = step_pixels(capture.depth_array(0), capture.scale_factor)
    rows, maps = [], {}
    for name, make in (("bicubic", bicubic), ("smooth fit", smooth_fit)):
        t = time.perf_counter()
        r, maps[name] = row(name, make(capture), capture, steps, time.perf_counter() - t)
        rows.append(r)
    for name, smoothness in (("ours, smoothness 0", 0.0), ("ours", None)):
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            refinement = refine(capture, RefineOptions(progress=False, smoothness=smoothness),
                                initial_poses=capture.groundtruth.poses)
        r, maps[name] = row(name, refinement, capture, steps, time.perf_counter() - t)
        rows.append(r)
    return rows, maps


def _cell(value, digits=2) -> str:
    return "" if value is None else f"{value:.{digits}f}"


def markdown_section(light: str, rows: list[dict]) -> list[str]:
    """One light's tables: the scores, and the error against the quantisation phase."""
    lines = [f"## {TITLES[light]}", "",
             "| method | MAE deg | RMSE mm | MAE interior | MAE rim | MAE on iso-depth lines | MAE elsewhere | "
             "banding ratio | seconds |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {_cell(r['mae_deg'])} | {_cell(r['rmse_mm'])} | "
                     f"{_cell(r['mae_interior_deg'])} | {_cell(r['mae_rim_deg'])} | {_cell(r['mae_on_lines_deg'])} | "
                     f"{_cell(r['mae_elsewhere_deg'])} | {_cell(r['banding_ratio'])} | {_cell(r['seconds'], 1)} |")
    centres = [f"{(i + 0.5) / PHASE_BINS:.2f}" for i in range(PHASE_BINS)]
    lines += ["", "Mean normal error (deg) against the quantisation phase of the true depth (0 and 1: on an "
              "iso-depth line; 0.5: mid-terrace):", "",
              "| method | " + " | ".join(centres) + " |", "|---|" + "---|" * PHASE_BINS]
    lines += [f"| {r['method']} | " + " | ".join(_cell(v) for v in r["mae_by_phase_deg"]) + " |" for r in rows]
    return lines + [""]


def run(args) -> None:
    case = QUICK if args.quick else FULL
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lights = LIGHTS if args.light == "both" else (args.light,)
    scenes, maps_by_light = [], {}
    lines = [f"# Table-and-wall scene, {args.mesh}, {case['size'][0]}x{case['size'][1]}, SF {case['scale_factor']}, "
             f"{case['frames']} frames (automatic masks, true poses, no noise)", ""]
    for light in lights:
        rows, maps = scene_rows(args.mesh, case, light)
        scenes.append({"light": light, "rows": rows})
        lines += markdown_section(light, rows)
        maps_by_light[light] = crop_to_object(maps)
    result = {"mesh": args.mesh, **{k: list(v) if isinstance(v, tuple) else v for k, v in case.items()},
              "poses": "true", "scenes": scenes}
    (out / "room.json").write_text(json_text(result, "room study"))
    (out / "room.md").write_text("\n".join(lines[:-1]) + "\n")
    save_maps(out / MAPS, maps_by_light)
    draw_pictures(out)


def crop_to_object(maps: dict, margin: int = 4) -> dict:
    """The (H, W) error maps cropped to the evaluated pixels' box plus ``margin`` pixels."""
    valid = np.isfinite(next(iter(maps.values())))
    rows, cols = np.nonzero(valid)
    crop = (slice(max(rows.min() - margin, 0), rows.max() + margin + 1),
            slice(max(cols.min() - margin, 0), cols.max() + margin + 1))
    return {name: error[crop] for name, error in maps.items()}


def save_maps(path: Path, maps_by_light: dict) -> None:
    """Write every light's cropped error maps (deg, float16, NaN = not evaluated) to one .npz,
    keys ``LIGHT/METHOD``: what :func:`draw_pictures` draws from."""
    np.savez_compressed(path, **{f"{light}/{name}": error.astype(np.float16)
                                 for light, maps in maps_by_light.items() for name, error in maps.items()})


def draw_pictures(out: Path, vmax: float = 60.0) -> list[Path]:
    """The error-map pictures (:data:`PICTURES`) from ``out/room_maps.npz``, one per light saved
    there; 0 deg black to ``vmax`` and above light yellow, not evaluated white."""
    source = out / MAPS
    if not source.is_file():
        return []
    with np.load(source) as saved:
        by_light: dict = {}
        for key in saved.files:
            light, name = key.split("/", 1)
            by_light.setdefault(light, {})[name] = saved[key].astype(np.float32)
    written = []
    for light, maps in by_light.items():
        path = out / PICTURES[light]
        error_maps(path, maps, vmax=vmax, title=f"{TITLES[light]}: normal error of the reference view")
        written.append(path)
    return written
