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

A file holds one pose per frame of the capture folder, in frame-name order. Integer ids (the
``.log`` and TUM first column) must be the frame numbers: 0..n-1 or the frame file names
(000000, ...); non-integer TUM timestamps are matched by order.
"""

from __future__ import annotations

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


def read_capture_poses(folder, poses_file=None) -> tuple[np.ndarray, Path] | None:
    """Initial poses of a capture folder's frames: from ``poses_file``, else its ``poses.*``, else None.

    Parameters
    ----------
    folder : str or os.PathLike
        The capture folder (its color/ and depth/ frame names are matched against the file).
    poses_file : str or os.PathLike, optional
        A pose file in any format of the module docstring; wins over the folder's own.

    Returns
    -------
    ((n, 4, 4) float64 poses T_i, the file read), or None when there is no pose file.

    Raises
    ------
    CaptureError
        The file is missing, unreadable, of an unknown format, or its pose count or ids do not
        match the frames; the folder holds more than one ``poses.*``.
    """
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
    color_files, _ = paired_frame_files(root, None)
    return read_poses(path, list(color_files)), path


def read_poses(path, frame_names: list[str]) -> np.ndarray:
    """Read a pose file (format from its suffix) for the named frames.

    Parameters
    ----------
    path : str or os.PathLike
        .json (Open3D PinholeCameraTrajectory), .log (Open3D / Redwood), .txt or .tum (TUM),
        .npy ((n, 4, 4) world to camera).
    frame_names : list of str
        The capture's frame names in order (file names without suffix).

    Returns
    -------
    (n, 4, 4) float64 array
        ``T_i`` mapping reference-camera (frame 0) coordinates to frame-i camera coordinates.
    """
    path = Path(path)
    readers = {".json": _read_trajectory_json, ".log": _read_log, ".txt": _read_tum, ".tum": _read_tum,
               ".npy": _read_npy}
    suffix = path.suffix.lower()
    if suffix not in readers:
        raise CaptureError(f"{path}: unknown pose file format {suffix!r}; use one of {', '.join(POSE_SUFFIXES)} "
                           "(formats in docs/capture-guide.md, 'Poses')")
    if not path.is_file():
        raise CaptureError(f"pose file {path} does not exist; check the path")
    world_to_camera, ids = readers[suffix](path)
    _check_frames(path, len(world_to_camera), ids, frame_names)
    for i, E in enumerate(world_to_camera):
        R = E[:3, :3]
        if not (np.all(np.isfinite(E)) and np.abs(R.T @ R - np.eye(3)).max() < ROTATION_TOLERANCE
                and np.allclose(E[3], [0, 0, 0, 1])):
            raise CaptureError(f"{path}: pose {i} is not a rigid transform (rotation and translation, last row "
                               "0 0 0 1); fix or re-export the file")
    return relative_to_reference(world_to_camera)


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


def _read_log(path: Path) -> tuple[np.ndarray, list[float]]:
    """Open3D / Redwood .log: blocks of 'id id n' and 4 rows of the camera-to-world matrix."""
    lines = _data_lines(path)
    if len(lines) % 5:
        raise CaptureError(f"{path} has {len(lines)} data lines, not a multiple of 5: a .log trajectory holds, per "
                           "frame, an 'id id n' line and the 4 rows of a camera-to-world matrix")
    ids, cam_to_world = [], []
    for b in range(0, len(lines), 5):
        ids.append(_numbers(path, lines[b][1], 3, lines[b][0])[0])
        cam_to_world.append([_numbers(path, line, 4, k) for k, line in lines[b + 1:b + 5]])
    return np.linalg.inv(np.asarray(cam_to_world, dtype=np.float64).reshape(-1, 4, 4)), ids


def _read_tum(path: Path) -> tuple[np.ndarray, list[float]]:
    """TUM: 'id tx ty tz qx qy qz qw' per line, camera to world."""
    rows = np.array([_numbers(path, line, 8, k) for k, line in _data_lines(path)]).reshape(-1, 8)
    quaternions = rows[:, 4:8]
    norms = np.linalg.norm(quaternions, axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-3):
        raise CaptureError(f"{path}: quaternion {int(np.argmax(np.abs(norms - 1)))} is not of unit length; a TUM "
                           "line is 'id tx ty tz qx qy qz qw' (scalar last)")
    cam_to_world = np.tile(np.eye(4), (len(rows), 1, 1))
    cam_to_world[:, :3, :3] = Rotation.from_quat(quaternions).as_matrix()
    cam_to_world[:, :3, 3] = rows[:, 1:4]
    return np.linalg.inv(cam_to_world), rows[:, 0].tolist()


def _read_trajectory_json(path: Path) -> tuple[np.ndarray, None]:
    """Open3D PinholeCameraTrajectory JSON: parameters[i].extrinsic, world to camera, column-major."""
    data = load_json(path)
    try:
        extrinsics = [np.asarray(p["extrinsic"], dtype=np.float64).reshape(4, 4).T for p in data["parameters"]]
    except (KeyError, TypeError, ValueError):
        raise CaptureError(f"{path} is not an Open3D PinholeCameraTrajectory JSON (\"parameters\": a list of "
                           "{\"extrinsic\": 16 numbers, column-major}); write it with "
                           "o3d.io.write_pinhole_camera_trajectory") from None
    return np.asarray(extrinsics).reshape(-1, 4, 4), None


def _read_npy(path: Path) -> tuple[np.ndarray, None]:
    """(n, 4, 4) world-to-camera transforms."""
    try:
        poses = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise CaptureError(f"cannot read pose file {path} ({e}); save an (n, 4, 4) array with numpy.save") from None
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise CaptureError(f"{path} holds an array of shape {poses.shape}; poses must be (n, 4, 4) world-to-camera "
                           "transforms")
    return poses.astype(np.float64), None
