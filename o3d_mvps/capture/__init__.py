"""Captures: n RGB-D frames of one object (frame 0 the reference) and the capture folder format.

Folder layout (the same names as Open3D's reconstruction system; docs/capture-guide.md)::

    capture/
      color/000000.png ...     colour frames (8- or 16-bit PNG, or JPEG), high resolution H x W
      depth/000000.png ...     uint16 depth, low resolution H/SF x W/SF, registered to colour
      mask/000000.png ...      optional object masks (colour resolution)
      intrinsic.json           colour camera, Open3D PinholeCameraIntrinsic JSON
      depth_intrinsic.json     optional; default: colour intrinsics scaled by 1/SF
      capture.json             depth_scale, depth_trunc, color_encoding (srgb|linear), sensor,
                               frames, light (led|room: picks refine's light model),
                               camera (static|moving: a fixed camera needs no registration),
                               metadata; optional (defaults 1000, 3.0 m, srgb)
      poses.{json,log,txt,npy} optional initial poses from another tool (see .poses)
      groundtruth/             synthetic captures only: depth.npy, normals.npy, albedo.npy,
                               poses.npy, mesh_to_reference.npy, light.json

Modules: :mod:`.types` (Capture, GroundTruth and the scale-factor rule
``integer_scale_factor``), :mod:`.reading` (``read_capture``), :mod:`.writing` (``write_capture``),
:mod:`.validation` (``validate_capture``), :mod:`.poses` (pose files of other tools),
:mod:`.static` (``camera_setting``: static-camera captures, declared or detected).
"""

from .layout import (
    CAPTURE_JSON,
    COLOR_DIR,
    DEPTH_DIR,
    DEPTH_INTRINSIC_JSON,
    DEPTH_RANGE_M,
    GROUNDTRUTH_DIR,
    INTRINSIC_JSON,
    MASK_DIR,
)
from .poses import read_capture_poses, read_poses, relative_to_reference
from .reading import load_json, read_capture, read_intrinsic_json
from .static import CameraSetting, camera_setting, frame_white_balance
from .types import Capture, GroundTruth, default_depth_intrinsic, image_from_array, integer_scale_factor, to_host
from .validation import validate_capture
from .writing import write_capture

__all__ = [
    "Capture", "GroundTruth", "default_depth_intrinsic", "image_from_array", "to_host", "read_capture", "write_capture",
    "validate_capture", "integer_scale_factor", "read_capture_poses", "read_poses", "relative_to_reference",
    "load_json", "read_intrinsic_json", "CAPTURE_JSON", "COLOR_DIR", "DEPTH_DIR", "DEPTH_INTRINSIC_JSON",
    "DEPTH_RANGE_M", "CameraSetting", "camera_setting", "frame_white_balance", "GROUNDTRUTH_DIR", "INTRINSIC_JSON", "MASK_DIR",
]
