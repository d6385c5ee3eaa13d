"""``report.html``: one self-contained page that shows what a run did.

Built beside a run's results (``refine``, ``reconstruct``, ``demo``) from the folder's
``report.json`` and the arrays in memory: input vs refined normals, albedo, depth, the
per-frame lighting, the reference frame's residual map, the energy and pose plots (matplotlib,
as inline PNG data URIs), the warnings, frames and input checks the report holds, and a 3D
view of the mesh that a person can turn (VTK's scene serialised by trame-vtk into vtk.js's
offline viewer, inline). The page loads nothing from the network.

Every key of report.json beyond ``method``, ``energy``, ``timings`` and ``info`` is optional:
a section whose data is absent is left out.
"""

from __future__ import annotations

import base64
import html
import io
import json
import os
import re
import time
from pathlib import Path

import numpy as np

from .fileio import atomic_files

__all__ = ["write_report_page", "report_page_html", "mesh_viewer_html", "reference_residual", "normals_figure",
           "albedo_depth_figure", "lighting_figure", "residual_figure", "frame_residuals_figure", "energy_figure",
           "pose_figure", "pose_errors", "show_mesh", "page_mesh", "REPORT_HTML", "MAX_PAGE_TRIANGLES"]

REPORT_HTML = "report.html"
#: The page's mesh is decimated to at most this many triangles (about 1.5 MB of vertex data).
MAX_PAGE_TRIANGLES = 40_000
#: Figure resolution (dots per inch) of the inline PNGs.
DPI = 80
#: Images are drawn from at most about this many pixels a side (every k-th pixel): a panel is
#: ~300 px wide on the page, and resampling a 1280x720 image in the figure cost more than the rest.
MAX_SHOWN_PX = 480

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em auto; max-width: 1100px; color: #222; padding: 0 1em; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; border-bottom: 1px solid #ccc; margin-top: 1.6em; }
table { border-collapse: collapse; margin: 0.5em 0; font-size: 0.9em; }
td, th { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: left; }
th { background: #f3f3f3; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
img { max-width: 100%; height: auto; display: block; margin: 0.5em 0; }
.warning { background: #fff4e0; border-left: 4px solid #e69500; padding: 0.3em 0.8em; margin: 0.3em 0; }
.error { background: #fde8e8; border-left: 4px solid #c62828; }
.ok { color: #2e7d32; } .note { color: #555; font-size: 0.9em; }
iframe.viewer { width: 100%; height: 560px; border: 1px solid #ccc; }
"""


# -- the page ------------------------------------------------------------------------------------
def write_report_page(folder, *, refinement=None, capture=None, mesh=None, title: str | None = None,
                      warnings: list | None = None) -> Path:
    """Write ``folder/report.html`` for a run whose results (and report.json) are in ``folder``.

    Parameters
    ----------
    folder : str or Path
        A run's output folder, already written (report.json is read from it when present).
    refinement : Refinement, optional
        The refinement the folder holds (default: read from the folder when it is a refinement
        folder; a reconstruction folder has none).
    capture : Capture, optional
        The input: adds the input normals (the sensor's depth, bicubic-upsampled), the reference
        frame's residual map and, for synthetic captures, the pose errors against the truth.
    mesh : o3d.t.geometry.TriangleMesh, optional
        Shown in the 3D view (default: ``refinement.to_mesh()``); decimated to
        :data:`MAX_PAGE_TRIANGLES`.
    title : str, optional
    warnings : list of str, optional
        Shown with report.json's ``warnings`` (e.g. the Python warnings a command caught).

    Returns
    -------
    Path
        The page, replaced when it exists (it belongs to the run that wrote ``folder``).
    """
    folder = Path(folder)
    report_path = folder / "report.json"
    report = json.loads(report_path.read_text()) if report_path.is_file() else {}
    if warnings:
        report = {**report, "warnings": list(report.get("warnings") or []) + [str(w) for w in warnings]}
    if refinement is None and (folder / "depth.npy").is_file():
        from .refinement import read_refinement

        refinement = read_refinement(folder)
    page = report_page_html(report, refinement=refinement, capture=capture, mesh=mesh,
                            title=title or f"o3d_mvps report: {folder.name}")
    path = folder / REPORT_HTML
    with atomic_files([path], overwrite=True) as tmp:
        tmp[0].write_text(page, encoding="utf-8")
    return path


def report_page_html(report: dict, *, refinement=None, capture=None, mesh=None, title: str = "o3d_mvps report") -> str:
    """The page's HTML text (see :func:`write_report_page`)."""
    t0 = time.perf_counter()
    info = report.get("info", {}) if isinstance(report.get("info"), dict) else {}
    parts = [f"<h1>{_e(title)}</h1>", _summary(report, info, refinement)]
    parts.append(_warnings(report, info))
    if refinement is not None:
        parts.append(_section("Normals, albedo and depth", _image_figures(refinement, capture)))
        parts.append(_section("Lighting per frame", _lighting_figure(refinement, info)))
        parts.append(_section("Residuals", _residual_figures(refinement, capture, report, info)))
        parts.append(_section("Convergence", _energy_figure(report)))
        parts.append(_section("Camera poses", _pose_figures(refinement, capture, info)))
    parts.append(_section("Accuracy against the ground truth", _accuracy_table(report)))
    parts.append(_section("Frames", _frames_table(report, info, refinement)))
    parts.append(_section("Input checks", _checks_table(report, info)))
    parts.append(_section("Reference views", _views_table(report)))
    parts.append(_section("Timings", _timings_table(report)))
    stride = 1
    if mesh is None and refinement is not None:
        mesh, stride = page_mesh(refinement)
    if mesh is not None:
        parts.append(_section("3D view", _mesh_section(mesh, "camera", stride)))
    parts.append(f'<p class="note">Built in {time.perf_counter() - t0:.1f} s by o3d_mvps; self-contained '
                 "(no network). Mouse: left drag turns, right drag or wheel zooms, shift + drag pans.</p>")
    body = "\n".join(p for p in parts if p)
    return (f'<!doctype html>\n<html lang="en"><head><meta charset="utf-8"><title>{_e(title)}</title>'
            f"<style>{_STYLE}</style></head><body>\n{body}\n</body></html>\n")


def _e(x) -> str:
    return html.escape(str(x))


def _section(heading: str, content: str | None) -> str:
    return f"<h2>{_e(heading)}</h2>\n{content}" if content else ""


def _table(header: list[str], rows: list[list]) -> str:
    def cell(v):
        if isinstance(v, float):
            return f'<td class="num">{v:.4g}</td>'
        if isinstance(v, (int, np.integer)) and not isinstance(v, bool):
            return f'<td class="num">{v}</td>'
        return f"<td>{_e('' if v is None else v)}</td>"

    head = "".join(f"<th>{_e(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(cell(v) for v in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


#: Fixed figure margins in inches (left, right, bottom, top, gap between panels): room for tick
#: labels, axis labels, a colour bar's label on the right and a title plus suptitle on top.
#: Fixed margins instead of matplotlib's constrained layout, which measured every text three
#: times: half the cost of the page's seven PNGs.
MARGINS_IN = (0.8, 0.75, 0.55, 0.65, 0.9)


def _subplots(nrows: int, ncols: int, figsize: tuple[float, float]):
    """(figure, axes (nrows, ncols)): a matplotlib Figure outside pyplot (no backend switch, nothing
    kept open: a notebook's inline backend is left alone), panels placed with :data:`MARGINS_IN`."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=DPI)
    width, height = figsize
    left, right, bottom, top, gap = MARGINS_IN
    panel_w = max((width - left - right - (ncols - 1) * gap) / ncols, 0.1)
    panel_h = max((height - bottom - top - (nrows - 1) * gap) / nrows, 0.1)
    fig.subplots_adjust(left=left / width, right=1 - right / width, bottom=bottom / height, top=1 - top / height,
                        wspace=gap / panel_w, hspace=gap / panel_h)
    return fig, fig.subplots(nrows, ncols, squeeze=False)


def _png(fig, alt: str) -> str:
    """An <img> holding the figure as a base64 PNG data URI, described by ``alt``."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI)
    data = base64.b64encode(buffer.getvalue()).decode("ascii")
    return f'<img alt="{_e(alt)}" src="data:image/png;base64,{data}">'


# -- text sections -------------------------------------------------------------------------------
def _summary(report: dict, info: dict, refinement) -> str:
    rows = [["method", report.get("method", "reconstruct" if "references" in report else "?")]]
    if refinement is not None:
        depth = refinement.depth_array()
        rows.append(["depth grid (colour resolution)", f"{depth.shape[1]} x {depth.shape[0]} px"])
        rows.append(["pixels refined", int(refinement.mask_array().sum())])
    frames = info.get("frames")
    if isinstance(frames, list):
        rows.append(["frames used", len(frames)])
    light = info.get("light_model")
    if isinstance(light, dict):
        offset = light.get("offset_m")
        rows.append(["light model", light.get("model", "?") + (
            f", LED at {', '.join(f'{1000 * v:.1f}' for v in offset)} mm from the lens" if offset else "")])
    for key, label in (("device", "device"), ("peak_memory_mb", "peak memory (MB)")):
        value = report.get(key, info.get(key))
        if value is not None:
            rows.append([label, value])
    total = (report.get("timings") or {}).get("total")
    if total is not None:
        rows.append(["total time (s)", float(total)])
    for key, label in (("azimuth_span_deg", "azimuth span (deg)"), ("goes_around", "goes all round"),
                       ("triangles", "mesh triangles"), ("textured", "textured")):
        if key in report:
            rows.append([label, report[key]])
    summary = report.get("summary")
    text = f"<p>{_e(summary)}</p>" if isinstance(summary, str) else ""
    if isinstance(summary, dict):
        rows += [[k, v] for k, v in summary.items() if not isinstance(v, (dict, list))]
    return text + _table(["", ""], rows)


def _warnings(report: dict, info: dict) -> str:
    items = list(report.get("warnings") or []) + list(info.get("warnings") or [])
    failed = report.get("failed") or {}
    items += [f"reference view {k} failed: {v}" for k, v in failed.items()]
    if "goes_around" in report and not report["goes_around"]:
        items.append(f"the frames cover {report.get('azimuth_span_deg', '?')} degrees around the object: "
                     "the back of the mesh is missing")
    left_out = (info.get("views") or {}).get("left_out") if isinstance(info.get("views"), dict) else None
    for frame, reason in (left_out or {}).items():
        items.append(f"frame {frame} left out: {reason}")
    if not items:
        return '<h2>Warnings</h2><p class="ok">none</p>'
    text = "".join(f'<div class="warning">{_e(w if isinstance(w, str) else json.dumps(w))}</div>' for w in items)
    return f"<h2>Warnings</h2>{text}"


def _accuracy_table(report: dict) -> str | None:
    rows = report.get("accuracy")
    if not rows:
        return None
    return _table(["method", "normal MAE (deg)", "depth RMSE (mm)"],
                  [[r.get("method"), r.get("mae_deg"), r.get("rmse_mm")] for r in rows])


def _frames_table(report: dict, info: dict, refinement) -> str | None:
    frames = info.get("frames_report") or report.get("frames")
    if isinstance(frames, list) and frames and isinstance(frames[0], dict):
        return _table(["frame", "file", "used", "reason"],
                      [[f.get("index"), f.get("file"), "yes" if f.get("used") else "no", f.get("reason")]
                       for f in frames])
    views = info.get("views")
    if isinstance(views, dict) and "covisibility" in views:
        used = set(views.get("frames") or [])
        left = views.get("left_out") or {}
        rows = [[0, "yes", 1.0, "reference"]]
        rows += [[int(k), "yes" if int(k) in used else "no", float(v), left.get(k) or left.get(int(k))]
                 for k, v in sorted(views["covisibility"].items(), key=lambda kv: int(kv[0]))]
        return _table(["frame", "used", "covisibility", "reason"], rows)
    if isinstance(info.get("frames"), list):
        return f"<p>capture frames used: {_e(', '.join(str(f) for f in info['frames']))}</p>"
    return None


def _checks_table(report: dict, info: dict) -> str | None:
    inputs = info.get("inputs") or report.get("inputs")
    checks = inputs.get("checks") if isinstance(inputs, dict) else None
    if not checks:
        return None
    table = _table(["check", "status", "detail"], [[c.get("name"), c.get("status"), c.get("detail")] for c in checks])
    conventions = inputs.get("conventions")
    if conventions:
        table += _table(["convention", "value"], [[k, json.dumps(v) if not isinstance(v, str) else v]
                                                 for k, v in conventions.items()])
    return table


def _views_table(report: dict) -> str | None:
    views = report.get("views")
    if not isinstance(views, list) or not views:
        return None
    return _table(["reference frame", "frames refined with it", "seconds"],
                  [[v.get("reference"), ", ".join(str(f) for f in (v.get("frames") or [])), v.get("seconds")]
                   for v in views])


def _timings_table(report: dict) -> str | None:
    timings = report.get("timings")
    if not isinstance(timings, dict) or not timings:
        return None
    return _table(["stage", "seconds"], [[k, float(v)] for k, v in timings.items() if isinstance(v, (int, float))])


# -- figures (public: the notebooks show the same ones) -------------------------------------------
def _image_axes(ax, title: str) -> None:
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")


def _crop(mask: np.ndarray, margin: int = 8) -> tuple[tuple[slice, slice], tuple[float, float, float, float]]:
    """(rows, columns) slices of the mask's bounding box plus ``margin`` pixels, and the imshow
    ``extent`` that keeps the axes in the full image's pixel coordinates."""
    if not mask.any():
        return (slice(None), slice(None)), (-0.5, mask.shape[1] - 0.5, mask.shape[0] - 0.5, -0.5)
    rows, cols = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    v0, v1 = max(rows[0] - margin, 0), min(rows[-1] + margin + 1, mask.shape[0])
    u0, u1 = max(cols[0] - margin, 0), min(cols[-1] + margin + 1, mask.shape[1])
    return (slice(v0, v1), slice(u0, u1)), (u0 - 0.5, u1 - 0.5, v1 - 0.5, v0 - 0.5)


def _shown(image: np.ndarray, box: tuple[slice, slice]) -> np.ndarray:
    """``image[box]`` (h, w, ...) at every k-th pixel, k the smallest keeping both sides <= :data:`MAX_SHOWN_PX`
    (for display: imshow's ``extent`` keeps the axes in full-image pixels)."""
    crop = image[box]
    k = max(1, -(-max(crop.shape[:2]) // MAX_SHOWN_PX))
    return crop[::k, ::k]


def _normal_rgb(normals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) display colours (n + 1) / 2, white outside the mask."""
    return np.where(mask[..., None], np.clip((normals + 1.0) / 2.0, 0, 1), 1.0)


def _frames_of(refinement, n: int) -> list:
    """The capture frame numbers of a refinement's n per-frame rows (``info["frames"]``, else 0..n-1)."""
    frames = refinement.info.get("frames")
    return list(frames) if isinstance(frames, list) and len(frames) == n else list(range(n))


def normals_figure(refinement, input_normals: np.ndarray | None = None, truth: np.ndarray | None = None):
    """Input (e.g. the sensor's depth upsampled), refined and true normals (H, W, 3) side by side
    as RGB = (n + 1) / 2, and the angle (deg) between the refined normals and the input's (or the
    truth's, when given) with its colour bar; cropped to the mask, axes in pixels."""
    mask = refinement.mask_array()
    normals = refinement.normals_array()
    panels = ([("input normals", input_normals)] if input_normals is not None else []) + \
        [("refined normals", normals)] + ([("true normals", truth)] if truth is not None else [])
    against, name = (truth, "truth") if truth is not None else (input_normals, "input")
    fig, axes = _subplots(1, len(panels) + (against is not None), (4.0 * (len(panels) + 1), 3.6))
    box, extent = _crop(mask)
    for ax, (title, image) in zip(axes[0], panels):
        ax.imshow(_normal_rgb(_shown(image, box), _shown(mask, box)), extent=extent)
        _image_axes(ax, title)
    if against is not None:
        cosine = np.clip(np.sum(against * normals, axis=-1), -1, 1)
        angle = np.where(mask, np.degrees(np.arccos(cosine)), np.nan)
        ax = axes[0, -1]
        im = ax.imshow(_shown(angle, box), extent=extent, cmap="magma", vmin=0,
                       vmax=max(5.0, float(np.nanpercentile(angle, 99))))
        _image_axes(ax, f"refined vs {name}: mean {np.nanmean(angle):.1f} deg")
        fig.colorbar(im, ax=ax, label="angle (deg)", shrink=0.8)
    fig.suptitle("normal colours: RGB = (n + 1) / 2 (x right, y down, z toward the camera)", fontsize=9)
    return fig


def albedo_depth_figure(refinement):
    """The refined albedo (sRGB) and depth (mm, colour bar), cropped to the mask, axes in pixels."""
    from .colour import linear_to_srgb

    mask = refinement.mask_array()
    albedo = refinement.albedo_array()
    box, extent = _crop(mask)
    fig, axes = _subplots(1, 2 if albedo is not None else 1, (9, 3.6))
    k = 0
    if albedo is not None:
        shown = _shown(mask, box)[..., None]
        axes[0, 0].imshow(np.where(shown, np.clip(linear_to_srgb(_shown(albedo, box)), 0, 1), 1.0), extent=extent)
        _image_axes(axes[0, 0], "albedo (sRGB)")
        k = 1
    z = np.where(mask, refinement.depth_array() * 1000.0, np.nan)
    im = axes[0, k].imshow(_shown(z, box), extent=extent, cmap="viridis")
    _image_axes(axes[0, k], "refined depth")
    fig.colorbar(im, ax=axes[0, k], label="depth (mm)", shrink=0.8)
    return fig


def lighting_figure(refinement):
    """Each light parameter per capture frame (LED: ambient and intensity; SH: four coefficients); None
    without lighting."""
    if refinement.lighting is None:
        return None
    lights = np.asarray(refinement.lighting.numpy(), dtype=np.float64)
    frames = _frames_of(refinement, len(lights))
    model = (refinement.info.get("light_model") or {}).get("model", "sh" if lights.shape[1] == 4 else "led")
    if lights.shape[1] == 2:
        names = [("ambient", "ambient (linear intensity)"), ("intensity", "LED intensity (irradiance x m$^2$)")]
    else:
        names = [(n, f"{n} (linear intensity)") for n in ("l0 ambient", "l1 (x)", "l2 (y)", "l3 (z)")]
    fig, axes = _subplots(1, len(names), (4.2 * len(names), 3.0))
    for j, (ax, (name, label)) in enumerate(zip(axes[0], names)):
        ax.plot(frames, lights[:, j], "o-", ms=3)
        ax.set_xlabel("capture frame")
        ax.set_ylabel(label)
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3)
    fig.suptitle(f"light model: {model}", fontsize=10)
    return fig


def reference_residual(refinement, capture) -> np.ndarray | None:
    """The reference frame's photometric residual (H, W) in linear intensity, mean over RGB:
    ``I_0 - albedo * shading_0``, NaN outside the mask; None without albedo or lighting.

    The shading is the solver's light model (``info["light_model"]``) at the reference pose.
    """
    albedo = refinement.albedo_array()
    if albedo is None or refinement.lighting is None:
        return None
    from .model.camera import backproject
    from .solver.lighting import make_light_model

    lights = np.asarray(refinement.lighting.numpy(), dtype=np.float64)
    described = refinement.info.get("light_model") or {}
    name = described.get("model", "sh" if lights.shape[1] == 4 else "led")
    offset = described.get("offset_m")
    model = make_light_model(name, led_offset=None if offset is None else np.asarray(offset, dtype=np.float64))
    if name == "point":  # a lamp per frame: the reference frame's
        model = model.at(np.asarray(described["positions_m"], dtype=np.float64)[:1])
    mask = refinement.mask_array()
    if not mask.any() or tuple(capture.color_size) != mask.shape:
        return None
    v, u = np.nonzero(mask)
    depth = refinement.depth_array().astype(np.float64)
    points = backproject(depth[v, u], refinement.intrinsic_matrix(), u.astype(np.float64), v.astype(np.float64))
    normals = refinement.normals_array()[v, u].astype(np.float64)
    shading = model.basis(normals, points, np.eye(4)) @ lights[0]
    image = capture.color_array(0).astype(np.float64)
    out = np.full(mask.shape, np.nan)
    out[v, u] = np.mean(image[v, u] - albedo[v, u] * shading[:, None], axis=1)
    return out


def residual_figure(residual: np.ndarray):
    """A residual map (H, W) (:func:`reference_residual`) with a symmetric colour bar."""
    fig, ax = _subplots(1, 1, (5.2, 3.8))
    ax = ax[0, 0]
    bound = max(float(np.nanpercentile(np.abs(residual), 99)), 1e-6)
    box, extent = _crop(np.isfinite(residual))
    im = ax.imshow(_shown(residual, box), extent=extent, cmap="coolwarm", vmin=-bound, vmax=bound)
    _image_axes(ax, f"reference frame: image - albedo x shading, RMS {np.sqrt(np.nanmean(residual ** 2)):.4f}")
    fig.colorbar(im, ax=ax, label="residual (linear intensity, mean RGB)", shrink=0.8)
    return fig


def frame_residuals_figure(rows: list):
    """Bars of the per-frame RMS residual, rows [{"frame", "rms"}] (report.json's ``residuals``)."""
    fig, ax = _subplots(1, 1, (6.5, 3.0))
    ax = ax[0, 0]
    ax.bar([str(r.get("frame")) for r in rows], [float(r["rms"]) for r in rows])
    ax.set_xlabel("capture frame")
    ax.set_ylabel("RMS residual (linear intensity)")
    ax.set_title("per-frame residual after refinement", fontsize=10)
    return fig


def energy_figure(energy: list):
    """The energy per sweep of each pyramid level, rows [{"level", "iteration", "energy"}], log scale."""
    fig, ax = _subplots(1, 1, (6.5, 3.0))
    ax = ax[0, 0]
    levels = sorted({int(r.get("level", 0)) for r in energy}, reverse=True)
    for level in levels:
        rows = [r for r in energy if int(r.get("level", 0)) == level]
        ax.plot([int(r.get("iteration", i)) for i, r in enumerate(rows)], [float(r["energy"]) for r in rows], "o-",
                ms=3, label=f"level {level}")
    ax.set_xlabel("sweep")
    ax.set_ylabel("energy (robust data term + prior)")
    ax.set_yscale("log")
    ax.legend(fontsize=8, ncol=min(len(levels), 5))
    ax.grid(alpha=0.3)
    ax.set_title("energy per sweep, each pyramid level (0 = full resolution)", fontsize=10)
    return fig


def pose_errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(n, 2) rotation (deg) and translation (mm) errors of poses (n, 4, 4) against truth (n, 4, 4)."""
    from .model.se3 import pose_error

    errors = np.array([pose_error(p, t) for p, t in zip(poses, truth)], dtype=np.float64).reshape(-1, 2)
    errors[:, 1] *= 1000.0
    return errors


def pose_figure(refinement, truth: np.ndarray | None = None, initial: np.ndarray | None = None,
                updates: list | None = None):
    """The refined camera motion from the reference per frame; with ``truth`` (poses of the
    refinement's frames, (n, 4, 4)) the refined pose errors, and the ``initial`` (e.g. odometry)
    poses' errors beside them; with ``updates`` (report.json's ``pose_updates``) how far the
    refinement moved each pose. None without poses."""
    if refinement.poses is None or len(refinement.poses) < 2:
        return None
    from .model.se3 import rotation_angle_deg

    poses = np.asarray(refinement.poses.numpy(), dtype=np.float64)
    frames = _frames_of(refinement, len(poses))
    n_panels = 1 + 2 * (truth is not None) + bool(updates)
    fig, axes = _subplots(1, n_panels, (4.2 * n_panels, 3.2))
    ax = axes[0, 0]
    ax.plot(frames, [rotation_angle_deg(T[:3, :3]) for T in poses], "o-", ms=3, label="rotation (deg)")
    ax.plot(frames, [100 * np.linalg.norm(T[:3, 3]) for T in poses], "s--", ms=3, label="translation (cm)")
    ax.set_xlabel("capture frame")
    ax.set_ylabel("deg / cm")
    ax.set_title("refined camera motion from the reference", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    k = 1
    if truth is not None:
        refined = pose_errors(poses, truth)
        before = pose_errors(initial, truth) if initial is not None else None
        for j, (unit, label) in enumerate((("deg", "rotation error"), ("mm", "translation error"))):
            ax = axes[0, k + j]
            if before is not None:
                ax.plot(frames, before[:, j], "s--", ms=3, color="grey", label="initial (odometry)")
            ax.plot(frames, refined[:, j], "o-", ms=3, label="refined")
            ax.set_xlabel("capture frame")
            ax.set_ylabel(f"{label} ({unit})")
            ax.set_title(f"{label} against the ground truth", fontsize=10)
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
        k += 2
    if updates:
        ax = axes[0, k]
        ax.bar([str(u.get("frame")) for u in updates], [float(u.get("moved_mm") or 0) for u in updates])
        ax.set_xlabel("capture frame")
        ax.set_ylabel("moved by the refinement (mm)")
        ax.set_title("pose updates", fontsize=10)
    return fig


# -- page sections built from the figures ---------------------------------------------------------------
def _image_figures(refinement, capture) -> str:
    input_normals = None
    if capture is not None:
        from .baselines import bicubic

        try:
            input_normals = bicubic(capture).normals_array()
        except Exception:  # noqa: BLE001 - the input view is an extra; the page must not fail for it
            input_normals = None
    return (_png(normals_figure(refinement, input_normals), "input and refined normals")
            + _png(albedo_depth_figure(refinement), "albedo and refined depth"))


def _lighting_figure(refinement, info: dict) -> str | None:
    fig = lighting_figure(refinement)
    return None if fig is None else _png(fig, "lighting per frame")


def _residual_figures(refinement, capture, report: dict, info: dict) -> str | None:
    parts = []
    residual = None
    if capture is not None:
        try:
            residual = reference_residual(refinement, capture)
        except Exception:  # noqa: BLE001 - an extra view; the page must not fail for it
            residual = None
    if residual is not None:
        parts.append(_png(residual_figure(residual), "reference frame residual map"))
    rows = info.get("residuals") or report.get("residuals")
    if isinstance(rows, list) and rows and isinstance(rows[0], dict) and "rms" in rows[0]:
        parts.append(_png(frame_residuals_figure(rows), "per-frame RMS residual"))
    return "".join(parts) or None


def _energy_figure(report: dict) -> str | None:
    energy = report.get("energy")
    if not isinstance(energy, list) or not energy or not isinstance(energy[0], dict):
        return None
    return _png(energy_figure(energy), "energy per sweep")


#: how a pyramid level updated the poses (``info["pose_steps"]``, :func:`.solver.driver._sweeps`), in words
POSE_STEPS = {"joint": "joint pose-depth steps",
              "alternating": "a pose step, then a depth step",
              "held": "held: settled by a coarser level's joint steps",
              "none": "not refined (too few object pixels, one frame, point lights or refine_poses off)"}


def _pose_figures(refinement, capture, info: dict) -> str | None:
    if refinement.poses is None:
        return None
    frames = _frames_of(refinement, len(refinement.poses))
    truth = getattr(getattr(capture, "groundtruth", None), "poses", None)
    truth = None if truth is None or len(truth) <= max(frames) else np.asarray(truth, dtype=np.float64)[frames]
    updates = info.get("pose_updates")
    fig = pose_figure(refinement, truth=truth, updates=updates)
    if fig is None:
        return None
    parts = [_png(fig, "camera poses")]
    if updates:
        parts.append(_table(["frame", "moved (mm)", "moved (deg)", "rejected updates", "note"],
                            [[u.get("frame"), u.get("moved_mm"), u.get("moved_deg"), u.get("rejected_updates"),
                              u.get("note")] for u in updates]))
    if info.get("pose_steps"):  # coarsest level first
        parts.append(_table(["level", "object pixels", "pose update"],
                            [[level, pixels, POSE_STEPS.get(kind, kind)] for level, pixels, kind in info["pose_steps"]]))
    return "".join(parts)


# -- the 3D view ---------------------------------------------------------------------------------
def page_mesh(refinement, max_triangles: int = MAX_PAGE_TRIANGLES):
    """(mesh, k): the refinement's relief meshed from every k-th pixel of each row and column, k the
    smallest stride whose ~2 triangles per kept mask pixel fit in ``max_triangles`` (k = 1: every pixel).

    For the page's 3D view only (exported meshes use every pixel): at D415 size (~90k object
    pixels) meshing every pixel and quadric-decimating took ~1.5 s; a strided grid takes a tenth.
    The stride keeps pixel (k u', k v'), so the intrinsics are divided by k (f / k, c / k).
    """
    mask = refinement.mask_array()
    k = max(1, int(np.ceil(np.sqrt(2.0 * mask.sum() / max_triangles))))
    if k == 1:
        return refinement.to_mesh(), 1
    from .refinement import Refinement

    K = refinement.intrinsic_matrix().astype(np.float64).copy()
    K[:2] /= k
    albedo = refinement.albedo_array()
    small = Refinement.from_arrays(refinement.depth_array()[::k, ::k], mask[::k, ::k], K,
                                   albedo=None if albedo is None else albedo[::k, ::k])
    return small.to_mesh(), k


def _mesh_section(mesh, view: str, stride: int = 1) -> str:
    try:
        viewer, triangles, shown = mesh_viewer_html(mesh, view=view)
    except Exception as err:  # noqa: BLE001 - say why, keep the rest of the page
        return f'<div class="warning">no 3D view: {_e(err)}</div>'
    if stride > 1:
        note = (f"{shown} triangles meshed from one pixel in {stride} along each row and column of the refined "
                "depth (for the page; exported meshes use every pixel), albedo as vertex colours")
    elif shown < triangles:
        note = f"{shown} of {triangles} triangles (decimated for the page), albedo as vertex colours"
    else:
        note = f"{shown} triangles, albedo as vertex colours"
    return (f'<p class="note">{note}; metres, reference camera frame.</p>'
            f'<iframe class="viewer" title="3D view" srcdoc="{html.escape(viewer, quote=True)}"></iframe>')


def mesh_viewer_html(mesh, *, view: str = "camera", max_triangles: int = MAX_PAGE_TRIANGLES,
                     size: tuple[int, int] = (900, 560)) -> tuple[str, int, int]:
    """A standalone HTML page (vtk.js offline viewer, inline) showing ``mesh``, turnable with the mouse.

    Returns (html, triangles of ``mesh``, triangles shown). ``view`` as in
    :func:`o3d_mvps.viz.render_preview`.
    """
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv
    from trame_vtk.modules.vtk.serializers import (SynchronizationContext, extract_array_hash,
                                                   initialize_serializers, reference_id, serialize)
    from trame_vtk.tools.vtksz2html import write_html

    from .export import mesh_arrays, simplify_mesh
    from .viz import _place_camera, _vtk_faces

    total = len(mesh_arrays(mesh)[1])
    positions, tri, _, colours, _, _ = mesh_arrays(simplify_mesh(mesh, max_triangles))
    if len(tri) == 0:
        raise ValueError("the mesh has no triangles")
    poly = pv.PolyData(positions.astype(np.float32), _vtk_faces(tri))
    poly = poly.compute_normals(auto_orient_normals=False, consistent_normals=False, split_vertices=False)
    kwargs = {"color": "lightgray"}
    if colours is not None:
        poly.point_data["rgb"] = np.round(np.clip(colours, 0, 1) * 255).astype(np.uint8)
        kwargs = {"scalars": "rgb", "rgb": True}
    plotter = pv.Plotter(off_screen=True, window_size=size)
    try:
        plotter.set_background("white")
        plotter.add_mesh(poly, smooth_shading=True, show_scalar_bar=False, **kwargs)
        _place_camera(plotter, positions, view)
        # serialised without a render (the first off-screen render of a process, an OpenGL
        # context and its shaders, cost 0.12 CPU s at D415 size): only the lights that follow
        # the camera are placed as a render would place them (tests/test_report_page.py)
        plotter.renderer.UpdateLightsGeometryToFollowCamera()
        window = plotter.render_window
        camera = plotter.renderer.GetActiveCamera()
        initialize_serializers()
        context = SynchronizationContext()
        context.set_ignore_last_dependencies(True)
        scene = serialize(None, window, reference_id(window), context, 1)
        scene["extra"] = {"vtkRefId": reference_id(window), "centerOfRotation": camera.GetFocalPoint(),
                          "camera": reference_id(camera)}
        hashes = {e["hash"]: {**e, "content": context.get_cached_data_array(e["hash"], False)}
                  for e in extract_array_hash(scene)}
    finally:
        plotter.close()
    import zipfile

    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as z:
        z.writestr("index.json", json.dumps({"hashes": hashes, "scene": scene}), compress_type=zipfile.ZIP_DEFLATED)
    text = io.StringIO()
    write_html(archive.getvalue(), text)
    return _offline(text.getvalue()), total, len(tri)


def show_mesh(mesh, *, interactive: bool | None = None, view: str = "camera", size: tuple[int, int] = (720, 480)):
    """A Jupyter display object of ``mesh``: the turnable 3D view (vtk.js, inline, as in report.html)
    when ``interactive``, else a static PNG rendered off-screen (:func:`o3d_mvps.viz.render_preview`).

    ``interactive`` None: static where no browser will look at it (the environment variable CI is
    set, as when the notebooks are executed by the tests), interactive otherwise.
    """
    from IPython.display import HTML, Image

    if interactive is None:
        interactive = not os.environ.get("CI")
    if interactive:
        viewer, _, _ = mesh_viewer_html(mesh, view=view, size=size)
        # in a div: IPython warns about HTML that is a bare iframe
        return HTML(f'<div><iframe title="3D view" style="width: {size[0]}px; height: {size[1]}px; border: 1px solid '
                    f'#ccc" srcdoc="{html.escape(viewer, quote=True)}"></iframe></div>')
    import tempfile

    from .viz import render_preview

    with tempfile.TemporaryDirectory() as folder:
        path = render_preview(mesh, Path(folder) / "mesh.png", size=size, view=view)
        return Image(data=path.read_bytes(), format="png")


#: vtk.js adds favicon links to kitware.github.io to the page's head: point them at an inline icon.
_FAVICON_URL = re.compile(r"https://kitware\.github\.io/vtk-js/icon/favicon-\$\{\w+\}x\$\{\w+\}\.png")
_BLANK_PNG = ("data:image/png;base64,"
              "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAQAAAC1HAwCAAAAC0lEQVR42mNkYAAAAAYAAjCB0C8AAAAASUVORK5CYII=")


def _offline(viewer: str) -> str:
    """The viewer page with its one network reference (favicons) replaced by an inline image."""
    return _FAVICON_URL.sub(_BLANK_PNG, viewer)
