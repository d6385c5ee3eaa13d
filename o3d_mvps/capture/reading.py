"""Read a capture folder into a Capture (layout in ``o3d_mvps.capture``), checking what real files get wrong."""

from __future__ import annotations

import json
import os
import re
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from ..errors import CaptureError
from .layout import (
    CAPTURE_JSON,
    COLOR_DIR,
    COLOR_SUFFIXES,
    DEFAULT_SETTINGS,
    DEPTH_DIR,
    DEPTH_INTRINSIC_JSON,
    DEPTH_RANGE_M,
    GROUNDTRUTH_DIR,
    GT_ARRAYS,
    INTRINSIC_JSON,
    MASK_DIR,
)
from .masks import auto_masks
from .types import Capture, GroundTruth, default_depth_intrinsic, image_from_array
from .validation import (check_camera, check_light, check_settings, groundtruth_problem, intrinsic_matrix, size_text,
                         validate_capture)

#: EXIF tag of the image orientation (1 = stored as displayed).
EXIF_ORIENTATION = 0x0112
#: Frames are decoded on at most this many threads (and the machine's core count).
READ_THREADS = 4


#: Where the object masks come from: the folder's mask/, automatic (depth), or none.
MASK_SOURCES = ("auto", "none", "folder")


def read_capture(path, mask: str | None = None, depth_range=None) -> Capture:
    """Read a capture folder (layout in the ``o3d_mvps.capture`` docstring).

    Colour PNGs (8- or 16-bit; .jpg also read) are kept as their uint8/uint16 codes, which
    :meth:`Capture.color_array` decodes to float32 linear RGB in [0, 1] (sRGB ones linearised;
    the solver decodes them where it samples them); their bit depth goes to
    ``metadata["color_bit_depth"]``. Depth PNGs
    (uint16) become float32 metres (value / depth_scale; 0 = missing). Frames are paired by
    file name in natural order (:func:`natural_key`: ``frame_2`` before ``frame_10``); files that
    are not frames (``._*``, hidden files, folders, broken links, other suffixes) are skipped with
    a warning naming them. A missing ``capture.json`` means the defaults (depth_scale 1000,
    depth_trunc 3 m, sRGB colour); a missing ``depth_intrinsic.json`` means
    ``default_depth_intrinsic``. Depth beyond depth_trunc is kept (depth_trunc is passed on
    for fusion). Masks (``mask``): ``"folder"`` reads mask/ (CaptureError when missing),
    ``"auto"`` computes them from depth (:func:`o3d_mvps.capture.masks.object_mask`: the connected
    depth region nearest the image centre within ``depth_range``, background planes cut),
    ``"none"`` gives ``masks=None``; by default mask/ when present, else ``"auto"``
    (:func:`mask_source` says which, in words). A ``groundtruth/`` folder that is
    incomplete or does not fit the capture is reported (a warning) and ignored: only the
    evaluation needs it. Initial poses (``poses.*``) are read by :func:`read_capture_poses`.

    Parameters
    ----------
    path : str or os.PathLike
        The capture folder.
    mask : {"auto", "none", "folder"} or None
        Where the object masks come from (None: mask/ when present, else "auto").
    depth_range : (near, far) metres or None
        The automatic masks' depth range (None: around the depth at the image centre).

    Returns
    -------
    Capture

    Raises
    ------
    CaptureError
        The folder, a file or the frames are missing, unreadable or inconsistent.
    """
    root = capture_root(path)
    mask = _choose_mask_source(root, mask, depth_range)
    settings = _read_settings(root / CAPTURE_JSON)
    color_K, color_K_size = read_intrinsic_json(root / INTRINSIC_JSON)
    depth_K, depth_K_size = None, None
    if (root / DEPTH_INTRINSIC_JSON).exists():
        depth_K, depth_K_size = read_intrinsic_json(root / DEPTH_INTRINSIC_JSON)

    color_files, depth_files = paired_frame_files(root, settings["frames"])
    names = list(color_files)

    color, first_of = [], {}  # bit depth -> the first file holding it
    decoded = _in_threads(lambda file: _decode_color(_read_image(file), settings["color_encoding"], file),
                          list(color_files.values()))
    for (array, bits), file in zip(decoded, color_files.values()):
        color.append(image_from_array(array))
        first_of.setdefault(bits, Path(file).name)
    if len(first_of) > 1:
        mixed = " and ".join(f"{bits}-bit frames (first: {name})" for bits, name in sorted(first_of.items()))
        raise CaptureError(f"{root / COLOR_DIR} mixes {mixed}; save every colour frame at one bit depth")
    depth = [image_from_array(z) for z in _in_threads(
        lambda f: _decode_depth(_read_image(f), settings["depth_scale"], f), list(depth_files.values()))]
    capture = Capture(
        color=color,
        depth=depth,
        color_intrinsic=o3d.core.Tensor(color_K),
        depth_intrinsic=o3d.core.Tensor(color_K if depth_K is None else depth_K),  # default set once SF is known
        masks=_read_masks(root / MASK_DIR, names) if mask == "folder" else None,
        depth_scale=settings["depth_scale"],
        depth_trunc=settings["depth_trunc"],
        color_encoding=settings["color_encoding"],
        sensor=settings["sensor"],
        metadata={**settings["metadata"], "color_bit_depth": next(iter(first_of))},
        light=settings["light"],
        camera=settings["camera"],
        frame_names=[p.name for p in color_files.values()],
        folder=str(root),
    )
    validate_capture(capture, names)
    _check_intrinsic_size(root / INTRINSIC_JSON, color_K_size, capture.color_size, COLOR_DIR)
    if depth_K is None:
        capture.depth_intrinsic = o3d.core.Tensor(default_depth_intrinsic(color_K, capture.scale_factor))
    else:
        _check_intrinsic_size(root / DEPTH_INTRINSIC_JSON, depth_K_size, capture.depth_size, DEPTH_DIR)
    if mask == "auto":
        masks = auto_masks([capture.depth_array(i) for i in range(capture.n_frames)], capture.depth_K(),
                           capture.scale_factor, depth_range)
        capture.masks = [image_from_array((m * np.uint8(255))[..., None]) for m in masks]
    if (root / GROUNDTRUTH_DIR).is_dir():
        capture.groundtruth = _read_groundtruth(root / GROUNDTRUTH_DIR, capture.n_frames, capture.color_size)
    return capture


def _choose_mask_source(root: Path, mask: str | None, depth_range) -> str:
    """The mask source to use ("auto", "none" or "folder"); CaptureError for a bad choice or range."""
    if mask is None:
        mask = "folder" if (root / MASK_DIR).is_dir() else "auto"
    if mask not in MASK_SOURCES:
        raise CaptureError(f"mask={mask!r} is not a mask source; use one of {', '.join(MASK_SOURCES)}")
    if mask == "folder" and not (root / MASK_DIR).is_dir():
        raise CaptureError(f"{root / MASK_DIR} is missing; add the masks, or use automatic masks (--mask auto)")
    if depth_range is not None:
        near, far = (float(x) for x in depth_range)
        if not 0 <= near < far:
            raise CaptureError(f"depth range {near:g}-{far:g} m is empty or negative; give NEAR < FAR in metres")
    return mask


def mask_source(path, mask: str | None = None, depth_range=None) -> str:
    """Where :func:`read_capture` (same arguments) takes the masks of the capture folder ``path``
    from, in words (for logs); CaptureError for a bad choice or depth range."""
    root = capture_root(path)
    mask = _choose_mask_source(root, mask, depth_range)
    if mask == "folder":
        return f"folder {root / MASK_DIR}"
    if mask == "none":
        return "none"
    if depth_range is None:
        return "auto (depth region nearest the image centre, range around the centre depth)"
    return f"auto (depth region nearest the image centre, range {depth_range[0]:g}-{depth_range[1]:g} m)"


def capture_root(path) -> Path:
    """The capture folder as a Path; CaptureError when it is missing or a file."""
    root = Path(path).expanduser()
    if not root.exists():
        raise CaptureError(f"capture folder {root} does not exist; check the path")
    if not root.is_dir():
        raise CaptureError(f"{root} is a file, not a capture folder; give the folder holding color/ and depth/")
    return root


def load_json(path: Path):
    """A JSON file's content; CaptureError naming the file when it cannot be read."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CaptureError(f"cannot read {path} ({e}); fix or rewrite the JSON file") from None


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
    return intrinsic_matrix(K, str(path)), size


def paired_frame_files(root: Path, expected: int | None) -> tuple[dict[str, Path], dict[str, Path]]:
    """Colour and depth frame files by name; CaptureError unless they pair up (and number ``expected``)."""
    color_files = _frame_files(root / COLOR_DIR, COLOR_SUFFIXES)
    depth_files = _frame_files(root / DEPTH_DIR, (".png",))
    if list(color_files) != list(depth_files):
        only_color = [color_files[k] for k in color_files if k not in depth_files]
        only_depth = [depth_files[k] for k in depth_files if k not in color_files]
        missing = [f"{root / DEPTH_DIR / (p.stem + '.png')} (for {p})" for p in only_color]
        missing += [f"{root / COLOR_DIR / (p.stem + '.png')} (for {p})" for p in only_depth]
        raise CaptureError(
            f"{root}: {COLOR_DIR}/ has {len(color_files)} frames and {DEPTH_DIR}/ has {len(depth_files)}; missing: "
            f"{', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}. Colour and depth frames are paired by "
            "file name: add the missing file, or remove or rename its partner"
        )
    if expected is not None and expected != len(color_files):
        raise CaptureError(
            f"{root / CAPTURE_JSON} says {expected} frames but {COLOR_DIR}/ has {len(color_files)}; "
            "restore the missing frames or correct \"frames\""
        )
    return color_files, depth_files


def natural_key(name: str) -> tuple:
    """Sort key ordering digit runs by value: ``frame_2`` before ``frame_10`` (then by the text)."""
    parts = re.split(r"(\d+)", name)
    return tuple((0, int(p), p) if p.isdigit() else (1, 0, p.lower()) for p in parts), name


def _frame_files(folder: Path, suffixes) -> dict[str, Path]:
    """Frame files of a folder by stem, in natural name order (:func:`natural_key`); CaptureError
    if none. Entries that are not frames are skipped with one warning naming them."""
    if not folder.is_dir():
        raise CaptureError(
            f"{folder} is missing; a capture folder needs {COLOR_DIR}/ and {DEPTH_DIR}/ with one PNG per frame"
        )
    files, skipped = [], []
    for p in folder.iterdir():
        if p.name.startswith("."):  # ._* (macOS), .DS_Store, editors' files
            skipped.append(f"{p.name} (hidden file)")
        elif p.is_symlink() and not p.exists():
            skipped.append(f"{p.name} (broken link)")
        elif p.is_dir():
            skipped.append(f"{p.name}/ (folder)")
        elif p.suffix.lower() not in suffixes:
            skipped.append(f"{p.name} (not {'/'.join(suffixes)})")
        else:
            files.append(p)
    files.sort(key=lambda p: natural_key(p.name))
    if skipped:
        warnings.warn(f"{folder}: skipping {len(skipped)} entries that are not frames: "
                      f"{', '.join(sorted(skipped)[:8])}{' ...' if len(skipped) > 8 else ''}", stacklevel=4)
    if not files:
        raise CaptureError(f"{folder} holds no frames; add {'/'.join(suffixes)} images named like 000000.png")
    by_stem = {p.stem: p for p in files}
    if len(by_stem) != len(files):
        raise CaptureError(f"{folder} has two frames with the same name but different suffixes; keep one of each")
    return by_stem


def _in_threads(read, files: list) -> list:
    """``[read(f) for f in files]`` on up to :data:`READ_THREADS` threads (PNG decoding releases the
    GIL: a D415 capture's 40 frames read in about half the wall time on 2 cores); the first
    failing file's error, in file order, is raised."""
    workers = min(READ_THREADS, os.cpu_count() or 1, len(files))
    if workers <= 1:
        return [read(f) for f in files]
    with ThreadPoolExecutor(workers, thread_name_prefix="o3d_mvps-read") as pool:
        return list(pool.map(read, files))


def _exif_orientation(path: Path) -> int:
    """The EXIF orientation tag of a JPEG (1 = stored as displayed, also when there is no tag)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            return int(image.getexif().get(EXIF_ORIENTATION, 1))
    except (OSError, UnidentifiedImageError, ValueError):
        return 1  # unreadable EXIF: cv2 reports an unreadable image itself


def _read_image(path: Path) -> np.ndarray:
    """An image file as stored (uint8/uint16; RGB(A) order for colour); CaptureError if unreadable.

    A JPEG whose EXIF orientation asks viewers to rotate it is refused: its stored pixels and
    its displayed picture differ, and only one of them matches the depth frame.
    """
    if path.suffix.lower() in (".jpg", ".jpeg"):
        orientation = _exif_orientation(path)
        if orientation != 1:
            raise CaptureError(
                f"colour frame {path} carries EXIF orientation {orientation} (viewers show it rotated or "
                "mirrored), so it is unclear which way matches the depth frame. If the stored pixels match "
                "the depth, clear the tag (exiftool -Orientation=1 -n FILE); if the picture was rotated for "
                "display, rotate it back; or save the colour frames as PNG"
            )
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CaptureError(f"cannot read image {path} (corrupt or not an image); re-export or remove that frame")
    if image.ndim == 3 and image.shape[2] in (3, 4):
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB if image.shape[2] == 3 else cv2.COLOR_BGRA2RGBA)
    return image


def _decode_color(raw: np.ndarray, encoding: str, path: Path) -> tuple[np.ndarray, int]:
    """Stored colour -> ((H, W, 3) uint8/uint16 codes as stored, bit depth): kept as codes, which
    :meth:`Capture.color_array` decodes by table (``encoding``; linear RGB in [0, 1])."""
    if raw.dtype not in (np.uint8, np.uint16) or raw.ndim != 3:
        raise CaptureError(
            f"colour frame {path} is {raw.dtype} with shape {raw.shape}; save colour as 8- or 16-bit RGB PNG"
        )
    return raw[..., :3], 8 * raw.dtype.itemsize


def _decode_depth(raw: np.ndarray, depth_scale: float, path: Path) -> np.ndarray:
    """Stored uint16 depth -> (h, w, 1) float32 metres.

    Refuses depth whose measured values are all at most DEPTH_RANGE_M's upper end (20): that is
    depth in metres cast to integers, which keeps whole metres only.
    """
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise CaptureError(
            f"depth frame {path} is {raw.dtype} with shape {raw.shape}; depth must be a single-channel "
            "16-bit PNG (units 1/depth_scale m)"
        )
    measured = raw[raw > 0]
    if measured.size and measured.max() <= DEPTH_RANGE_M[1]:
        raise CaptureError(
            f"depth frame {path} holds only the values {int(measured.min())}..{int(measured.max())}: it looks like "
            "depth in metres stored as integers, which keeps whole metres only. Re-export the depth in millimetres "
            "(uint16 PNG of round(metres * 1000), depth_scale 1000 in capture.json)"
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


def _read_settings(path: Path) -> dict:
    """capture.json with defaults filled in; 'frames' is None when absent."""
    settings = {**DEFAULT_SETTINGS, "frames": None, "metadata": {}, "light": None, "camera": None}
    if not path.exists():
        return settings
    data = load_json(path)
    if not isinstance(data, dict):
        raise CaptureError(f"{path} must hold a JSON object like {{\"depth_scale\": 1000, ...}}")
    settings.update({k: data[k] for k in settings if k in data})
    try:
        settings["depth_scale"] = float(settings["depth_scale"])
        settings["depth_trunc"] = float(settings["depth_trunc"])
        frames = settings["frames"]
        settings["frames"] = None if frames is None else int(frames)
    except (TypeError, ValueError):
        raise CaptureError(f"{path}: depth_scale, depth_trunc and frames must be numbers; fix the file") from None
    if frames is not None and (isinstance(frames, bool) or settings["frames"] != frames or settings["frames"] < 1):
        raise CaptureError(f"{path}: \"frames\": {frames!r} must be a whole number of frames >= 1 (the count of "
                           "color/ images); fix the file or remove the key")
    check_settings(settings["depth_scale"], settings["depth_trunc"], settings["color_encoding"], 8, f"{path}: ")
    if not isinstance(settings["metadata"], dict):
        raise CaptureError(f"{path}: metadata must be a JSON object")
    settings["sensor"] = str(settings["sensor"])
    check_light(settings["light"], f"{path}: ")
    check_camera(settings["camera"], f"{path}: ")
    return settings


def _check_intrinsic_size(path: Path, size, image_size, images: str) -> None:
    """CaptureError when intrinsics for ``size`` (H, W) are given for frames of ``image_size``."""
    if tuple(size) == tuple(image_size):
        return
    ratio = image_size[0] / size[0]
    hint = ""
    if np.isclose(image_size[1] / size[1], ratio):
        hint = (f" The frames are {ratio:g} times that size: if they were resized after calibration, scale the "
                f"intrinsics by {ratio:g} (o3d_mvps.model.camera.scale_intrinsics) and fix width and height.")
    raise CaptureError(
        f"{path} is for {size_text(size)} images but {images}/ frames are {size_text(image_size)} (WxH); "
        f"use the intrinsics of the camera mode the frames were recorded in.{hint}"
    )


def read_groundtruth(path, n_frames: int, color_size) -> GroundTruth | None:
    """The ground truth of the capture folder ``path`` as :func:`read_capture` reads it (for
    ``n_frames`` frames of ``color_size`` (H, W)), or None where it has none (or, with a warning,
    an incomplete or foreign one): for a caller that does not hold it through a refinement."""
    folder = capture_root(path) / GROUNDTRUTH_DIR
    return _read_groundtruth(folder, n_frames, color_size) if folder.is_dir() else None


def _read_groundtruth(folder: Path, n_frames: int, color_size) -> GroundTruth | None:
    """The ground truth of a synthetic capture, or None (with a warning) when incomplete or foreign."""
    arrays = {}
    try:
        for name in GT_ARRAYS:
            arrays[name] = np.load(folder / f"{name}.npy", allow_pickle=False)
        light = json.loads((folder / "light.json").read_text())
    except (OSError, ValueError, UnicodeDecodeError) as e:
        problem = f"cannot read it ({e})"
    else:
        gt = GroundTruth(light=light, **arrays)
        problem = groundtruth_problem(gt, n_frames, color_size)
        if problem is None:
            return gt
    warnings.warn(
        f"ignoring {folder}: {problem}. Only the evaluation against ground truth needs it (a synthetic capture "
        f"holds {', '.join(n + '.npy' for n in GT_ARRAYS)} and light.json); refinement goes on without it",
        stacklevel=3,
    )
    return None
