"""Consistency checks of a Capture: ``validate_capture`` raises CaptureError naming problem and fix."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..errors import CaptureError
from ..model.camera import as_intrinsic_matrix
from ..model.sensor import check_depth_unit
from .layout import CAPTURE_CAMERAS, CAPTURE_LIGHTS, COLOR_ENCODINGS
from .types import integer_scale_factor

if TYPE_CHECKING:
    from .types import Capture, GroundTruth


def validate_capture(capture: Capture, frame_names: list[str] | None = None) -> None:
    """Check that a capture is complete and consistent; raise CaptureError naming problem and fix.

    Checks: at least one frame; as many depth as colour frames; colour (H, W, 3) finite in
    [0, 1] (or uint8/uint16 codes, every frame of one dtype) and depth (h, w[, 1]) finite and >= 0, each the same size in every frame; an integer
    SF = H/h = W/w >= 1 (:func:`integer_scale_factor`); some depth in every frame and a
    plausible median depth (0.05-20 m, else the unit is wrong); masks (H, W[, 1]) with at least
    one object pixel; finite intrinsics; the settings fields; the ground-truth shapes.

    Parameters
    ----------
    capture : Capture
    frame_names : list of str, optional
        Name of each frame (file name without suffix), used in the messages.
    """
    n = len(capture.color)
    if n == 0:
        raise CaptureError("the capture has no frames; record or render at least one RGB-D frame")
    if len(capture.depth) != n:
        raise CaptureError(
            f"the capture has {n} colour frames but {len(capture.depth)} depth frames; "
            "give exactly one depth frame per colour frame"
        )

    def label(i: int) -> str:
        return f"frame {i}" if frame_names is None else f"frame {i} ({frame_names[i]})"

    color_size = _check_frames(capture.color, "colour", (3,), label, (0.0, 1.0))
    first_of = {}  # dtype -> the first frame holding it
    for i, frame in enumerate(capture.color):
        first_of.setdefault(str(pixels(frame).dtype), i)
    if len(first_of) > 1 and any(d in ("uint8", "uint16") for d in first_of):
        mixed = " and ".join(f"{d} (first: {label(i)})" for d, i in sorted(first_of.items()))
        raise CaptureError(f"the colour frames mix {mixed}; give every frame as codes of one bit depth "
                           "(8-bit or 16-bit image files alike) or every frame as float32 linear RGB")
    depth_size = _check_frames(capture.depth, "depth", (None, 1), label, (0.0, None))
    integer_scale_factor(color_size, depth_size)
    _check_depth_unit(capture.depth, label)
    _check_masks(capture.masks, n, color_size, label)
    for name, K in (("colour", capture.color_intrinsic), ("depth", capture.depth_intrinsic)):
        intrinsic_matrix(K, f"the {name} intrinsics")
    check_settings(capture.depth_scale, capture.depth_trunc, capture.color_encoding,
                   capture.metadata.get("color_bit_depth", 8))
    check_camera(capture.camera)
    if capture.groundtruth is not None:
        problem = groundtruth_problem(capture.groundtruth, n, color_size)
        if problem:
            raise CaptureError(f"{problem}; regenerate the ground truth")


def pixels(image) -> np.ndarray:
    """The numpy array of an o3d.t.geometry.Image (or an array), (rows, cols[, C])."""
    return np.asarray(image.as_tensor().numpy()) if hasattr(image, "as_tensor") else np.asarray(image)


def size_text(shape) -> str:
    """'WxH' text of an (H, W, ...) shape."""
    return f"{shape[1]}x{shape[0]}"


def intrinsic_matrix(K, what: str) -> np.ndarray:
    """as_intrinsic_matrix, raising CaptureError that names ``what``."""
    try:
        return as_intrinsic_matrix(K)
    except ValueError as e:
        raise CaptureError(f"{what}: {e}") from None


def check_settings(depth_scale, depth_trunc, color_encoding, color_bit_depth, where: str = "") -> None:
    """Check the capture.json fields; ``where`` prefixes the messages (e.g. the file name)."""
    if not (np.isfinite(depth_scale) and depth_scale > 0):
        raise CaptureError(f"{where}depth_scale {depth_scale!r} must be a positive number (1000 for millimetres)")
    if not (np.isfinite(depth_trunc) and depth_trunc > 0):
        raise CaptureError(f"{where}depth_trunc {depth_trunc!r} must be a positive number of metres (e.g. 3.0)")
    if color_encoding not in COLOR_ENCODINGS:
        raise CaptureError(f"{where}color_encoding {color_encoding!r} is unknown; use one of {COLOR_ENCODINGS}")
    if color_bit_depth not in (8, 16):
        raise CaptureError(f"{where}color_bit_depth {color_bit_depth!r} is unsupported; use 8 or 16")


def check_light(light, where: str = "") -> None:
    """Check a capture's ``light`` (None, or one of :data:`.layout.CAPTURE_LIGHTS`); ``where`` prefixes the message."""
    if light is not None and light not in CAPTURE_LIGHTS:
        raise CaptureError(f"{where}light must be one of {', '.join(map(repr, CAPTURE_LIGHTS))} (the LED on the camera, "
                           f"room light or a lamp moved by hand: one point light per frame), got {light!r}")


def check_camera(camera, where: str = "") -> None:
    """Check a capture's ``camera`` (None, or one of :data:`.layout.CAPTURE_CAMERAS`); ``where`` prefixes messages."""
    if camera is not None and camera not in CAPTURE_CAMERAS:
        raise CaptureError(f"{where}camera must be one of {', '.join(map(repr, CAPTURE_CAMERAS))} (a camera fixed "
                           f"while a light moves, or a camera moved around the object), got {camera!r}; or leave it "
                           "out and the depth decides")


def groundtruth_problem(gt: GroundTruth, n: int, color_size) -> str | None:
    """What is wrong with the ground truth of an n-frame capture of colour size (H, W), or None."""
    H, W = color_size
    expected = {
        "depth": (H, W), "normals": (H, W, 3), "albedo": (H, W, 3), "poses": (n, 4, 4), "mesh_to_reference": (4, 4)
    }
    for name, shape in expected.items():
        actual = np.shape(getattr(gt, name))
        if actual != shape:
            return f"ground truth {name} has shape {actual}, expected {shape}"
    if not isinstance(gt.light, dict):
        return f"ground truth light must be a dict, got {type(gt.light).__name__}"
    return None


def _check_frames(frames, kind, channels, label, value_range) -> tuple[int, int]:
    """Check the frames share one shape and hold finite values in value_range; return (rows, cols).

    channels: allowed channel counts, None allowing a 2-D (rows, cols) array.
    value_range: (low, high), either None for unbounded.
    """
    first = None
    for i, frame in enumerate(frames):
        a = pixels(frame)
        c = None if a.ndim == 2 else a.shape[-1]
        if a.ndim not in (2, 3) or c not in channels:
            raise CaptureError(
                f"{kind} {label(i)} has shape {a.shape}; {kind} frames must be (H, W"
                + (", 3) RGB" if kind == "colour" else "[, 1]) single-channel")
            )
        if first is None:
            first = a.shape[:2]
        elif a.shape[:2] != first:
            raise CaptureError(
                f"{kind} {label(i)} is {size_text(a.shape)} but {label(0)} is {size_text(first)} (WxH); "
                f"every {kind} frame must have the same size, resample or drop the odd one"
            )
        if a.dtype.kind in "ui" and kind == "colour":
            if a.dtype not in (np.uint8, np.uint16):
                raise CaptureError(f"{kind} {label(i)} is {a.dtype}; integer colour must be uint8 or uint16 codes "
                                   "(decoded by color_encoding), else float32 linear RGB in [0, 1]")
            continue  # codes as stored in files: any value is a colour
        if not np.all(np.isfinite(a)):
            raise CaptureError(f"{kind} {label(i)} contains NaN or inf; replace them (0 = missing for depth)")
        lo, hi = value_range
        if a.size and ((lo is not None and a.min() < lo) or (hi is not None and a.max() > hi)):
            want = "linear RGB in [0, 1] (divide 8-bit values by 255)" if kind == "colour" else "metres >= 0"
            raise CaptureError(
                f"{kind} {label(i)} has values in [{a.min():g}, {a.max():g}]; {kind} must be {want}"
            )
    return first


def _check_depth_unit(depth, label) -> None:
    """Every frame needs some depth, and its median valid depth must lie in DEPTH_RANGE_M."""
    for i, frame in enumerate(depth):
        d = pixels(frame)
        valid = d[d > 0]
        if valid.size == 0:
            raise CaptureError(
                f"depth {label(i)} has no measurement at all (every pixel 0): re-export that depth frame, or "
                "remove the frame (its colour and depth files, or Capture.select without it)"
            )
        check_depth_unit(valid, f"depth {label(i)}",
                         "depth_scale in capture.json is probably wrong (1000 for millimetres), or in-memory depth "
                         "is not in metres")


def _check_masks(masks, n, color_size, label) -> None:
    if masks is None:
        return
    if len(masks) != n:
        raise CaptureError(
            f"the capture has {n} frames but {len(masks)} masks; give one entry per frame (None = no mask)"
        )
    for i, mask in enumerate(masks):
        if mask is None:
            continue
        m = pixels(mask)
        if m.ndim == 3 and m.shape[2] == 1:
            m = m[..., 0]
        if m.shape != tuple(color_size):
            raise CaptureError(
                f"mask of {label(i)} has shape {m.shape} but colour is {size_text(color_size)} (WxH); "
                "masks must be single-channel at colour resolution"
            )
        if not np.any(m):
            raise CaptureError(
                f"mask of {label(i)} has no object pixel; remove that mask (None / delete the file) or redraw it"
            )
