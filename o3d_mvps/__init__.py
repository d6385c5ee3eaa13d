"""o3d_mvps: depth super-resolution and multi-view uncalibrated photometric stereo for Open3D.

An LED attached to an RGB-D camera lights the object differently in every frame; from ~20
frames ``refine`` jointly estimates camera poses, depth at colour resolution, RGB albedo and
per-frame lighting (Sang, Haefner, Cremers, WACV 2020).
"""

from .capture import Capture, GroundTruth, read_capture, write_capture
from .errors import (
    CaptureError,
    ExportError,
    MVPSError,
    OdometryError,
    OutputExistsError,
    RecordingError,
)
from .integration import refine_rgbd
from .refinement import Refinement, read_refinement
from .solver.driver import refine
from .solver.options import RefineOptions

__version__ = "0.1.0"

__all__ = [
    "Capture",
    "GroundTruth",
    "read_capture",
    "write_capture",
    "Refinement",
    "read_refinement",
    "refine",
    "refine_rgbd",
    "RefineOptions",
    "MVPSError",
    "CaptureError",
    "OutputExistsError",
    "OdometryError",
    "RecordingError",
    "ExportError",
]
