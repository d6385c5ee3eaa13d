"""Initial camera poses from Open3D point-to-plane ICP on the low-resolution depth (DESIGN section 2).

Each depth frame (h, w) in metres is lightly denoised (normalised Gaussian convolution over
valid pixels, ``SMOOTH_PX``), its silhouette is eroded by one pixel (unless that leaves fewer than
``4 * MIN_POINTS`` points), and it is back-projected
with the depth intrinsics into a point cloud with normals (radius ``NORMAL_RADIUS``). Frame i
is registered to the reference by Open3D's multi-scale point-to-plane ICP
(``o3d.pipelines.registration.registration_icp``, correspondence distances ``ICP_DISTANCES``),
starting from the estimate of frame i - 1; if that fails, frame i is registered to frame i - 1
and the result is chained.

Direction (pinned by ``tests/test_odometry.py``): ICP with ``source`` = reference cloud and
``target`` = frame-i cloud returns the transform mapping reference-camera coordinates to
frame-i camera coordinates, i.e. ``T_i`` of the package's convention.

Why not RGB-D odometry (``o3d.t.pipelines.odometry.rgbd_odometry_multi_scale``), measured on
``render_capture('bunny', scale_factor=4, light='led')``: point-to-plane odometry on the
native depth grid (80 x 60 at 320 x 240) has too few pixels for its image pyramid (singular
systems, a 18 deg failure on the 8-frame orbit) and on depth upsampled to colour size it stalls
at the initial pose; hybrid odometry at colour size reaches 1.3 deg on the 8-frame orbit but is
biased by the LED moving with the camera (1.3 deg even without noise, where ICP gets 0.74 deg)
and diverges on ``trajectory='orbit-translate'`` (3-5 deg, sometimes tens of degrees). ICP is
the most accurate and robust; see ``initial_poses`` for its figures.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy import ndimage

from .errors import OdometryError
from .model.camera import backproject
from .model.se3 import rotation_angle_deg

METHODS = ("point_to_plane",)

#: Std (LR pixels) of the normalised Gaussian smoothing of the depth before back-projection.
SMOOTH_PX = 0.7
#: Radius (m) and neighbour cap of the normal estimation.
NORMAL_RADIUS = 0.02
NORMAL_MAX_NN = 40
#: Maximum correspondence distances (m) of the coarse-to-fine ICP levels.
ICP_DISTANCES = (0.03, 0.015, 0.008)
ICP_MAX_ITERATIONS = 50
#: A frame needs at least this many valid depth points.
MIN_POINTS = 50
#: A registration is accepted when at least this fraction of the source points has a
#: correspondence within the finest distance ...
MIN_FITNESS = 0.3
#: ... and it moves the camera by less than this much from its initial estimate.
MAX_STEP_DEG = 30.0
MAX_STEP_M = 0.3


def depth_cloud(depth: np.ndarray, K: np.ndarray, max_depth: float = 3.0) -> o3d.geometry.PointCloud:
    """Denoised point cloud with camera-facing normals of one depth frame.

    Parameters
    ----------
    depth : (h, w) or (h, w, 1) array
        Depth in metres, 0 where missing.
    K : (3, 3) array
        Intrinsic matrix of the depth image (pixels).
    max_depth : float
        Depth at or beyond this many metres is ignored.

    Returns
    -------
    o3d.geometry.PointCloud
        Points (m) in the frame's camera coordinates, with unit normals facing the camera.
    """
    z = np.asarray(depth, dtype=np.float64).reshape(np.shape(depth)[:2])
    valid = (z > 0) & (z < max_depth) & np.isfinite(z)
    v = valid.astype(np.float64)
    num = ndimage.gaussian_filter(np.where(valid, z, 0.0), SMOOTH_PX, mode="constant")
    den = ndimage.gaussian_filter(v, SMOOTH_PX, mode="constant")
    z = np.where(valid, num / np.maximum(den, 1e-12), 0.0)
    keep = ndimage.binary_erosion(valid)  # silhouette pixels are the least reliable ...
    if keep.sum() < 4 * MIN_POINTS:  # ... but a small object (e.g. at SF 8) cannot spare them
        keep = valid
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(backproject(z, np.asarray(K, dtype=np.float64))[keep]))
    if len(cloud.points) >= 3:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS, max_nn=NORMAL_MAX_NN))
        cloud.orient_normals_towards_camera_location(np.zeros(3))
    return cloud


def register(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, init: np.ndarray) -> tuple[np.ndarray, float, bool]:
    """Multi-scale point-to-plane ICP of ``source`` onto ``target``.

    Parameters
    ----------
    source, target : o3d.geometry.PointCloud
        Clouds with normals (target's are used), metres.
    init : (4, 4) array
        Initial source -> target transform.

    Returns
    -------
    T : (4, 4) float64 array
        Transform mapping source coordinates to target coordinates.
    fitness : float
        Fraction of source points with a correspondence within the finest ICP distance.
    accepted : bool
        Fitness at least ``MIN_FITNESS`` and a step from ``init`` below ``MAX_STEP_DEG`` /
        ``MAX_STEP_M``.
    """
    if len(source.points) < MIN_POINTS or len(target.points) < MIN_POINTS:
        return np.asarray(init, dtype=np.float64), 0.0, False
    reg = o3d.pipelines.registration
    T = np.asarray(init, dtype=np.float64)
    criteria = reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=ICP_MAX_ITERATIONS)
    for distance in ICP_DISTANCES:
        result = reg.registration_icp(source, target, distance, T, reg.TransformationEstimationPointToPlane(), criteria)
        T = np.asarray(result.transformation, dtype=np.float64)
    step = T @ np.linalg.inv(init)
    accepted = bool(np.all(np.isfinite(T)) and result.fitness >= MIN_FITNESS
                    and rotation_angle_deg(step[:3, :3]) < MAX_STEP_DEG and np.linalg.norm(step[:3, 3]) < MAX_STEP_M)
    return T, float(result.fitness), accepted


def initial_poses(capture, *, method: str = "point_to_plane", max_depth: float = 3.0, progress: bool = False) -> np.ndarray:
    """Camera poses of every frame relative to the reference, from Open3D ICP on the depth.

    Frame i is registered directly to the reference (frame 0) starting from the estimate of
    frame i - 1 (the camera moves little between frames). When that fails (fitness below
    ``MIN_FITNESS`` or an implausible jump), frame i is registered to frame i - 1 and chained:
    ``T_i = T_{i-1 -> i} @ T_{i-1}``.

    Measured on ``render_capture('bunny', scale_factor=4, light='led', seed=0)`` with noise:
    8 frames at 320 x 240 (80 x 60 depth, ~300 object points, 2-15 deg from the reference):
    max 1.7 deg / 16 mm, median 0.8 deg / 8 mm; 20 frames at 640 x 480: max 0.8 deg / 8 mm,
    median 0.5 deg / 5 mm (orbit-translate: 0.9 deg / 10 mm), about 1 s. Without noise at
    320 x 240: max 0.7 deg / 7 mm. The accuracy is limited by the sparse, noisy depth
    (~3.6 mm noise at 0.6 m); the joint refinement improves the poses afterwards.

    Parameters
    ----------
    capture : Capture
        n >= 1 frames; uses the depth (metres, 0 = missing) and the depth intrinsics.
    method : {"point_to_plane"}
        Registration method (Open3D point-to-plane ICP).
    max_depth : float
        Depth at or beyond this many metres is ignored.
    progress : bool
        Show a tqdm progress bar over frames.

    Returns
    -------
    (n, 4, 4) float64 array
        ``T_i`` mapping reference-camera coordinates (metres) to frame-i camera coordinates;
        ``T_0`` is the identity.

    Raises
    ------
    OdometryError
        When a frame has too few valid depth points or registers neither to the reference
        nor to its predecessor.
    ValueError
        On an unknown ``method``.
    """
    if method not in METHODS:
        raise ValueError(f"initial_poses: unknown method {method!r}; use one of {list(METHODS)}")
    n = capture.n_frames
    poses = np.tile(np.eye(4), (n, 1, 1))
    if n == 1:
        return poses
    K = np.asarray(capture.depth_K(), dtype=np.float64)
    clouds = [depth_cloud(capture.depth_array(i), K, max_depth) for i in range(n)]
    for i, cloud in enumerate(clouds):
        if len(cloud.points) < MIN_POINTS:
            raise OdometryError(
                f"frame {i} has only {len(cloud.points)} valid depth points below {max_depth} m "
                f"(at least {MIN_POINTS} are needed to register it): drop frame {i} (Capture.select), "
                f"move the object into the depth range, or raise max_depth."
            )
    indices = range(1, n)
    if progress:
        from tqdm.auto import tqdm

        indices = tqdm(indices, desc="odometry", unit="frame")
    for i in indices:
        T, fitness, ok = register(clouds[0], clouds[i], poses[i - 1])
        fitness_prev = 0.0
        if not ok:
            step, fitness_prev, ok = register(clouds[i - 1], clouds[i], np.eye(4))
            T = step @ poses[i - 1]
        if not ok:
            raise OdometryError(
                f"ICP could not register frame {i} to the reference frame 0 (fitness {fitness:.2f}) "
                f"nor to frame {i - 1} (fitness {fitness_prev:.2f}; at least {MIN_FITNESS} needed): "
                f"the frames barely overlap. Move the camera more slowly, drop frame {i} "
                f"(Capture.select), or use fewer frames."
            )
        poses[i] = T
    return poses
