"""SolverInput: the arrays the solver works on, and its saved-problem file (.npz).

A capture, once read, masked and registered (the Open3D side, :mod:`o3d_mvps.solving`), becomes
plain NumPy arrays; :func:`o3d_mvps.solver.driver.solve` needs nothing else. A saved problem
holds them in one .npz (the options as JSON), so a problem can be solved where Open3D is not
installed (``python -m o3d_mvps.solver``) or attached to a bug report.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..colour import CodedColours
from ..errors import MVPSError
from ..fileio import atomic_files, json_text
from .options import RefineOptions

#: What a saved problem calls itself, and the newest format version this code reads and writes.
#: Version 2 saves coded colour frames as their codes with their tables (version 1: decoded).
PROBLEM_FORMAT, PROBLEM_VERSION = "o3d_mvps.solver_input", 2
SAVE_HOW = "o3d-mvps refine CAPTURE OUT --save-problem FILE.npz"


@dataclass
class SolverInput:
    """n frames of one object (frame 0 the reference) as the solver reads them.

    colors: (n, H, W, 3) float32 linear RGB in [0, 1], or a list of n (H, W, 3) frames (then
    not copied where they are float32 and C-ordered: a capture's own frames), or a
    :class:`~o3d_mvps.colour.CodedColours` (frames read from files, kept as their codes and
    decoded where the solver samples them; indexing it gives float32 frames too). depths: (n, h, w) float32 metres at the
    depth sensor's resolution (h = H / scale_factor), 0 = no measurement. masks: n entries, each
    None or an (H, W) bool object mask. K, depth_K: (3, 3) float64 colour and depth intrinsics
    (pixels). scale_factor: integer H / h. initial_poses: (n, 4, 4) float64 reference -> frame i,
    initial_poses[0] the identity. led_offset: (3,) float64 metres, the LED position in the colour
    camera's frame to start from. frames: the capture's indices of the n frames (reported back).
    options: the refinement options (``options.frames`` was applied when the frames were picked).
    report: JSON-ready notes on how the input was made (``inputs``: the input checks,
    ``frames_report``: every capture frame, used or why not); passed on to the refinement's info,
    not saved. pose_trust: None where the initial poses were registered; for given poses, how far
    they are trusted, (metres, radians) (:mod:`o3d_mvps.solver.pose_trust`). depth_noise: s (1/m)
    of the depth noise sigma(z) = s z^2 that the frames' disagreement at the initial poses gave
    (:func:`o3d_mvps.covisibility.depth_noise_scale`; a moving camera of 4 frames or more), which
    the frames' mean depth is judged by (``average_frames_depth``); None where not measured.
    """

    colors: np.ndarray | list
    depths: np.ndarray
    masks: list
    K: np.ndarray
    depth_K: np.ndarray
    scale_factor: int
    initial_poses: np.ndarray
    led_offset: np.ndarray
    frames: list
    options: RefineOptions
    report: dict = field(default_factory=dict)
    pose_trust: tuple | None = None
    depth_noise: float | None = None

    def __post_init__(self):
        if isinstance(self.colors, np.ndarray):
            self.colors = np.ascontiguousarray(self.colors, dtype=np.float32)
        elif not isinstance(self.colors, CodedColours):
            self.colors = [np.ascontiguousarray(c, dtype=np.float32) for c in self.colors]
        self.depths = np.ascontiguousarray(self.depths, dtype=np.float32)
        self.K, self.depth_K = (np.asarray(a, dtype=np.float64) for a in (self.K, self.depth_K))
        self.initial_poses = np.asarray(self.initial_poses, dtype=np.float64)
        self.led_offset = np.asarray(self.led_offset, dtype=np.float64)
        self.scale_factor, self.frames = int(self.scale_factor), [int(i) for i in self.frames]
        self.masks = [None if m is None else np.asarray(m, dtype=bool) for m in self.masks]
        if self.pose_trust is not None:
            trust = np.asarray(self.pose_trust, dtype=np.float64).reshape(-1)
            if trust.shape != (2,) or not np.all(np.isfinite(trust)) or not np.all(trust > 0):
                raise ValueError(f"pose_trust must be (metres, radians), both > 0, got {self.pose_trust!r}")
            self.pose_trust = (float(trust[0]), float(trust[1]))
        if self.depth_noise is not None:
            if not (np.isfinite(self.depth_noise) and self.depth_noise >= 0):
                raise ValueError(f"depth_noise must be a finite s (1/m) >= 0 or None, got {self.depth_noise!r}")
            self.depth_noise = float(self.depth_noise)
        n = len(self.colors)
        shapes = self._frame_shapes()
        H, W = shapes[0][:2] if n and len(shapes[0]) == 3 else (0, 0)
        sf = max(self.scale_factor, 1)
        expected = {"depths": (n, H // sf, W // sf), "K": (3, 3), "depth_K": (3, 3), "initial_poses": (n, 4, 4),
                    "led_offset": (3,)}
        wrong = [f"colors[{i}] has shape {shape}, not {(H, W, 3)}" for i, shape in enumerate(shapes)
                 if shape != (H, W, 3)]
        wrong += [f"{name} has shape {getattr(self, name).shape}, not {shape}" for name, shape in expected.items()
                  if getattr(self, name).shape != shape]
        wrong += [f"masks[{i}] has shape {m.shape}, not {(H, W)}" for i, m in enumerate(self.masks)
                  if m is not None and m.shape != (H, W)]
        wrong += [f"{name} has {len(getattr(self, name))} entries for {n} frames" for name in ("masks", "frames")
                  if len(getattr(self, name)) != n]
        if n < 1 or self.scale_factor < 1 or H % sf or W % sf:
            wrong.insert(0, f"{n} frames of {W}x{H} colour, scale factor {self.scale_factor} (need n >= 1 and "
                            "H, W multiples of the scale factor)")
        if wrong:
            raise ValueError("inconsistent solver input: " + "; ".join(wrong))
        if not isinstance(self.options, RefineOptions):
            raise ValueError(f"options must be a RefineOptions, got {type(self.options).__name__}")

    @property
    def n_frames(self) -> int:
        return len(self.colors)

    @property
    def color_size(self) -> tuple[int, int]:
        """(H, W) of the colour frames."""
        return self._frame_shapes()[0][:2]

    def _frame_shapes(self) -> list[tuple]:
        """Each colour frame's shape (read without decoding coded frames)."""
        if isinstance(self.colors, CodedColours):
            return [c.shape for c in self.colors.codes]
        return [c.shape for c in self.colors]

    def float_colors(self) -> np.ndarray | list:
        """The colour frames as float32 (H, W, 3) arrays: ``colors`` itself, or coded frames
        decoded (a new (n, H, W, 3) array)."""
        if isinstance(self.colors, CodedColours):
            return np.stack(list(self.colors)) if len(self.colors) else np.zeros((0, 0, 0, 3), np.float32)
        return self.colors


#: SolverInput fields stored as one array each under their own name.
_ARRAYS = ("colors", "depths", "K", "depth_K", "scale_factor", "initial_poses", "led_offset", "frames")


def write_problem(problem: SolverInput, path, *, overwrite: bool = False) -> Path:
    """Write ``problem`` to the .npz ``path`` (compressed; refuses an existing file unless ``overwrite``).

    Keys: format, format_version, the arrays of :class:`SolverInput` under their names, masks
    (n, H, W) bool with has_mask (n,) bool (False: the frame had no mask), options (JSON),
    pose_trust (2,) where the poses were given, depth_noise () where measured. Coded frames
    (:class:`~o3d_mvps.colour.CodedColours`) are saved as they are held: colors (n, H, W, 3)
    uint8/uint16 codes and color_tables (n, 3, K) float32 (a quarter of the float frames' bytes
    for 8-bit files).
    """
    path = Path(path)
    H, W = problem.color_size
    arrays = {name: np.asarray(getattr(problem, name)) for name in _ARRAYS if name != "colors"}
    if isinstance(problem.colors, CodedColours):
        arrays["colors"], arrays["color_tables"] = np.stack(problem.colors.codes), problem.colors.tables
    else:
        arrays["colors"] = np.asarray(problem.colors)
    arrays["masks"] = np.stack([np.zeros((H, W), bool) if m is None else m for m in problem.masks])
    arrays["has_mask"] = np.array([m is not None for m in problem.masks])
    arrays["options"] = np.array(json_text(problem.options.to_dict(), "the options"))
    if problem.pose_trust is not None:
        arrays["pose_trust"] = np.asarray(problem.pose_trust)
    if problem.depth_noise is not None:
        arrays["depth_noise"] = np.array(problem.depth_noise)
    with atomic_files([path], overwrite) as (tmp,), open(tmp, "wb") as file:
        np.savez_compressed(file, format=np.array(PROBLEM_FORMAT), format_version=np.array(PROBLEM_VERSION), **arrays)
    return path


def read_problem(path) -> SolverInput:
    """The :class:`SolverInput` of a file :func:`write_problem` wrote; MVPSError naming the file
    and the fix when it is missing, not a saved problem, from a newer version, or corrupt."""
    path = Path(path)
    if not path.is_file():
        raise MVPSError(f"{path}: no such file; give the .npz that `{SAVE_HOW}` wrote")
    remake = f"the file is damaged: write it again with `{SAVE_HOW}`"
    try:
        with np.load(path, allow_pickle=False) as npz:
            data = {key: npz[key] for key in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise MVPSError(f"{path} is not a saved o3d_mvps problem (cannot read it as .npz: {e}); give the .npz "
                        f"that `{SAVE_HOW}` wrote") from None
    if str(data.get("format", "")) != PROBLEM_FORMAT:
        raise MVPSError(f"{path} is an .npz but not a saved o3d_mvps problem (no format '{PROBLEM_FORMAT}'); give "
                        f"the .npz that `{SAVE_HOW}` wrote")
    try:
        version = int(data["format_version"])
    except (KeyError, TypeError, ValueError):
        raise MVPSError(f"{path} has no readable format_version; {remake}") from None
    if version > PROBLEM_VERSION:
        raise MVPSError(f"{path} is a saved problem of format version {version}, newer than this o3d_mvps reads "
                        f"({PROBLEM_VERSION}); upgrade o3d_mvps (pip install -U o3d-mvps) where you solve it")
    if version < 1:
        raise MVPSError(f"{path}: format_version {version} is not a version o3d_mvps ever wrote "
                        f"(1..{PROBLEM_VERSION}); {remake}")
    problem = _check_values(path, data)
    if problem:
        raise MVPSError(f"{path}: {problem}; {remake}")
    try:
        masks = [m if has else None for m, has in zip(data["masks"], data["has_mask"])]
        options = RefineOptions.from_dict(json.loads(str(data["options"])))
        trust, noise = data.get("pose_trust"), data.get("depth_noise")
        arrays = {name: data[name] for name in _ARRAYS}
        if "color_tables" in data:
            arrays["colors"] = CodedColours(list(arrays["colors"]), data["color_tables"])
        return SolverInput(**arrays, masks=list(masks), options=options,
                           pose_trust=None if trust is None else tuple(trust.tolist()),
                           depth_noise=None if noise is None else float(noise))
    except KeyError as e:
        raise MVPSError(f"{path} lacks the array {e}; {remake}") from None
    except (TypeError, ValueError) as e:
        raise MVPSError(f"{path}: {e}; {remake}") from None



#: Largest deviation of a saved pose's rotation from orthonormality (R^T R - I, max abs).
ROTATION_TOLERANCE = 1e-6


def _check_values(path: Path, data: dict) -> str | None:
    """What is wrong with a saved problem's values (naming the key), or None: finite intrinsics with
    positive focal lengths and the last row 0 0 1, finite rigid poses (orthonormal rotations,
    last row 0 0 0 1), a finite LED offset, finite non-negative frames."""
    for key in ("K", "depth_K"):
        K = np.asarray(data.get(key, np.eye(3)), dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 \
                or not np.allclose(K[2], [0, 0, 1]):
            return f"key '{key}' is not finite intrinsics with positive focal lengths ([[fx, 0, cx], [0, fy, cy], " \
                   f"[0, 0, 1]], got {np.round(K, 4).tolist()})"
    poses = np.asarray(data.get("initial_poses", np.eye(4)[None]), dtype=np.float64)
    if poses.ndim == 3 and poses.shape[1:] == (4, 4):
        for i, T in enumerate(poses):
            R = T[:3, :3]
            if not np.all(np.isfinite(T)):
                return f"key 'initial_poses': pose {i} is not finite"
            if np.abs(R.T @ R - np.eye(3)).max() > ROTATION_TOLERANCE or np.linalg.det(R) <= 0 \
                    or not np.allclose(T[3], [0, 0, 0, 1]):
                return f"key 'initial_poses': pose {i} is not a rigid transform (orthonormal rotation, last row " \
                       f"0 0 0 1; got {np.round(T, 4).tolist()})"
    offset = np.asarray(data.get("led_offset", np.zeros(3)), dtype=np.float64)
    if not np.all(np.isfinite(offset)):
        return f"key 'led_offset' {offset.tolist()} is not finite"
    for key in ("colors", "color_tables", "depths"):
        if key in data and np.asarray(data[key]).dtype.kind == "f" and not np.all(np.isfinite(data[key])):
            return f"key '{key}' holds NaN or infinite values"
    if "depths" in data and np.any(np.asarray(data["depths"]) < 0):
        return "key 'depths' holds negative depths (0 = no measurement)"
    return None
