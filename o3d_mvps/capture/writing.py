"""Write a Capture as a capture folder (layout in ``o3d_mvps.capture``), all or nothing."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..colour import linear_to_srgb
from ..errors import CaptureError
from ..fileio import atomic_folder, json_text, write_intrinsic_json
from ..fileio import (
    write_png as _write_png,  # module-level name: tests patch it to simulate a failing disk
)
from .layout import (
    CAPTURE_JSON,
    COLOR_DIR,
    DEPTH_DIR,
    DEPTH_INTRINSIC_JSON,
    GROUNDTRUTH_DIR,
    GT_ARRAYS,
    INTRINSIC_JSON,
    MASK_DIR,
)
from .types import Capture
from .validation import pixels, validate_capture


def write_capture(capture: Capture, path, overwrite: bool = False) -> None:
    """Write a capture folder (layout in the ``o3d_mvps.capture`` docstring), all or nothing.

    Everything is written into a temporary sibling folder which is then renamed into place,
    so a failure never leaves a half-written capture; with ``overwrite=True`` the old capture's
    entries (an earlier mask/ and groundtruth/ too) are moved aside and deleted only once the
    new ones are in place; other files in the folder stay. Colour is encoded
    as ``capture.color_encoding`` at ``metadata["color_bit_depth"]`` bits (8 by default);
    depth as uint16 round(metres * depth_scale).

    Parameters
    ----------
    capture : Capture
    path : str or os.PathLike
        The capture folder to create.
    overwrite : bool
        Replace an existing non-empty folder.

    Raises
    ------
    CaptureError
        The capture is invalid (see ``validate_capture``) or cannot be encoded.
    OutputExistsError
        ``path`` is a file, or a non-empty folder and ``overwrite`` is False.
    """
    validate_capture(capture)
    bits = capture.metadata.get("color_bit_depth", 8)
    _capture_json(capture.metadata, "capture.metadata")
    max_depth = max(float(np.max(pixels(d))) for d in capture.depth)
    if max_depth * capture.depth_scale > np.iinfo(np.uint16).max:
        raise CaptureError(
            f"depth up to {max_depth:.1f} m does not fit a uint16 PNG at depth_scale {capture.depth_scale:g}; "
            "lower depth_scale or zero the far depth"
        )

    with atomic_folder(path, overwrite=overwrite, what="capture folder", layout=(MASK_DIR, GROUNDTRUTH_DIR)) as tmp:
        _write_folder(capture, tmp, bits)


def _encode_color(linear: np.ndarray, encoding: str, bits: int) -> np.ndarray:
    """(H, W, 3) linear RGB in [0, 1] -> stored uint8/uint16 RGB."""
    value = linear_to_srgb(linear) if encoding == "srgb" else linear
    top = 2**bits - 1
    return np.rint(value.astype(np.float64) * top).astype(np.uint8 if bits == 8 else np.uint16)


def _write_folder(capture: Capture, root: Path, bits: int) -> None:
    """Write every file of the capture into the (empty) folder root."""
    names = [f"{i:06d}.png" for i in range(capture.n_frames)]
    for sub in (COLOR_DIR, DEPTH_DIR):
        (root / sub).mkdir()
    for i, name in enumerate(names):
        codes = capture.color_codes(i)
        if codes is None or codes.dtype.itemsize * 8 != bits:  # floats, or codes of another bit depth
            codes = _encode_color(capture.color_array(i), capture.color_encoding, bits)
        _write_png(root / COLOR_DIR / name, codes)  # codes read from files: written as they were
        depth = np.rint(capture.depth_array(i).astype(np.float64) * capture.depth_scale).astype(np.uint16)
        _write_png(root / DEPTH_DIR / name, depth)
    if capture.masks is not None and any(m is not None for m in capture.masks):
        (root / MASK_DIR).mkdir()
        for i, name in enumerate(names):
            if capture.masks[i] is not None:
                _write_png(root / MASK_DIR / name, capture.mask_array(i).astype(np.uint8) * np.uint8(255))
    write_intrinsic_json(root / INTRINSIC_JSON, capture.color_K(), capture.color_size)
    write_intrinsic_json(root / DEPTH_INTRINSIC_JSON, capture.depth_K(), capture.depth_size)
    settings = {
        "depth_scale": float(capture.depth_scale),
        "depth_trunc": float(capture.depth_trunc),
        "color_encoding": capture.color_encoding,
        "sensor": capture.sensor,
        "frames": capture.n_frames,
        **({"light": capture.light} if capture.light is not None else {}),
        **({"camera": capture.camera} if capture.camera is not None else {}),
        "metadata": {**capture.metadata, "color_bit_depth": bits},
    }
    (root / CAPTURE_JSON).write_text(_capture_json(settings, "capture settings"))
    if capture.groundtruth is not None:
        gt = capture.groundtruth
        (root / GROUNDTRUTH_DIR).mkdir()
        for name in GT_ARRAYS:
            np.save(root / GROUNDTRUTH_DIR / f"{name}.npy", np.asarray(getattr(gt, name)), allow_pickle=False)
        (root / GROUNDTRUTH_DIR / "light.json").write_text(_capture_json(gt.light, "ground truth light"))


def _capture_json(data, what: str) -> str:
    return json_text(data, what, error=CaptureError)
