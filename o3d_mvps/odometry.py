"""Initial camera poses by registering the low-resolution depth clouds (Open3D ICP and global registration).

Each depth frame (h, w) in metres is lightly denoised (normalised Gaussian convolution over
valid pixels, ``SMOOTH_PX``), its silhouette is eroded by one pixel (unless that leaves fewer than
``4 * MIN_POINTS`` points), and it is back-projected with the depth intrinsics into a point cloud
with normals (from the depth grid, :func:`grid_normals`, or the nearest points) and the colour
area-averaged onto the depth grid. When the frames have object masks (given, or automatic), a
cloud keeps the object only (:func:`registration_region`): in a room the table and wall outnumber
the object's points and ICP slid along the table, where a rotation about its normal costs
nothing. On a rendered room scene (320 x 240, 20 frames 18 deg apart, automatic masks) frame 2
was 51 mm off and frames 4-19 stayed where the chain started them (18-174 deg off); on the object
alone frames 1-3 and 17-19 are 0.9-4.5 deg off (a margin of table around the object, 8 % of its
size, gave 2-17 deg).

Each ICP runs coarse to fine on a pyramid of voxel-downsampled clouds (:func:`cloud_pyramid`,
``ICP_VOXELS``: 6 mm, 3 mm, 1 mm), built once per frame, its normals averaged per voxel from the
finest cloud's: the cost is bounded by the object's area rather than the pixel count (a rendered
2-megapixel capture's 20 frames registered in 2.7 s of CPU, 2.7x less than full-resolution ICP
at aacda76 in the same run, with the same pose errors, ``benchmarks/results/registration.json``;
with the depth grid's normals 1.8-2.3 s against 3.8-4.2 s with Open3D's in the same run,
``benchmarks/results/registration_normals_2026-11-28.jsonl``).
Open3D's ICP releases the GIL but already runs on every core (OpenMP), so frames are registered
one after the other.

The registration chain (:func:`register_frames`), per frame i, until one step is accepted:

1. multi-scale point-to-plane ICP to the reference frame 0, starting from the previous frame's
   pose (``o3d.pipelines.registration.registration_icp``, distances ``ICP_DISTANCES``);
2. the same ICP to the previous registered frame, chained onto its pose;
3. global registration to the reference: FPFH features and RANSAC
   (``registration_ransac_based_on_feature_matching``) and the ICP results refused only for their
   step size, each refined by coloured ICP (``registration_colored_icp``); the best is accepted
   at a stricter fitness (``GLOBAL_MIN_FITNESS``). For wide baselines, where ICP has no good start
   or its (right) answer lies farther from the start than the step check allows.

A step is accepted when its fitness is at least ``MIN_FITNESS`` and it moves the camera less than
``MAX_STEP_DEG`` / ``MAX_STEP_M`` from where it started; a frame with fewer than ``MIN_POINTS``
depth points cannot be registered. A frame no step registers is dropped with a warning naming it
and each step's cause, while at least ``MIN_FRAMES`` frames remain (``strict=True`` makes it an
error).

Direction (pinned by ``tests/test_odometry.py``): registering ``source`` = reference cloud onto
``target`` = frame-i cloud gives the transform mapping reference-camera coordinates to frame-i
camera coordinates, i.e. ``T_i`` of the package's convention (docs/capture-guide.md, "Poses").

Why not RGB-D odometry (``o3d.t.pipelines.odometry.rgbd_odometry_multi_scale``), measured on
``render_capture('bunny', scale_factor=4, light='led')``: point-to-plane odometry on the
native depth grid (80 x 60 at 320 x 240) has too few pixels for its image pyramid (singular
systems, a 18 deg failure on the 8-frame orbit) and on depth upsampled to colour size it stalls
at the initial pose; hybrid odometry at colour size reaches 1.3 deg on the 8-frame orbit but is
biased by the LED moving with the camera (1.3 deg even without noise, where ICP gets 0.74 deg)
and diverges on ``trajectory='orbit-translate'`` (3-5 deg, sometimes tens of degrees). ICP is
the most accurate and robust; see ``register_frames`` for its figures.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import cv2
import numpy as np
import open3d as o3d
from scipy import ndimage

from .errors import OdometryError
from .model.camera import backproject
from .model.normals import perspective_normals
from .model.resampling import masked_gaussian
from .model.se3 import rotation_angle_deg

METHODS = ("point_to_plane",)

#: Std (LR pixels) of the normalised Gaussian smoothing of the depth before back-projection.
SMOOTH_PX = 0.7
#: A cloud of at least this many points (before the voxel's thinning) takes the normals of its
#: depth grid (:func:`grid_normals`); a smaller one Open3D's plane fit of its nearest points
#: (:func:`estimate_normals`), cheap there. The k-d tree's fit was half the registration's CPU on
#: D415 frames (11 000-21 000 points) and 2 MP ones (58 000); the grid's halved the registration's
#: CPU and gave poses as close to the truth at D415 size (0.009 deg further on average at 2 MP).
#: On smaller clouds it did worse: 640x480 renders (SF 2, 5 100 points) 0.153 -> 0.166 deg mean,
#: and on the 80x60 room scene of tests/test_scenes.py (260 points, 8 mm a pixel) the chain
#: drifted, frames 16-19 17-24 deg off against 1.4-7.0 (docs/performance.md, "Registration
#: normals from the depth grid")
GRID_NORMALS_MIN_POINTS = 8000
#: Std (LR pixels) of the normalised Gaussian smoothing of the depth before the grid's normals.
NORMAL_SMOOTH_PX = 1.0
#: Radius (m) and neighbour cap of Open3D's normal estimation (the global registration's radius:
#: two of its voxels).
NORMAL_RADIUS = 0.02
NORMAL_MAX_NN = 40
#: Maximum correspondence distances (m) of the coarse-to-fine ICP levels ...
ICP_DISTANCES = (0.03, 0.015, 0.008)
#: ... the voxel (m) each level's clouds are downsampled to (None: the full cloud; the finest
#: voxel bounds a frame's points by the object's area, whatever the resolution) ...
ICP_VOXELS = (0.006, 0.003, 0.001)
#: A finest cloud with more points than this (a whole room, when no mask keeps the object) is
#: downsampled further, to about this many (an object frame has 10-30k at 1 mm).
MAX_CLOUD_POINTS = 30_000
#: ... and each level's iteration cap (it stops earlier when fitness and RMSE change by less than
#: ICP_RELATIVE_CHANGE).
ICP_MAX_ITERATIONS = (30, 30, 30)
ICP_RELATIVE_CHANGE = 1e-6
#: A frame needs at least this many valid depth points.
MIN_POINTS = 50
#: A registration is accepted when at least this fraction of the source points has a
#: correspondence within the finest distance ...
MIN_FITNESS = 0.3
#: ... and it moves the camera by less than this much from where it started.
MAX_STEP_DEG = 30.0
MAX_STEP_M = 0.3
#: Global registration: voxel of the FPFH clouds (at least GLOBAL_VOXEL m, or this many point
#: spacings of the source cloud), feature radius in voxels, RANSAC budget.
GLOBAL_VOXEL = 0.005
GLOBAL_VOXEL_SPACINGS = 1.5
FPFH_RADIUS_VOXELS = 5
GLOBAL_MIN_FITNESS = 0.6
RANSAC_ITERATIONS, RANSAC_CONFIDENCE = 100_000, 0.999
#: Frames never dropped below this count (a refinement needs a reference and two views).
MIN_FRAMES = 3

#: The fix for each kind of failure, quoted in the messages.
FIXES = {
    "points": "bring the object into the depth range (or raise max_depth), or remove the frame",
    "fitness": "the frames overlap too little: record with smaller steps between frames, or give poses from "
               "another tool (--poses FILE)",
    "step": "the frame is far from its starting estimate (a wide baseline): give poses from another tool "
            "(--poses FILE), or record with smaller steps between frames",
}


@dataclass
class Attempt:
    """One registration step of a frame: what it was, and why it was refused (None: accepted)."""

    step: str
    T: np.ndarray
    fitness: float
    failure: str | None = None
    kind: str | None = None  # key of FIXES


@dataclass
class FrameRegistration:
    """Poses of the registered frames of a capture.

    frames: indices (into the capture) of the frames kept, reference first. poses: (len(frames),
    4, 4) float64, reference -> frame. steps: for every kept frame index, the chain step that
    registered it. dropped: for every dropped frame index, why (each step's cause and the fix).
    """

    frames: list
    poses: np.ndarray
    steps: dict = field(default_factory=dict)
    dropped: dict = field(default_factory=dict)


def registration_region(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) bool: the depth-grid pixels a frame's cloud keeps, given its object ``mask`` (H, W)
    at colour resolution: depth pixels more than half covered by the object."""
    h, w = shape
    return cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0.5


def depth_cloud(depth: np.ndarray, K: np.ndarray, max_depth: float = 3.0,
                color: np.ndarray | None = None, region: np.ndarray | None = None,
                voxel: float | None = None, pixel_stride: int = 1,
                normals: bool = True) -> o3d.geometry.PointCloud:
    """Denoised point cloud with camera-facing normals (and colours) of one depth frame.

    Parameters
    ----------
    depth : (h, w) or (h, w, 1) array
        Depth in metres, 0 where missing.
    K : (3, 3) array
        Intrinsic matrix of the depth image (pixels).
    max_depth : float
        Depth at or beyond this many metres is ignored.
    color : (H, W, 3) array, optional
        Linear RGB of the frame at colour resolution (an integer multiple of (h, w)); area-averaged
        onto the depth grid as the points' colours (coloured ICP needs them).
    region : (h, w) bool array, optional
        Pixels to keep (e.g. :func:`registration_region`); None keeps every valid one.
    voxel : float, optional
        Downsample the points (their normals and colours averaged) to this voxel (m), then to
        every k-th point where more than ``MAX_CLOUD_POINTS`` remain (None: every point).
    pixel_stride : int, optional
        Keep every k-th pixel of every k-th row only (after the smoothing): a cloud that the
        voxel and ``MAX_CLOUD_POINTS`` thin anyway, made for less (1: every pixel).
    normals : bool, optional
        Give the points normals: of the depth grid (:func:`grid_normals`, of every pixel before
        the voxel's averaging) where at least ``GRID_NORMALS_MIN_POINTS`` pixels are kept, else
        of the nearest points (:func:`estimate_normals`, after the thinning); False: none.

    Returns
    -------
    o3d.geometry.PointCloud
        Points (m) in the frame's camera coordinates, with unit normals facing the camera.
    """
    z = np.asarray(depth, dtype=np.float64).reshape(np.shape(depth)[:2])
    valid = (z > 0) & (z < max_depth) & np.isfinite(z)
    if region is not None:
        valid &= region
    raw, z = z, _smoothed(z, valid, SMOOTH_PX)
    keep = ndimage.binary_erosion(valid)  # silhouette pixels are the least reliable ...
    if keep.sum() < 4 * MIN_POINTS:  # ... but a small object (e.g. at SF 8) cannot spare them
        keep = valid
    if pixel_stride > 1:
        grid = np.zeros_like(keep)
        grid[::pixel_stride, ::pixel_stride] = True
        keep = keep & grid
    K = np.asarray(K, dtype=np.float64)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(backproject(z, K)[keep]))
    from_grid = normals and np.count_nonzero(keep) >= GRID_NORMALS_MIN_POINTS
    if from_grid:  # averaged per voxel below
        cloud.normals = o3d.utility.Vector3dVector(grid_normals(raw, valid, K)[keep])
    if color is not None:
        low = cv2.resize(np.asarray(color, dtype=np.float32), (z.shape[1], z.shape[0]), interpolation=cv2.INTER_AREA)
        cloud.colors = o3d.utility.Vector3dVector(low[keep].astype(np.float64))
    if voxel is not None:
        cloud = cloud.voxel_down_sample(voxel)
        if len(cloud.points) > MAX_CLOUD_POINTS:  # every k-th point (row-major pixels, so spread evenly)
            cloud = cloud.uniform_down_sample(int(np.ceil(len(cloud.points) / MAX_CLOUD_POINTS)))
    if from_grid:
        return cloud.normalize_normals()
    return estimate_normals(cloud) if normals else cloud


def estimate_normals(cloud: o3d.geometry.PointCloud) -> o3d.geometry.PointCloud:
    """``cloud`` (camera coordinates, m) given unit normals facing the camera, in place: the plane
    of each point's ``NORMAL_MAX_NN`` nearest points within ``NORMAL_RADIUS`` (Open3D); returns it."""
    if len(cloud.points) >= 3:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS, max_nn=NORMAL_MAX_NN))
        cloud.orient_normals_towards_camera_location(np.zeros(3))
    return cloud


def grid_normals(depth: np.ndarray, valid: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(h, w, 3) unit normals facing the camera of a depth frame (m) on its own pixel grid, 0
    off ``valid`` (h, w): the perspective normals
    (:func:`o3d_mvps.model.normals.perspective_normals`) of the depth smoothed over ``valid`` by a
    Gaussian of ``NORMAL_SMOOTH_PX``. The grid's
    neighbours stand in for a nearest-neighbour search on clouds of ``GRID_NORMALS_MIN_POINTS``
    and more: there a k-d tree's plane fit of 40 neighbours (Open3D's ``estimate_normals``) took
    28-64 ms a frame, half the registration's CPU."""
    return perspective_normals(_smoothed(depth, valid, NORMAL_SMOOTH_PX), K, valid)[0]


def _smoothed(z: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """(h, w): depth ``z`` smoothed over the ``valid`` pixels by a Gaussian of ``sigma`` pixels
    (:func:`o3d_mvps.model.resampling.masked_gaussian`), 0 elsewhere."""
    return np.where(valid, masked_gaussian(z, valid, sigma)[0], 0.0)


def _judge(step: str, T: np.ndarray, fitness: float, start: np.ndarray) -> Attempt:
    """Accept a registration result, or name why not (fitness, step size)."""
    move = T @ np.linalg.inv(start)
    angle, shift = rotation_angle_deg(move[:3, :3]), float(np.linalg.norm(move[:3, 3]))
    if not np.all(np.isfinite(T)):
        return Attempt(step, T, fitness, "diverged (non-finite transform)", "step")
    if fitness < MIN_FITNESS:
        return Attempt(step, T, fitness, f"fitness {fitness:.2f} (at least {MIN_FITNESS} needed)", "fitness")
    if angle >= MAX_STEP_DEG or shift >= MAX_STEP_M:
        return Attempt(step, T, fitness, f"fitness {fitness:.2f} passed, but it moved the camera {angle:.0f} deg / "
                       f"{shift * 1000:.0f} mm from its start (at most {MAX_STEP_DEG:g} deg / {MAX_STEP_M:g} m)",
                       "step")
    return Attempt(step, T, fitness)


def cloud_pyramid(cloud: o3d.geometry.PointCloud) -> tuple:
    """The clouds of the ICP levels (``ICP_VOXELS``), coarse to fine: ``cloud`` voxel-downsampled
    (points, normals and colours averaged per voxel, so the normals are estimated once, on
    ``cloud``); the finest level, and any whose voxel is None, is ``cloud`` itself (already at
    the finest voxel: :func:`depth_cloud` with ``voxel=ICP_VOXELS[-1]``)."""
    return tuple(cloud if voxel is None else cloud.voxel_down_sample(voxel) for voxel in ICP_VOXELS[:-1]) + (cloud,)


def _levels(cloud) -> tuple:
    """One cloud per ICP level: a :func:`cloud_pyramid` as it is, a single cloud at every level."""
    return tuple(cloud) if isinstance(cloud, (tuple, list)) else (cloud,) * len(ICP_DISTANCES)


def register(source, target, init: np.ndarray, step: str = "ICP", colored: bool = False) -> Attempt:
    """Multi-scale point-to-plane (or coloured) ICP of ``source`` onto ``target``, judged.

    Parameters
    ----------
    source, target : o3d.geometry.PointCloud or tuple of them
        Clouds with normals (and colours for ``colored``), metres: one cloud used at every level,
        or one per level (:func:`cloud_pyramid`, coarse to fine).
    init : (4, 4) array
        Initial source -> target transform.
    step : str
        Name of the step in messages.
    colored : bool
        Open3D coloured ICP (geometry and colour) instead of point-to-plane.

    Returns
    -------
    Attempt
        ``T`` (4, 4) maps source coordinates to target coordinates; ``fitness`` is the fraction of
        (finest-level) source points with a correspondence within the finest ICP distance;
        ``failure`` is None when the fitness is at least ``MIN_FITNESS`` and the move from ``init``
        is below ``MAX_STEP_DEG`` / ``MAX_STEP_M``.
    """
    init = np.asarray(init, dtype=np.float64)
    sources, targets = _levels(source), _levels(target)
    few = min(len(sources[-1].points), len(targets[-1].points))
    if few < MIN_POINTS:
        return Attempt(step, init, 0.0, f"too few depth points ({few}, at least {MIN_POINTS} needed)", "points")
    reg = o3d.pipelines.registration
    estimation = reg.TransformationEstimationForColoredICP() if colored else reg.TransformationEstimationPointToPlane()
    icp = reg.registration_colored_icp if colored else reg.registration_icp
    T = init
    for src, tgt, distance, iterations in zip(sources, targets, ICP_DISTANCES, ICP_MAX_ITERATIONS):
        if min(len(src.points), len(tgt.points)) < MIN_POINTS:  # a tiny cloud: its coarse levels are skipped
            continue
        criteria = reg.ICPConvergenceCriteria(relative_fitness=ICP_RELATIVE_CHANGE, relative_rmse=ICP_RELATIVE_CHANGE,
                                              max_iteration=iterations)
        try:
            result = icp(src, tgt, distance, T, estimation, criteria)
        except RuntimeError:  # coloured ICP raises when no point has a correspondence
            return Attempt(step, T, 0.0, f"fitness 0 (no correspondence within {distance * 1000:.0f} mm)", "fitness")
        T = np.asarray(result.transformation, dtype=np.float64)
    return _judge(step, T, float(result.fitness), init)


def _fpfh(cloud: o3d.geometry.PointCloud, voxel: float):
    """Voxel-downsampled cloud (with normals) and its FPFH features (radius FPFH_RADIUS_VOXELS voxels)."""
    down = cloud.voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=NORMAL_MAX_NN))
    down.orient_normals_towards_camera_location(np.zeros(3))
    feature = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_RADIUS_VOXELS * voxel, max_nn=100))
    return down, feature


def register_globally(source, target, candidates=(), step: str = "global registration") -> Attempt:
    """Registration of ``source`` onto ``target`` without a trusted start: FPFH + RANSAC, then coloured ICP.

    ``source``, ``target``: clouds or :func:`cloud_pyramid` tuples, as for :func:`register`; the
    features are computed on the finest cloud.

    The RANSAC estimate (seeded with ``o3d.utility.random.seed(0)``, so a capture always
    registers the same way) and the ``candidates`` (4, 4) (e.g. ICP results refused only for
    their step size) are each refined by ICP (coloured ICP for the RANSAC estimate: the LED's
    shading, which moves with the camera, misleads it from a good start); the accepted one of
    highest fitness is returned,
    accepted when its fitness is at least ``GLOBAL_MIN_FITNESS`` (stricter than ICP's: nothing
    vouches for the start). Single views of ~1000 noisy points give unreliable FPFH matches
    (13-25 deg off at 30-45 deg baselines on the rendered bunny), which this threshold refuses.
    """
    pyramids = source, target
    source, target = _levels(source)[-1], _levels(target)[-1]
    few = min(len(source.points), len(target.points))
    if few < MIN_POINTS:
        return Attempt(step, np.eye(4), 0.0, f"too few depth points ({few}, at least {MIN_POINTS} needed)", "points")
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(0)
    spacing = float(np.median(np.asarray(source.compute_nearest_neighbor_distance())))
    voxel = max(GLOBAL_VOXEL, GLOBAL_VOXEL_SPACINGS * spacing)
    (src, src_fpfh), (tgt, tgt_fpfh) = _fpfh(source, voxel), _fpfh(target, voxel)
    distance = 1.5 * voxel
    ransac = reg.registration_ransac_based_on_feature_matching(
        src, tgt, src_fpfh, tgt_fpfh, True, distance, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(RANSAC_ITERATIONS, RANSAC_CONFIDENCE))
    # colour misleads ICP where the LED moves with the camera: the candidates keep point-to-plane ICP
    refined = [register(*pyramids, np.asarray(ransac.transformation), step, colored=True)]
    refined += [register(*pyramids, np.asarray(T), step) for T in candidates]
    best = max(refined, key=lambda a: (a.failure is None, a.fitness))
    if best.failure is None and best.fitness < GLOBAL_MIN_FITNESS:
        best.failure, best.kind = f"fitness {best.fitness:.2f} (at least {GLOBAL_MIN_FITNESS} needed)", "fitness"
    return best


def register_frames(capture, *, strict: bool = False, max_depth: float = 3.0,
                    progress: bool = False) -> FrameRegistration:
    """Register every frame to the reference by the chain of the module docstring; drop what fails.

    Measured on ``render_capture('bunny', scale_factor=4, light='led', seed=0)`` with noise:
    8 frames at 320 x 240 (80 x 60 depth, ~300 object points, 2-15 deg from the reference):
    max 1.7 deg / 16 mm, median 0.8 deg / 8 mm; 20 frames at 640 x 480: max 0.8 deg / 8 mm,
    median 0.5 deg / 5 mm (orbit-translate: 0.9 deg / 10 mm), about 1 s. Without noise at
    320 x 240: max 0.7 deg / 7 mm. The accuracy is limited by the sparse, noisy depth
    (~3.6 mm noise at 0.6 m); the joint refinement improves the poses afterwards. A frame
    50 deg from the reference (tests/test_odometry.py), which ICP cannot register, is found by
    the global step.

    Parameters
    ----------
    capture : Capture
        n >= 1 frames; uses the depth (metres, 0 = missing), colour and the depth intrinsics.
    strict : bool
        Raise OdometryError on the first frame that cannot be registered instead of dropping it.
    max_depth : float
        Depth at or beyond this many metres is ignored.
    progress : bool
        Show a tqdm progress bar over frames.

    Returns
    -------
    FrameRegistration
        Kept frames and their poses ``T_i`` (reference-camera coordinates in metres -> frame-i
        camera coordinates; the reference's is the identity), with a warning per dropped frame.

    Raises
    ------
    OdometryError
        The reference has too few depth points; a frame cannot be registered and ``strict`` is
        set, or dropping it would leave fewer than ``MIN_FRAMES`` frames.
    """
    n = capture.n_frames
    K = np.asarray(capture.depth_K(), dtype=np.float64)
    clouds = [cloud_pyramid(depth_cloud(capture.depth_array(i), K, max_depth, capture.color_array(i),
                                        frame_region(capture, i), ICP_VOXELS[-1])) for i in range(n)]
    if len(clouds[0][-1].points) < MIN_POINTS:
        raise OdometryError(f"the reference frame 0 has only {len(clouds[0][-1].points)} valid depth points below "
                            f"{max_depth} m (at least {MIN_POINTS} are needed): {FIXES['points']}, so that another "
                            "frame becomes the reference")
    result = FrameRegistration(frames=[0], poses=np.eye(4)[None], steps={0: "reference"})
    indices = range(1, n)
    if progress:
        from tqdm.auto import tqdm

        indices = tqdm(indices, desc="registration", unit="frame")
    for i in indices:
        attempts = _register_frame(clouds, i, result)
        accepted = attempts[-1]
        if accepted.failure is None:
            result.frames.append(i)
            result.poses = np.concatenate([result.poses, accepted.T[None]])
            result.steps[i] = accepted.step
            continue
        reason = _failure_message(i, attempts)
        if strict or n - len(result.dropped) - 1 < MIN_FRAMES:
            why = "" if strict else f" (dropping it would leave fewer than {MIN_FRAMES} frames)"
            raise OdometryError(f"{reason}{why}")
        result.dropped[i] = reason
        warnings.warn(f"{reason}. Frame {i} is dropped; pass strict=True (--strict) to stop instead", stacklevel=2)
    return result


def frame_region(capture, i: int) -> np.ndarray | None:
    """Frame i's :func:`registration_region`, or None when its mask is missing or empty (an empty
    reference mask is reported by the solver, which names it)."""
    mask = capture.mask_array(i)
    return None if mask is None or not mask.any() else registration_region(mask, capture.depth_size)


def _register_frame(clouds: list, i: int, result: FrameRegistration) -> list[Attempt]:
    """The chain for frame i (see the module docstring), on every frame's :func:`cloud_pyramid`
    ``clouds``; the last attempt is the accepted one if any."""
    previous, T_previous = result.frames[-1], result.poses[-1]
    attempts = [register(clouds[0], clouds[i], T_previous, "ICP to the reference frame 0")]
    if previous != 0 and attempts[-1].failure is not None:
        chained = register(clouds[previous], clouds[i], np.eye(4), f"ICP to frame {previous}")
        chained.T = chained.T @ T_previous
        attempts.append(chained)
    if attempts[-1].failure is not None:
        # ICP results refused only for their step size are candidates the global step verifies
        candidates = [a.T for a in attempts if a.kind == "step"]
        found = register_globally(clouds[0], clouds[i], candidates,
                                  "global registration (FPFH + RANSAC, coloured ICP) to frame 0")
        attempts.append(found)
    return attempts


def _failure_message(i: int, attempts: list[Attempt]) -> str:
    """'cannot register frame i: <step>: <cause>; ...; fix: ...' naming each distinct fix once."""
    causes = "; ".join(f"{a.step}: {a.failure}" for a in attempts)
    fixes = "; ".join(dict.fromkeys(FIXES[a.kind] for a in attempts))
    return f"cannot register frame {i}: {causes}. Fix: {fixes}"


def initial_poses(capture, *, method: str = "point_to_plane", max_depth: float = 3.0, progress: bool = False) -> np.ndarray:
    """Poses (n, 4, 4) of every frame of a capture: :func:`register_frames` with ``strict=True``
    (same arguments), so a frame that cannot be registered raises OdometryError instead of
    being dropped. ``method``: "point_to_plane", the only one (ValueError otherwise).
    """
    if method not in METHODS:
        raise ValueError(f"initial_poses: unknown method {method!r}; use one of {list(METHODS)}")
    if capture.n_frames == 1:
        return np.eye(4)[None]
    return register_frames(capture, strict=True, max_depth=max_depth, progress=progress).poses
