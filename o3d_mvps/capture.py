"""The Capture type: n RGB-D frames of an LED-lit object, and the capture folder format.

Folder layout (DESIGN section 3, the same names as Open3D's reconstruction system)::

    capture/
      color/000000.png ...     colour frames (8- or 16-bit), high resolution H x W
      depth/000000.png ...     uint16 depth, low resolution H/SF x W/SF, registered to colour
      mask/000000.png ...      optional object masks (colour resolution)
      intrinsic.json           colour camera, Open3D PinholeCameraIntrinsic JSON
      depth_intrinsic.json     optional; default: colour intrinsics scaled by 1/SF
      capture.json             depth_scale, depth_trunc, color_encoding (srgb|linear), sensor,
                               frames, metadata; optional (defaults 1000, 3.0 m, srgb)
      groundtruth/             synthetic captures only: depth.npy, normals.npy, albedo.npy,
                               poses.npy, mesh_to_reference.npy, light.json

``read_capture`` and ``write_capture`` convert between this folder and a ``Capture``;
``validate_capture`` checks a ``Capture`` and raises ``CaptureError`` naming problem and fix.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from .colour import linear_to_srgb, srgb_to_linear
from .errors import CaptureError
from .fileio import atomic_folder, json_text, write_intrinsic_json
from .fileio import (
    write_png as _write_png,  # module-level name: tests patch it to simulate a failing disk
)
from .model.camera import as_intrinsic_matrix, scale_intrinsics


@dataclass
class GroundTruth:
    """Ground truth of a synthetic capture (reference frame 0, colour resolution).

    depth: (H, W) float32 metres, 0 off the object. normals: (H, W, 3) float32, reference
    camera frame, unit, pointing to the camera, 0 off the object. albedo: (H, W, 3) float32
    linear RGB. poses: (n, 4, 4) float64 mapping reference-camera coordinates to frame-i
    coordinates. light: JSON-serialisable light parameters (``"model"``: ``"led"`` or
    ``"directional"``; the directional model stores ``"sh"``: n x 4 first-order SH vectors in
    reference coordinates). mesh_to_reference: (4, 4) float64 mesh -> reference camera.
    """

    depth: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    poses: np.ndarray
    light: dict
    mesh_to_reference: np.ndarray


@dataclass
class Capture:
    """n RGB-D frames; frame 0 is the reference.

    color: n images (H, W, 3) float32 linear RGB in [0, 1].
    depth: n images (h, w, 1) float32 metres, 0 = no measurement; h = H/SF, w = W/SF.
    color_intrinsic, depth_intrinsic: (3, 3) float64 tensors (pixels).
    masks: None, or n entries each None or an (H, W, 1) uint8 image (nonzero = object).
    depth_scale: depth PNG units per metre (1000 = mm). depth_trunc: metres.
    color_encoding: how colour PNGs are encoded on disk ("srgb" or "linear").
    """

    color: list
    depth: list
    color_intrinsic: o3d.core.Tensor
    depth_intrinsic: o3d.core.Tensor
    masks: list | None = None
    depth_scale: float = 1000.0
    depth_trunc: float = 3.0
    color_encoding: str = "srgb"
    sensor: str = "unknown"
    groundtruth: GroundTruth | None = None
    metadata: dict = field(default_factory=dict)

    # --- sizes -------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return len(self.color)

    @property
    def color_size(self) -> tuple[int, int]:
        """(H, W) of the colour frames."""
        return (self.color[0].rows, self.color[0].columns)

    @property
    def depth_size(self) -> tuple[int, int]:
        """(h, w) of the depth frames."""
        return (self.depth[0].rows, self.depth[0].columns)

    @property
    def scale_factor(self) -> int:
        """Integer super-resolution factor SF = H / h."""
        return int(round(self.color_size[0] / self.depth_size[0]))

    # --- numpy views (what the solver works on) ----------------------------------------
    def color_array(self, i: int) -> np.ndarray:
        """Frame i colour, (H, W, 3) float32 linear RGB."""
        return np.asarray(self.color[i].as_tensor().numpy(), dtype=np.float32).reshape(*self.color_size, 3)

    def depth_array(self, i: int) -> np.ndarray:
        """Frame i depth, (h, w) float32 metres, 0 = missing."""
        return np.asarray(self.depth[i].as_tensor().numpy(), dtype=np.float32).reshape(self.depth_size)

    def mask_array(self, i: int) -> np.ndarray | None:
        """Frame i object mask, (H, W) bool, or None when the frame has none."""
        if self.masks is None or self.masks[i] is None:
            return None
        return np.asarray(self.masks[i].as_tensor().numpy()).reshape(self.color_size) > 0

    def color_K(self) -> np.ndarray:
        """Colour intrinsics as a (3, 3) float64 numpy array."""
        return as_intrinsic_matrix(self.color_intrinsic)

    def depth_K(self) -> np.ndarray:
        """Depth intrinsics as a (3, 3) float64 numpy array."""
        return as_intrinsic_matrix(self.depth_intrinsic)

    def select(self, frames) -> "Capture":
        """A capture of the listed frame indices; the first one becomes the reference.

        Ground truth is kept only when the reference stays frame 0 (poses are re-indexed).
        """
        frames = [int(i) for i in frames]
        pick = lambda seq: None if seq is None else [seq[i] for i in frames]  # noqa: E731
        gt = self.groundtruth
        if gt is not None:
            gt = replace(gt, poses=gt.poses[frames]) if frames[0] == 0 else None
        return replace(self, color=pick(self.color), depth=pick(self.depth), masks=pick(self.masks), groundtruth=gt)


def default_depth_intrinsic(color_K: np.ndarray, scale_factor: int) -> np.ndarray:
    """Depth intrinsics of a depth grid that area-averages SF x SF colour pixels."""
    return scale_intrinsics(color_K, 1.0 / scale_factor)


def image_from_array(array: np.ndarray) -> o3d.t.geometry.Image:
    """An o3d.t.geometry.Image holding a contiguous copy of an (H, W) or (H, W, C) array."""
    return o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(array)))



# --- folder format -------------------------------------------------------------------------

COLOR_DIR, DEPTH_DIR, MASK_DIR, GROUNDTRUTH_DIR = "color", "depth", "mask", "groundtruth"
INTRINSIC_JSON, DEPTH_INTRINSIC_JSON, CAPTURE_JSON = "intrinsic.json", "depth_intrinsic.json", "capture.json"
COLOR_ENCODINGS = ("srgb", "linear")
DEPTH_RANGE_M = (0.05, 20.0)  # plausible median depth; outside it the unit is almost surely wrong
_COLOR_SUFFIXES = (".png", ".jpg", ".jpeg")  # .jpg: Open3D's reconstruction system writes those
_GT_ARRAYS = ("depth", "normals", "albedo", "poses", "mesh_to_reference")  # each <name>.npy
_DEFAULT_SETTINGS = {"depth_scale": 1000.0, "depth_trunc": 3.0, "color_encoding": "srgb", "sensor": "unknown"}


def validate_capture(capture: Capture, frame_names: list[str] | None = None) -> None:
    """Check that a capture is complete and consistent; raise CaptureError naming problem and fix.

    Checks: at least one frame; as many depth as colour frames; colour (H, W, 3) finite in
    [0, 1] and depth (h, w[, 1]) finite and >= 0, each the same size in every frame; an integer
    SF = H/h = W/w >= 1; a plausible median depth (0.05-20 m, else the unit is wrong); masks
    (H, W[, 1]) with at least one object pixel; finite intrinsics; the settings fields; the
    ground-truth shapes.

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
    depth_size = _check_frames(capture.depth, "depth", (None, 1), label, (0.0, None))
    _check_scale_factor(color_size, depth_size)
    _check_depth_unit(capture.depth, label)
    _check_masks(capture.masks, n, color_size, label)
    for name, K in (("colour", capture.color_intrinsic), ("depth", capture.depth_intrinsic)):
        _intrinsic_matrix(K, f"the {name} intrinsics")
    _check_settings(capture.depth_scale, capture.depth_trunc, capture.color_encoding,
                    capture.metadata.get("color_bit_depth", 8))
    if capture.groundtruth is not None:
        _check_groundtruth(capture.groundtruth, n, color_size)


def read_capture(path) -> Capture:
    """Read a capture folder (layout in the module docstring).

    Colour PNGs (8- or 16-bit; .jpg also read) become float32 linear RGB in [0, 1] (sRGB ones
    are linearised); their bit depth goes to ``metadata["color_bit_depth"]``. Depth PNGs
    (uint16) become float32 metres (value / depth_scale; 0 = missing). Frames are paired by
    file name in sorted order. A missing ``capture.json`` means the defaults (depth_scale 1000,
    depth_trunc 3 m, sRGB colour); a missing ``depth_intrinsic.json`` means
    ``default_depth_intrinsic``. Depth beyond depth_trunc is kept (depth_trunc is passed on
    for fusion). A missing mask/ folder gives ``masks=None``.

    Parameters
    ----------
    path : str or os.PathLike
        The capture folder.

    Returns
    -------
    Capture

    Raises
    ------
    CaptureError
        The folder, a file or the frames are missing, unreadable or inconsistent.
    """
    root = Path(path).expanduser()
    if not root.exists():
        raise CaptureError(f"capture folder {root} does not exist; check the path")
    if not root.is_dir():
        raise CaptureError(f"{root} is a file, not a capture folder; give the folder holding color/ and depth/")
    settings = _read_settings(root / CAPTURE_JSON)
    color_K, color_K_size = read_intrinsic_json(root / INTRINSIC_JSON)
    depth_K, depth_K_size = None, None
    if (root / DEPTH_INTRINSIC_JSON).exists():
        depth_K, depth_K_size = read_intrinsic_json(root / DEPTH_INTRINSIC_JSON)

    color_files, depth_files = _paired_frame_files(root, settings["frames"])
    names = list(color_files)

    color, bit_depths = [], set()
    for file in color_files.values():
        array, bits = _decode_color(_read_image(file), settings["color_encoding"], file)
        color.append(image_from_array(array))
        bit_depths.add(bits)
    if len(bit_depths) > 1:
        raise CaptureError(f"{root / COLOR_DIR} mixes 8- and 16-bit frames; save every colour frame at one bit depth")
    depth = [image_from_array(_decode_depth(_read_image(f), settings["depth_scale"], f)) for f in depth_files.values()]
    capture = Capture(
        color=color,
        depth=depth,
        color_intrinsic=o3d.core.Tensor(color_K),
        depth_intrinsic=o3d.core.Tensor(color_K if depth_K is None else depth_K),  # default set once SF is known
        masks=_read_masks(root / MASK_DIR, names),
        depth_scale=settings["depth_scale"],
        depth_trunc=settings["depth_trunc"],
        color_encoding=settings["color_encoding"],
        sensor=settings["sensor"],
        groundtruth=_read_groundtruth(root / GROUNDTRUTH_DIR) if (root / GROUNDTRUTH_DIR).is_dir() else None,
        metadata={**settings["metadata"], "color_bit_depth": bit_depths.pop()},
    )
    validate_capture(capture, names)
    _check_intrinsic_size(root / INTRINSIC_JSON, color_K_size, capture.color_size, COLOR_DIR)
    if depth_K is None:
        capture.depth_intrinsic = o3d.core.Tensor(default_depth_intrinsic(color_K, capture.scale_factor))
    else:
        _check_intrinsic_size(root / DEPTH_INTRINSIC_JSON, depth_K_size, capture.depth_size, DEPTH_DIR)
    return capture


def write_capture(capture: Capture, path, overwrite: bool = False) -> None:
    """Write a capture folder (layout in the module docstring), all or nothing.

    Everything is written into a temporary sibling folder which is then renamed into place,
    so a failure never leaves a half-written capture; with ``overwrite=True`` the old capture's
    entries are moved aside and deleted only once the new ones are in place (other files stay). Colour is encoded
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
    max_depth = max(float(np.max(_pixels(d))) for d in capture.depth)
    if max_depth * capture.depth_scale > np.iinfo(np.uint16).max:
        raise CaptureError(
            f"depth up to {max_depth:.1f} m does not fit a uint16 PNG at depth_scale {capture.depth_scale:g}; "
            "lower depth_scale or zero the far depth"
        )

    with atomic_folder(path, overwrite=overwrite, what="capture folder", layout=(MASK_DIR, GROUNDTRUTH_DIR)) as tmp:
        _write_folder(capture, tmp, bits)


# --- validation helpers --------------------------------------------------------------------


def _pixels(image) -> np.ndarray:
    """The numpy array of an o3d.t.geometry.Image (or an array), (rows, cols[, C])."""
    return np.asarray(image.as_tensor().numpy()) if hasattr(image, "as_tensor") else np.asarray(image)


def _size(shape) -> str:
    """'WxH' text of an (H, W, ...) shape."""
    return f"{shape[1]}x{shape[0]}"


def _check_frames(frames, kind, channels, label, value_range) -> tuple[int, int]:
    """Check the frames share one shape and hold finite values in value_range; return (rows, cols).

    channels: allowed channel counts, None allowing a 2-D (rows, cols) array.
    value_range: (low, high), either None for unbounded.
    """
    first = None
    for i, frame in enumerate(frames):
        a = _pixels(frame)
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
                f"{kind} {label(i)} is {_size(a.shape)} but {label(0)} is {_size(first)} (WxH); "
                f"every {kind} frame must have the same size, resample or drop the odd one"
            )
        if not np.all(np.isfinite(a)):
            raise CaptureError(f"{kind} {label(i)} contains NaN or inf; replace them (0 = missing for depth)")
        lo, hi = value_range
        if a.size and ((lo is not None and a.min() < lo) or (hi is not None and a.max() > hi)):
            want = "linear RGB in [0, 1] (divide 8-bit values by 255)" if kind == "colour" else "metres >= 0"
            raise CaptureError(
                f"{kind} {label(i)} has values in [{a.min():g}, {a.max():g}]; {kind} must be {want}"
            )
    return first


def _check_scale_factor(color_size, depth_size) -> None:
    (H, W), (h, w) = color_size, depth_size
    if h == 0 or w == 0 or H % h or W % w or H // h != W // w:
        raise CaptureError(
            f"depth is {_size(depth_size)} but colour is {_size(color_size)} (WxH): colour must be an integer "
            "multiple SF >= 1 of depth in both directions (W = SF*w, H = SF*h); crop or resample one of them"
        )


def _check_depth_unit(depth, label) -> None:
    """Each frame's median valid depth must lie in DEPTH_RANGE_M."""
    lo, hi = DEPTH_RANGE_M
    any_valid = False
    for i, frame in enumerate(depth):
        d = _pixels(frame)
        valid = d[d > 0]
        if valid.size == 0:
            continue
        any_valid = True
        median = float(np.median(valid))
        if not lo <= median <= hi:
            raise CaptureError(
                f"depth {label(i)}: median depth {median:.4g} m is outside {lo:g}-{hi:g} m, so the unit looks wrong: "
                "depth_scale in capture.json is probably wrong (1000 for millimetres), or in-memory depth "
                "is not in metres"
            )
    if not any_valid:
        raise CaptureError("no frame has any valid (nonzero) depth; check the depth frames and depth_scale")


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
        m = _pixels(mask)
        if m.ndim == 3 and m.shape[2] == 1:
            m = m[..., 0]
        if m.shape != tuple(color_size):
            raise CaptureError(
                f"mask of {label(i)} has shape {m.shape} but colour is {_size(color_size)} (WxH); "
                "masks must be single-channel at colour resolution"
            )
        if not np.any(m):
            raise CaptureError(
                f"mask of {label(i)} has no object pixel; remove that mask (None / delete the file) or redraw it"
            )


def _check_settings(depth_scale, depth_trunc, color_encoding, color_bit_depth, where: str = "") -> None:
    """Check the capture.json fields; ``where`` prefixes the messages (e.g. the file name)."""
    if not (np.isfinite(depth_scale) and depth_scale > 0):
        raise CaptureError(f"{where}depth_scale {depth_scale!r} must be a positive number (1000 for millimetres)")
    if not (np.isfinite(depth_trunc) and depth_trunc > 0):
        raise CaptureError(f"{where}depth_trunc {depth_trunc!r} must be a positive number of metres (e.g. 3.0)")
    if color_encoding not in COLOR_ENCODINGS:
        raise CaptureError(f"{where}color_encoding {color_encoding!r} is unknown; use one of {COLOR_ENCODINGS}")
    if color_bit_depth not in (8, 16):
        raise CaptureError(f"{where}color_bit_depth {color_bit_depth!r} is unsupported; use 8 or 16")


def _check_groundtruth(gt: GroundTruth, n, color_size) -> None:
    H, W = color_size
    expected = {
        "depth": (H, W), "normals": (H, W, 3), "albedo": (H, W, 3), "poses": (n, 4, 4), "mesh_to_reference": (4, 4)
    }
    for name, shape in expected.items():
        actual = np.shape(getattr(gt, name))
        if actual != shape:
            raise CaptureError(f"ground truth {name} has shape {actual}, expected {shape}; regenerate the ground truth")
    if not isinstance(gt.light, dict):
        raise CaptureError(f"ground truth light must be a dict, got {type(gt.light).__name__}")


def _intrinsic_matrix(K, what: str) -> np.ndarray:
    """as_intrinsic_matrix, raising CaptureError that names ``what``."""
    try:
        return as_intrinsic_matrix(K)
    except ValueError as e:
        raise CaptureError(f"{what}: {e}") from None


# --- reading helpers -----------------------------------------------------------------------


def _frame_files(folder: Path, suffixes) -> dict[str, Path]:
    """Frame files of a folder by stem, in sorted name order; CaptureError if none."""
    if not folder.is_dir():
        raise CaptureError(
            f"{folder} is missing; a capture folder needs {COLOR_DIR}/ and {DEPTH_DIR}/ with one PNG per frame"
        )
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes)
    if not files:
        raise CaptureError(f"{folder} holds no frames; add {'/'.join(suffixes)} images named like 000000.png")
    by_stem = {p.stem: p for p in files}
    if len(by_stem) != len(files):
        raise CaptureError(f"{folder} has two frames with the same name but different suffixes; keep one of each")
    return by_stem


def _paired_frame_files(root: Path, expected: int | None) -> tuple[dict[str, Path], dict[str, Path]]:
    """Colour and depth frame files by name; CaptureError unless they pair up (and number ``expected``)."""
    color_files = _frame_files(root / COLOR_DIR, _COLOR_SUFFIXES)
    depth_files = _frame_files(root / DEPTH_DIR, (".png",))
    if len(color_files) != len(depth_files):
        raise CaptureError(
            f"{root}: {COLOR_DIR}/ has {len(color_files)} frames but {DEPTH_DIR}/ has {len(depth_files)}; "
            "every colour frame needs a depth frame with the same file name"
        )
    if list(color_files) != list(depth_files):
        only = sorted(set(color_files) ^ set(depth_files))[0]
        raise CaptureError(
            f"{root}: frame {only!r} is in only one of {COLOR_DIR}/ and {DEPTH_DIR}/; "
            "colour and depth frames are paired by file name, rename or remove it"
        )
    if expected is not None and expected != len(color_files):
        raise CaptureError(
            f"{root / CAPTURE_JSON} says {expected} frames but {COLOR_DIR}/ has {len(color_files)}; "
            "restore the missing frames or correct \"frames\""
        )
    return color_files, depth_files


def _read_image(path: Path) -> np.ndarray:
    """An image file as stored (uint8/uint16; RGB(A) order for colour); CaptureError if unreadable."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CaptureError(f"cannot read image {path} (corrupt or not an image); re-export or remove that frame")
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB if image.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
    return image


def _decode_color(raw: np.ndarray, encoding: str, path: Path) -> tuple[np.ndarray, int]:
    """Stored colour -> ((H, W, 3) float32 linear RGB in [0, 1], bit depth)."""
    if raw.dtype not in (np.uint8, np.uint16) or raw.ndim != 3:
        raise CaptureError(
            f"colour frame {path} is {raw.dtype} with shape {raw.shape}; save colour as 8- or 16-bit RGB PNG"
        )
    bits = 8 * raw.dtype.itemsize
    value = raw[..., :3] / float(2**bits - 1)  # float64, so k / 255 is exactly what callers compute
    return (srgb_to_linear(value) if encoding == "srgb" else value.astype(np.float32)), bits


def _decode_depth(raw: np.ndarray, depth_scale: float, path: Path) -> np.ndarray:
    """Stored uint16 depth -> (h, w, 1) float32 metres."""
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise CaptureError(
            f"depth frame {path} is {raw.dtype} with shape {raw.shape}; depth must be a single-channel "
            "16-bit PNG (units 1/depth_scale m)"
        )
    return (raw.astype(np.float64) / depth_scale).astype(np.float32)[..., None]


def _read_masks(folder: Path, names: list[str]) -> list | None:
    """Masks matched to frame names: None if there is no mask folder, else one entry per frame."""
    if not folder.is_dir():
        return None
    files = {p.stem: p for p in sorted(folder.iterdir()) if p.is_file() and p.suffix.lower() == ".png"}
    if not files:
        return None
    stray = sorted(set(files) - set(names))
    if stray:
        raise CaptureError(
            f"mask {files[stray[0]]} has no colour frame of the same name; rename it to match a frame or remove it"
        )
    masks = []
    for name in names:
        if name not in files:
            masks.append(None)
            continue
        m = _read_image(files[name])
        m = np.any(m != 0, axis=-1) if m.ndim == 3 else m != 0
        masks.append(image_from_array((m * np.uint8(255))[..., None]))
    return masks


def load_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CaptureError(f"cannot read {path} ({e}); fix or rewrite the JSON file") from None


def _read_settings(path: Path) -> dict:
    """capture.json with defaults filled in; 'frames' is None when absent."""
    settings = {**_DEFAULT_SETTINGS, "frames": None, "metadata": {}}
    if not path.exists():
        return settings
    data = load_json(path)
    if not isinstance(data, dict):
        raise CaptureError(f"{path} must hold a JSON object like {{\"depth_scale\": 1000, ...}}")
    settings.update({k: data[k] for k in settings if k in data})
    try:
        settings["depth_scale"] = float(settings["depth_scale"])
        settings["depth_trunc"] = float(settings["depth_trunc"])
        settings["frames"] = None if settings["frames"] is None else int(settings["frames"])
    except (TypeError, ValueError):
        raise CaptureError(f"{path}: depth_scale, depth_trunc and frames must be numbers; fix the file") from None
    _check_settings(settings["depth_scale"], settings["depth_trunc"], settings["color_encoding"], 8, f"{path}: ")
    if not isinstance(settings["metadata"], dict):
        raise CaptureError(f"{path}: metadata must be a JSON object")
    settings["sensor"] = str(settings["sensor"])
    return settings


def read_intrinsic_json(path: Path) -> tuple[np.ndarray, tuple[int, int]]:
    """Open3D PinholeCameraIntrinsic JSON -> ((3, 3) float64 K, image size (H, W))."""
    if not path.exists():
        raise CaptureError(
            f"{path} is missing; write the camera intrinsics as Open3D PinholeCameraIntrinsic JSON "
            "(o3d.io.write_pinhole_camera_intrinsic)"
        )
    data = load_json(path)
    try:
        size = (int(data["height"]), int(data["width"]))
        K = np.asarray(data["intrinsic_matrix"], dtype=np.float64).reshape(3, 3).T  # stored column-major
    except (KeyError, TypeError, ValueError):
        raise CaptureError(
            f"{path} is not an Open3D PinholeCameraIntrinsic JSON; it needs \"width\", \"height\" and "
            "\"intrinsic_matrix\" (9 numbers, column-major): rewrite it with o3d.io.write_pinhole_camera_intrinsic"
        ) from None
    return _intrinsic_matrix(K, str(path)), size


def _check_intrinsic_size(path: Path, size, image_size, images: str) -> None:
    if tuple(size) != tuple(image_size):
        raise CaptureError(
            f"{path} is for {_size(size)} images but {images}/ frames are {_size(image_size)} (WxH); "
            "use the intrinsics of the camera mode the frames were recorded in"
        )


def _read_groundtruth(folder: Path) -> GroundTruth:
    arrays = {}
    for name in _GT_ARRAYS:
        file = folder / f"{name}.npy"
        try:
            arrays[name] = np.load(file, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise CaptureError(f"cannot read ground truth {file} ({e}); regenerate the synthetic capture") from None
    if not (folder / "light.json").exists():
        raise CaptureError(f"ground truth {folder / 'light.json'} is missing; regenerate the synthetic capture")
    return GroundTruth(light=load_json(folder / "light.json"), **arrays)


# --- writing helpers -----------------------------------------------------------------------


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
        _write_png(root / COLOR_DIR / name, _encode_color(capture.color_array(i), capture.color_encoding, bits))
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
        "metadata": {**capture.metadata, "color_bit_depth": bits},
    }
    (root / CAPTURE_JSON).write_text(_capture_json(settings, "capture settings"))
    if capture.groundtruth is not None:
        gt = capture.groundtruth
        (root / GROUNDTRUTH_DIR).mkdir()
        for name in _GT_ARRAYS:
            np.save(root / GROUNDTRUTH_DIR / f"{name}.npy", np.asarray(getattr(gt, name)), allow_pickle=False)
        (root / GROUNDTRUTH_DIR / "light.json").write_text(_capture_json(gt.light, "ground truth light"))




def _capture_json(data, what: str) -> str:
    return json_text(data, what, error=CaptureError)
