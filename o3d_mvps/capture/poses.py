"""Initial camera poses from other tools' files: Open3D trajectories, TUM lines, numpy arrays.

The package's convention, used everywhere: ``T_i`` (4, 4) maps reference-camera coordinates
(frame 0, metres) into frame-i camera coordinates, so ``T_0`` is the identity. Each reader
converts its format's own convention once, here:

=====================================  ==========  ===============================  =====================
format                                 suffix      stores per frame                 conversion
=====================================  ==========  ===============================  =====================
Open3D ``PinholeCameraTrajectory``     .json       ``extrinsic`` E_i, world to       T_i = E_i E_0^-1
                                                   camera (16 numbers, column-major)
Open3D / Redwood trajectory (what      .log        ``id id n`` line, then 4 rows    T_i = C_i^-1 C_0
Open3D's reconstruction system                     of C_i, camera to world
writes)
TUM RGB-D                              .txt .tum   ``id tx ty tz qx qy qz qw``,     T_i = C_i^-1 C_0
                                                   camera to world
numpy                                  .npy        (n, 4, 4) E_i, world to camera   T_i = E_i E_0^-1
                                                   (``poses.npy`` of a refinement:
                                                   world = reference camera)
=====================================  ==========  ===============================  =====================

A file holds one pose per frame of the capture folder, in frame-name order (natural order:
``frame_2`` before ``frame_10``). Integer ids (the ``.log`` and TUM first column) must be the
frame numbers: 0..n-1 or the frame file names (000000, ...); non-integer TUM timestamps are
matched by order.

Files that break their format's convention are read with three options (``refine
--poses-convention``, ``--quaternion-order``, ``--poses-unit``): ``convention``
(``"world-to-camera"`` or ``"camera-to-world"``: what each matrix maps, overriding the
format's own), ``quaternion_order`` (TUM: ``"xyzw"``, the format's, or ``"wxyz"``) and
``unit`` (``"m"`` or ``"mm"``: the translations' unit). :func:`given_poses` keeps the matrices
as read, so :mod:`o3d_mvps.capture.pose_checks` can try the usual mix-ups against the depth.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import CaptureError
from ..model.se3 import relative_to_reference
from .reading import capture_root, load_json, paired_frame_files

#: Suffixes of the pose file formats (see the module docstring).
POSE_SUFFIXES = (".json", ".log", ".txt", ".tum", ".npy")
#: Name (without suffix) of the pose file that a capture folder may hold.
POSES_STEM = "poses"
#: Largest deviation of a rotation block from orthonormality accepted (R^T R - I, max abs).
ROTATION_TOLERANCE = 1e-3
#: What a pose file's matrices map (``--poses-convention``); None: the format's own (table above).
POSE_CONVENTIONS = ("world-to-camera", "camera-to-world")
#: TUM quaternion orders (``--quaternion-order``): the format's scalar-last, or scalar-first.
QUATERNION_ORDERS = ("xyzw", "wxyz")
#: Translation units of a pose file (``--poses-unit``), in metres per unit.
POSE_UNITS = {"m": 1.0, "mm": 1e-3}
#: Each format's own convention.
FORMAT_CONVENTION = {".json": "world-to-camera", ".log": "camera-to-world", ".txt": "camera-to-world",
                     ".tum": "camera-to-world", ".npy": "world-to-camera"}


@dataclass
class GivenPoses:
    """Initial poses as given (a file or an array), kept as read so their conventions can be checked.

    world_to_camera: (n, 4, 4) float64, the matrices as read (after ``convention``, ``unit`` and
    ``quaternion_order``), one per frame in frame order; the poses :attr:`poses` are these
    re-based on frame 0. path: the file, or None for an array. frame_names: the capture's frame
    names (None for an array). options: the reader options used ({"convention", "quaternion_order",
    "unit"}). variants: {name: (n, 4, 4)} world-to-camera matrices read with other file options
    (TUM: the other quaternion order), tried by :mod:`.pose_checks`.
    """

    world_to_camera: np.ndarray
    path: Path | None = None
    frame_names: list | None = None
    options: dict = field(default_factory=dict)
    variants: dict = field(default_factory=dict)

    @property
    def poses(self) -> np.ndarray:
        """(n, 4, 4) float64 ``T_i``, reference (frame 0) -> frame i."""
        return relative_to_reference(self.world_to_camera)

    @property
    def where(self) -> str:
        """The poses' source in words: the file, or "initial_poses"."""
        return str(self.path) if self.path is not None else "initial_poses"

    @classmethod
    def from_array(cls, poses) -> "GivenPoses":
        """Poses passed as an (n, 4, 4) array (reference -> frame i, or any world -> camera)."""
        return cls(np.asarray(poses, dtype=np.float64))


def read_capture_poses(folder, poses_file=None, **options) -> tuple[np.ndarray, Path] | None:
    """Initial poses of a capture folder's frames: from ``poses_file``, else its ``poses.*``, else None.

    Parameters
    ----------
    folder : str or os.PathLike
        The capture folder (its color/ and depth/ frame names are matched against the file).
    poses_file : str or os.PathLike, optional
        A pose file in any format of the module docstring; wins over the folder's own.
    **options
        ``convention``, ``quaternion_order``, ``unit`` (module docstring).

    Returns
    -------
    ((n, 4, 4) float64 poses T_i, the file read), or None when there is no pose file.

    Raises
    ------
    CaptureError
        The file is missing, unreadable, of an unknown format, or its pose count or ids do not
        match the frames; the folder holds more than one ``poses.*``.
    """
    given = given_poses(folder, poses_file, **options)
    return None if given is None else (given.poses, given.path)


def given_poses(folder, poses_file=None, convention=None, quaternion_order=None, unit="m") -> GivenPoses | None:
    """:func:`read_capture_poses` keeping the matrices as read (:class:`GivenPoses`), or None
    when there is no pose file; a TUM file is also read in the other quaternion order."""
    root = capture_root(folder)
    if poses_file is None:
        found = sorted(p for p in root.glob(f"{POSES_STEM}.*") if p.suffix.lower() in POSE_SUFFIXES)
        if not found:
            return None
        if len(found) > 1:
            raise CaptureError(f"{root} holds several pose files ({', '.join(p.name for p in found)}); keep one, "
                               "or choose one with --poses FILE")
        poses_file = found[0]
    path = Path(poses_file).expanduser()
    names = list(paired_frame_files(root, None)[0])
    options = {"convention": convention, "quaternion_order": quaternion_order or "xyzw", "unit": unit}
    E = read_world_to_camera(path, names, **options)
    variants = {}
    if path.suffix.lower() in (".txt", ".tum"):
        other = QUATERNION_ORDERS[1 - QUATERNION_ORDERS.index(options["quaternion_order"])]
        try:
            variants[f"quaternion-order {other}"] = read_world_to_camera(path, names, **{**options,
                                                                                         "quaternion_order": other})
        except CaptureError:
            pass  # not readable that way: not a candidate
    return GivenPoses(E, path, names, options, variants)


def read_poses(path, frame_names: list[str], **options) -> np.ndarray:
    """Read a pose file (format from its suffix) for the named frames.

    Parameters
    ----------
    path : str or os.PathLike
        .json (Open3D PinholeCameraTrajectory), .log (Open3D / Redwood), .txt or .tum (TUM),
        .npy ((n, 4, 4) world to camera).
    frame_names : list of str
        The capture's frame names in order (file names without suffix).
    **options
        ``convention``, ``quaternion_order``, ``unit`` (module docstring).

    Returns
    -------
    (n, 4, 4) float64 array
        ``T_i`` mapping reference-camera (frame 0) coordinates to frame-i camera coordinates.
    """
    return relative_to_reference(read_world_to_camera(path, frame_names, **options))


def read_world_to_camera(path, frame_names: list[str], convention=None, quaternion_order="xyzw",
                         unit="m") -> np.ndarray:
    """A pose file's (n, 4, 4) float64 world-to-camera matrices (not yet re-based on frame 0);
    options as in the module docstring. CaptureError naming the file (and line) for a bad pose."""
    path = Path(path)
    if convention is not None and convention not in POSE_CONVENTIONS:
        raise CaptureError(f"poses convention {convention!r} is unknown; use one of {', '.join(POSE_CONVENTIONS)} "
                           "(--poses-convention)")
    if quaternion_order not in QUATERNION_ORDERS:
        raise CaptureError(f"quaternion order {quaternion_order!r} is unknown; use one of "
                           f"{', '.join(QUATERNION_ORDERS)} (--quaternion-order)")
    if unit not in POSE_UNITS:
        raise CaptureError(f"poses unit {unit!r} is unknown; use one of {', '.join(POSE_UNITS)} (--poses-unit)")
    readers = {".json": _read_trajectory_json, ".log": _read_log, ".txt": _read_tum, ".tum": _read_tum,
               ".npy": _read_npy}
    suffix = path.suffix.lower()
    if suffix not in readers:
        raise CaptureError(f"{path}: unknown pose file format {suffix!r}; use one of {', '.join(POSE_SUFFIXES)} "
                           "(formats in docs/capture-guide.md, 'Poses')")
    if not path.is_file():
        raise CaptureError(f"pose file {path} does not exist; check the path")
    args = (path, quaternion_order) if suffix in (".txt", ".tum") else (path,)
    matrices, ids, lines = readers[suffix](*args)
    _check_frames(path, len(matrices), ids, frame_names)
    for i, E in enumerate(matrices):
        R = E[:3, :3]
        if not (np.all(np.isfinite(E)) and np.abs(R.T @ R - np.eye(3)).max() < ROTATION_TOLERANCE
                and np.allclose(E[3], [0, 0, 0, 1])):
            where = f"{path}, line {lines[i]}" if lines is not None else f"{path}"
            raise CaptureError(f"{where}: pose {i} is not a rigid transform (an orthonormal rotation and a "
                               f"translation, last row 0 0 0 1; got {np.round(E, 4).tolist()}); fix or re-export "
                               "the file")
    matrices = matrices.copy()
    matrices[:, :3, 3] *= POSE_UNITS[unit]
    if (convention or FORMAT_CONVENTION[suffix]) == "camera-to-world":
        matrices = np.linalg.inv(matrices)
    return matrices


def _check_frames(path: Path, count: int, ids: list[float] | None, frame_names: list[str]) -> None:
    """CaptureError unless the file has one pose per frame, with matching integer ids if it has any."""
    n = len(frame_names)
    if count != n:
        raise CaptureError(f"{path} holds {count} poses but the capture folder has {n} frames; give one pose per "
                           "frame in frame-name order (or drop the extra frames from color/ and depth/)")
    if ids is None or not all(float(i).is_integer() for i in ids):
        return
    ids = [int(i) for i in ids]
    numbers = [int(name) for name in frame_names] if all(name.isdigit() for name in frame_names) else None
    if ids != list(range(n)) and ids != numbers:
        raise CaptureError(
            f"{path}: the pose ids {ids[0]}..{ids[-1]} do not match the {n} frames {frame_names[0]}..{frame_names[-1]} "
            f"(ids must be 0..{n - 1} or the frame file numbers, in order); renumber the poses or rename the frames"
        )


def _numbers(path: Path, line: str, count: int, line_number: int) -> list[float]:
    try:
        values = [float(v) for v in line.split()]
    except ValueError:
        values = []
    if len(values) != count:
        raise CaptureError(f"{path}, line {line_number}: expected {count} numbers, got {line.strip()!r}; "
                           "the file is not in the format its suffix names")
    return values


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, text) of the non-empty, non-comment ('#') lines."""
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise CaptureError(f"cannot read pose file {path} ({e})") from None
    return [(k + 1, line) for k, line in enumerate(text.splitlines()) if line.strip() and not line.startswith("#")]


def _read_log(path: Path) -> tuple[np.ndarray, list[float], list[int]]:
    """Open3D / Redwood .log: blocks of 'id id n' and 4 rows of the camera-to-world matrix
    (returned as stored, with each block's first line number)."""
    lines = _data_lines(path)
    if len(lines) % 5:
        raise CaptureError(f"{path} has {len(lines)} data lines, not a multiple of 5: a .log trajectory holds, per "
                           "frame, an 'id id n' line and the 4 rows of a camera-to-world matrix")
    ids, cam_to_world = [], []
    for b in range(0, len(lines), 5):
        ids.append(_numbers(path, lines[b][1], 3, lines[b][0])[0])
        cam_to_world.append([_numbers(path, line, 4, k) for k, line in lines[b + 1:b + 5]])
    return np.asarray(cam_to_world, dtype=np.float64).reshape(-1, 4, 4), ids, [lines[b + 1][0] for b in
                                                                                 range(0, len(lines), 5)]


def _read_tum(path: Path, order: str = "xyzw") -> tuple[np.ndarray, list[float], list[int]]:
    """TUM: 'id tx ty tz qx qy qz qw' per line (``order`` "wxyz": 'id tx ty tz qw qx qy qz'),
    camera to world (returned as stored, with the line numbers)."""
    lines = _data_lines(path)
    rows = np.array([_numbers(path, line, 8, k) for k, line in lines]).reshape(-1, 8)
    quaternions = rows[:, 4:8] if order == "xyzw" else rows[:, [5, 6, 7, 4]]
    norms = np.linalg.norm(quaternions, axis=1)
    bad = ~(np.abs(norms - 1.0) <= 1e-3)  # NaN too
    if np.any(bad):
        k = int(np.argmax(bad))
        raise CaptureError(f"{path}, line {lines[k][0]}: quaternion {rows[k, 4:8].tolist()} is not of unit length "
                           f"(norm {norms[k]:.4g}); a TUM line is 'id tx ty tz qx qy qz qw' (scalar last), with "
                           "finite numbers")
    if not np.all(np.isfinite(rows[:, 1:4])):
        k = int(np.argmax(~np.isfinite(rows[:, 1:4]).all(axis=1)))
        raise CaptureError(f"{path}, line {lines[k][0]}: translation {rows[k, 1:4].tolist()} is not finite; fix or "
                           "remove that pose")
    cam_to_world = np.tile(np.eye(4), (len(rows), 1, 1))
    cam_to_world[:, :3, :3] = Rotation.from_quat(quaternions).as_matrix()
    cam_to_world[:, :3, 3] = rows[:, 1:4]
    return cam_to_world, rows[:, 0].tolist(), [k for k, _ in lines]


def _read_trajectory_json(path: Path) -> tuple[np.ndarray, None, None]:
    """Open3D PinholeCameraTrajectory JSON: parameters[i].extrinsic, world to camera, column-major."""
    data = load_json(path)
    try:
        extrinsics = [np.asarray(p["extrinsic"], dtype=np.float64).reshape(4, 4).T for p in data["parameters"]]
    except (KeyError, TypeError, ValueError):
        raise CaptureError(f"{path} is not an Open3D PinholeCameraTrajectory JSON (\"parameters\": a list of "
                           "{\"extrinsic\": 16 numbers, column-major}); write it with "
                           "o3d.io.write_pinhole_camera_trajectory") from None
    return np.asarray(extrinsics).reshape(-1, 4, 4), None, None


def _read_npy(path: Path) -> tuple[np.ndarray, None, None]:
    """(n, 4, 4) world-to-camera transforms."""
    try:
        poses = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise CaptureError(f"cannot read pose file {path} ({e}); save an (n, 4, 4) array with numpy.save") from None
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise CaptureError(f"{path} holds an array of shape {poses.shape}; poses must be (n, 4, 4) world-to-camera "
                           "transforms")
    return poses.astype(np.float64), None, None
