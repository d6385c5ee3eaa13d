"""o3d_mvps: depth super-resolution and multi-view uncalibrated photometric stereo for Open3D.

An LED attached to an RGB-D camera lights the object differently in every frame; from ~20
frames ``refine`` jointly estimates camera poses, depth at colour resolution, RGB albedo and
per-frame lighting (Sang, Haefner, Cremers, WACV 2020).

Names and submodules load on first use (module ``__getattr__``): ``import o3d_mvps`` is quick,
``o3d_mvps.synthetic.render_capture`` works without importing the submodule first, and the
numerical core (``o3d_mvps.model``) imports without Open3D.
"""

from __future__ import annotations

import importlib

from .lazy_imports import defer_open3d_plotly

defer_open3d_plotly()  # before any submodule imports Open3D: plotly and Dash load only if their viewer is used

__version__ = "0.1.0"

#: Public name -> submodule that defines it.
_EXPORTS = {
    "Capture": "capture",
    "GroundTruth": "capture",
    "read_capture": "capture",
    "write_capture": "capture",
    "Refinement": "refinement",
    "read_refinement": "refinement",
    "refine": "solving",
    "solve": "solver.driver",
    "SolverInput": "solver.problem_input",
    "SolverOutput": "solver.solution",
    "read_problem": "solver.problem_input",
    "write_problem": "solver.problem_input",
    "refine_rgbd": "integration",
    "ReconstructOptions": "reconstruct",
    "RefineOptions": "solver.options",
    "ModelOptions": "solver.options",
    "ConvergenceCriteria": "solver.options",
    "StepOptions": "solver.options",
    "LightModel": "solver.options",
    "DifferenceScheme": "solver.options",
    "MVPSError": "errors",
    "CaptureError": "errors",
    "OutputExistsError": "errors",
    "OdometryError": "errors",
    "RecordingError": "errors",
    "ExportError": "errors",
    "DeviceError": "errors",
}

#: Submodules reachable as attributes (``o3d_mvps.synthetic``) without an import of their own.
_SUBMODULES = {"baselines", "capture", "cli", "colour", "datasets", "errors", "export", "fileio", "integration",
               "metrics", "model", "odometry", "realsense", "reconstruct", "refinement", "depth_to_colour", "report", "solver",
               "solving", "synthetic", "covisibility", "viz"}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(f".{name}", __name__)
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS) | _SUBMODULES)
