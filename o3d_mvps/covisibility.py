"""Which frames see a reference view's surface (covisibility), and which to refine it with.

A capture that goes around the object (a 360-degree ring) has frames that see the reference's
surface from behind or not at all; such frames only add outliers to the reference's data
term. For a reference frame, its object surface is unprojected from its depth (and mask) with
its intrinsics; each other frame's *covisibility* is the fraction of that surface's pixels
that the frame sees: the point projects inside the frame, in front of it, faces it within
``max_angle_deg`` and is not hidden behind that frame's own depth measurement (when the frame
has one there). Pixels, not surface area: the data term is a sum over the reference's pixels,
and a sensor's mixed depths along a silhouette in front of a wall look like steep surface of
large area (weighted by area, a room scene's neighbouring frames seemed to see 38 % of the
reference, with pixels 83 %). Open3D-free: NumPy arrays in, NumPy arrays out.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from .depth_to_colour import register_depth
from .errors import CaptureError
from .model.camera import backproject, project, scale_intrinsics, transform
from .model.normals import perspective_normals
from .model.resampling import block_average, blend_into_mean, harmonic_fill, masked_gaussian, resample_valid
from .model.robust import nan_median
from .model.warping import in_view

logger = logging.getLogger(__name__)

#: Default least covisibility of a frame kept for a reference (fraction of its surface seen).
MIN_COVISIBILITY = 0.4
#: Default largest angle between a surface normal and the direction to a camera that sees it.
MAX_VIEW_ANGLE_DEG = 75.0
#: Default relative depth margin of the occlusion test (a frame's depth in front by more hides a point).
OCCLUSION_TOLERANCE = 0.03
#: Frames besides the reference that a selection always has (else it is an error).
MIN_OTHER_FRAMES = 2
#: A frame "sees most of" the reference when its covisibility is at least this.
MOST_OF_REFERENCE = 0.6
#: Fewer frames than this (besides the reference) that see most of it: the photometric evidence is
#: weak (issue 32 item 3: 8 frames of which 3 saw the reference came out grainy, 64 deg against
#: bicubic's 18), and the refinement leans on the sensor (:func:`o3d_mvps.solving.refine`).
MIN_WELL_COVISIBLE = 3
#: what a refinement with weak coverage leans on (:func:`o3d_mvps.solving.lean_on_sensor`), as
#: its warning says; ``o3d_mvps.reconstruct`` gathers the views whose warning has it into one
WEAK_COVERAGE_NOTE = "10 times its weight, its noise's smoothness and its low frequencies"
#: Widest grid (pixels) the reference surface is taken on. Finite-difference normals of a finer
#: sensor depth map follow its quantisation steps, not the surface (1 mm steps at 0.6 m are
#: several pixels apart at 1000 px wide): at 1064 px a bunny's frames 15 degrees away seemed to
#: see a quarter of it. Covisibility is a coarse measure; a few thousand points are plenty.
SURFACE_WIDTH_PX = 160


def reference_surface(depth: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None,
                      max_width: int = SURFACE_WIDTH_PX) -> tuple[np.ndarray, ...]:
    """Points (m, 3) metres and unit normals (m, 3) toward the camera of a depth map's valid pixels.

    depth: (h, w) metres, 0 = missing; K: (3, 3) intrinsics of that grid; mask: (h, w) bool or
    None. A map wider than ``max_width`` is first area-averaged (over blocks at least half valid) onto a
    grid at most that wide.
    """
    valid = depth > 0 if mask is None else (depth > 0) & mask
    k = -(-depth.shape[1] // max_width)
    if k > 1:
        h, w = depth.shape
        size = (h // k, w // k)
        depth, valid = resample_valid(depth, valid, size, min_valid_fraction=0.5)
        K = scale_intrinsics(K, size[1] / w, size[0] / h)
    normals, area = perspective_normals(depth, K, valid)
    keep = valid & (area > 0)
    return backproject(depth, K)[keep], normals[keep]


def covisibility(points: np.ndarray, normals: np.ndarray, poses: np.ndarray, K: np.ndarray,
                 size: tuple[int, int], depths: list | None = None, *, max_angle_deg: float = MAX_VIEW_ANGLE_DEG,
                 occlusion_tolerance: float = OCCLUSION_TOLERANCE) -> np.ndarray:
    """Fraction (n,) of the reference surface's pixels that each frame sees (module docstring).

    points, normals: (m, 3) reference camera frame; poses: (n, 4, 4) reference ->
    frame i; K: (3, 3) intrinsics of the frames' (H, W) ``size`` grid; depths: None or n entries,
    each None or an (H, W) depth map in metres (0 = missing) on that grid.
    """
    if len(points) == 0:
        raise CaptureError("the reference mask is empty or holds no valid depth (no object surface in frame 0); "
                           "give a mask that covers the object and check frame 0's depth")
    cos_min = np.cos(np.radians(max_angle_deg))
    fractions = np.zeros(len(poses))
    for i, T in enumerate(poses):
        q = transform(T, points)
        u, v, Z = project(q, K)
        seen = in_view(u, v, Z, size)
        facing = -np.einsum("ij,ij->i", normals @ T[:3, :3].T, q) / np.maximum(np.linalg.norm(q, axis=1), 1e-12)
        seen &= facing >= cos_min
        if depths is not None and depths[i] is not None:
            iu = np.rint(np.where(seen, u, 0)).astype(np.int64)
            iv = np.rint(np.where(seen, v, 0)).astype(np.int64)
            measured = depths[i][iv, iu]
            seen &= ~((measured > 0) & (measured < Z * (1 - occlusion_tolerance)))
        fractions[i] = float(seen.mean())
    return fractions


#: A moving camera's reference depth pixel is an outlier (a flying pixel) when the frames that see
#: it measure, by their median, a surface farther than its tolerance in front of or behind it, and
#: at least :data:`OUTLIER_MIN_FRAMES` of them each that far (:func:`reference_depth_outliers`).
#: The tolerance: max(OUTLIER_TOLERANCE_M, OUTLIER_TOLERANCE_REL z, OUTLIER_SIGMAS sigma(z)).
OUTLIER_TOLERANCE_M = 0.005
OUTLIER_TOLERANCE_REL = 0.01
OUTLIER_MIN_FRAMES = 3
#: ... sigma(z) = s z^2 the capture's own depth noise, s measured from the frames' disagreement
#: (:func:`depth_noise_scale`): at 4 sigma a clean Gaussian sensor's tail stays unflagged
#: (the D415-size render, sigma 3.6 mm at 0.6 m: 163 pixels of 22165 flagged at the fixed 6 mm,
#: 5 to 17 mm off, the sensor's own noise, and rim pixels; their drop then started pixels on the wrong side
#: of the bunny's self-occlusions, up to 75 mm off)
OUTLIER_SIGMAS = 4.0
#: ... unless this many of the other frames, their depth moved into the reference
#: (:func:`frame_depths_in_reference`), measure the pixel's own depth within the tolerance: a
#: point beside a self-occlusion is hidden from the frames on the occluder's side (they measure
#: the occluder in front of it, like a flying pixel) and seen by the others. On the D415-size
#: render all 8 pixels the median flagged were such points (their depth 1 to 8 mm off, 2 to 8
#: frames confirming at :data:`SPLAT_FOOTPRINT`); on the peers' render none of the flagged pixels
#: with a true depth (13 to 105 mm off) had more than 1.
OUTLIER_CONFIRMING_FRAMES = 2
#: footprint of the frames' depth samples splatted into the reference
#: (:func:`o3d_mvps.depth_to_colour.register_depth`): the least, 1 (each sample covers its own
#: pixel square), keeps an occluder's edge off the pixels beside it; at its default 1.2 the
#: D415-size render's one point beside a self-occlusion left flagged took the occluder's depth, 18 mm
#: off (its refinement's depth RMSE 0.516 -> 0.527 mm)
SPLAT_FOOTPRINT = 1.0
#: standard deviation (depth pixels) over which the reference's offset from the other frames'
#: median around a flagged pixel is carried into it (:func:`reference_depth_fill`)
FILL_OFFSET_SIGMA_PX = 4.0
#: side (depth pixels) of the window in which a flagged pixel's kept neighbours say which surface
#: it belongs to (:func:`foreground_side`)
FOREGROUND_WINDOW_PX = 3
#: ... a silhouette's depth edge there: the farthest kept neighbour more than this fraction behind
#: the nearest. The room scene's bunny against its wall and table: 0.7 to 1.5; the peers-like
#: bunny's self-occlusions at most 0.13, where the frames' fill is right (taking the nearer side
#: there at 0.10: its flagged object pixels' fill 13.8 -> 21.1 mm RMS)
SILHOUETTE_JUMP_REL = 0.25
#: share of the reference's depth pixels flagged above which the run report warns (the peers'
#: D415-like 640x480 bunny, SF 4: 6.0 %, 83 of its 1384, most along the silhouette)
FLYING_WARNING_FRACTION = 0.15


def _frame_differences(depths: np.ndarray, poses: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, ...]:
    """(v, u) (m,) the reference's valid depth pixels, and (n - 1, m) each for the other frames
    (NaN where a frame does not measure the point): the point's distance outside the envelope
    of the four depth pixels around its projection (0 inside) and its difference from their mean
    (metres, positive: the frame measures the surface behind the point)."""
    z0 = depths[0]
    v, u = np.nonzero(z0 > 0)
    points = backproject(z0[v, u], K, u.astype(np.float64), v.astype(np.float64))
    size = z0.shape
    outside = np.full((len(depths) - 1, len(points)), np.nan)
    difference = np.full_like(outside, np.nan)
    for k, (T, depth) in enumerate(zip(poses[1:], depths[1:])):
        pu, pv, Z = project(transform(T, points), K)
        seen = in_view(pu, pv, Z, size)
        # the frame's surface there lies between its four surrounding depth pixels (valid ones):
        # a point on a steep slope is inside that envelope, a flying pixel centimetres outside
        iu = np.clip(np.floor(np.where(seen, pu, 0)).astype(np.int64), 0, size[1] - 2)
        iv = np.clip(np.floor(np.where(seen, pv, 0)).astype(np.int64), 0, size[0] - 2)
        corners = np.stack([depth[iv, iu], depth[iv, iu + 1], depth[iv + 1, iu], depth[iv + 1, iu + 1]])
        valid = corners > 0
        seen &= valid.any(axis=0)
        low = np.where(valid, corners, np.inf).min(axis=0)
        high = np.where(valid, corners, -np.inf).max(axis=0)
        outside[k, seen] = (np.clip(Z, low, high) - Z)[seen]
        mean = np.where(valid, corners, 0.0).sum(axis=0) / np.maximum(valid.sum(axis=0), 1)
        difference[k, seen] = (mean - Z)[seen]
    return v, u, outside, difference


def depth_noise_scale(difference: np.ndarray, z: np.ndarray) -> float:
    """s (1/m) of the depth noise model sigma(z) = s z^2 (metres; stereo and time-of-flight noise
    grows with the depth squared), from the frames' differences (n - 1, m) metres (NaN: not
    measured) to the reference's points at depths z (m,) metres: the robust spread (1.4826 x the
    median absolute deviation) of their per-point median over z^2, points measured by at least
    :data:`OUTLIER_MIN_FRAMES` frames. The median over frames leaves the reference's own error
    (and a little of the frames'), so sigma(z) is the reference depth's noise; 0 with too few points."""
    enough = np.isfinite(difference).sum(axis=0) >= OUTLIER_MIN_FRAMES
    if enough.sum() < 10:
        return 0.0
    ratio = nan_median(difference[:, enough]) / z[enough] ** 2
    return 1.4826 * float(np.median(np.abs(ratio - np.median(ratio))))


def outlier_tolerance(z: np.ndarray, noise_scale: float) -> np.ndarray:
    """Metres (like z, metres): ``max(OUTLIER_TOLERANCE_M, OUTLIER_TOLERANCE_REL z, OUTLIER_SIGMAS
    noise_scale z^2)``, the disagreement with the other frames that makes a depth an outlier."""
    z = np.asarray(z, dtype=np.float64)
    return np.maximum(np.maximum(OUTLIER_TOLERANCE_M, OUTLIER_TOLERANCE_REL * z), OUTLIER_SIGMAS * noise_scale * z**2)


def reference_depth_outliers(depths: np.ndarray, poses: np.ndarray, K: np.ndarray, *,
                             warped: np.ndarray | None = None, return_noise: bool = False) -> np.ndarray:
    """(h, w) bool: reference depth pixels the other frames' depth contradicts (flying pixels).

    A sensor's flying pixels along silhouettes and depth edges (a mixture of the near and far
    depth, centimetres off) fall anew in every frame; depth fusion averages them away, a prior on
    the reference frame's depth alone keeps them. Each valid reference pixel's point is moved into
    every other frame (``poses``: (n, 4, 4) reference -> frame i) and compared with that frame's
    depth: its distance outside the least and greatest of the four depth pixels around it (valid
    ones; 0 inside, so steep slopes pass). It is flagged where at least :data:`OUTLIER_MIN_FRAMES`
    frames measure it, the median distance exceeds :func:`outlier_tolerance` (the capture's own
    noise at 4 sigma, :func:`depth_noise_scale`, at least 5 mm and 1 %) and at least
    :data:`OUTLIER_MIN_FRAMES` frames each measure a distance beyond it, and fewer than
    :data:`OUTLIER_CONFIRMING_FRAMES` frames moved into the reference confirm its depth (true
    points beside a self-occlusion). The static camera's rule
    (:func:`o3d_mvps.capture.static.reference_depth_outliers`) is this one with identity poses
    and a fixed tolerance.

    depths: (n, h, w) metres on the depth grid (0 = missing); K: (3, 3) its intrinsics.
    warped: (n - 1, h, w) :func:`frame_depths_in_reference` of these, if already made.
    return_noise: also return the noise scale s (1/m) of :func:`depth_noise_scale`.
    """
    depths = np.asarray(depths, dtype=np.float64)
    z0 = depths[0]
    v, u, outside, difference = _frame_differences(depths, poses, K)
    z = z0[v, u]
    noise = depth_noise_scale(difference, z)
    tolerance = outlier_tolerance(z, noise)
    beyond = (np.abs(np.nan_to_num(outside)) > tolerance).sum(axis=0)
    counts = np.isfinite(outside).sum(axis=0)
    flagged = ((counts >= OUTLIER_MIN_FRAMES) & (beyond >= OUTLIER_MIN_FRAMES)
               & (np.abs(np.nan_to_num(nan_median(outside))) > tolerance))
    if flagged.any():
        if warped is None:
            warped = frame_depths_in_reference(depths, poses, K)
        seen = warped[:, v[flagged], u[flagged]]
        confirming = ((seen > 0) & (np.abs(seen - z[flagged]) <= tolerance[flagged])).sum(axis=0)
        flagged[np.nonzero(flagged)[0][confirming >= OUTLIER_CONFIRMING_FRAMES]] = False
    out = np.zeros(z0.shape, dtype=bool)
    out[v[flagged], u[flagged]] = True
    return (out, noise) if return_noise else out


def frame_depths_in_reference(depths: np.ndarray, poses: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(n - 1, h, w) metres: every other frame's depth (``depths`` (n, h, w), 0 = missing) moved
    into the reference camera by ``poses`` (n, 4, 4) reference -> frame i, each sample splatted
    with a z-buffer onto the reference's depth grid of intrinsics K (3, 3)
    (:func:`o3d_mvps.depth_to_colour.register_depth`); 0 where none lands."""
    h, w = depths[0].shape
    return np.stack([register_depth(depth, K, K, np.linalg.inv(T), (w, h), footprint=SPLAT_FOOTPRINT)
                     for T, depth in zip(poses[1:], depths[1:])]).astype(np.float64)


def reference_depth_fill(depths: np.ndarray, poses: np.ndarray, K: np.ndarray, flagged: np.ndarray,
                         noise_scale: float = 0.0, *,
                         warped: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depths for the reference's flagged pixels: (values (h, w) metres, 0 off ``flagged``;
    from_frames (h, w) bool, the flagged pixels filled from the other frames; foreground (h, w)
    bool, those given their nearer neighbours' depth by :func:`foreground_side`).

    The other frames' depth moved into the reference (:func:`frame_depths_in_reference`): where
    at least :data:`OUTLIER_MIN_FRAMES` of them, and half of those that land there, agree within
    :func:`outlier_tolerance` of their median, that median plus the reference's own offset from
    the frames' median around the pixel (a Gaussian of :data:`FILL_OFFSET_SIGMA_PX`, over its kept
    pixels where the frames agree: a sensor's low-frequency error and a pose's small error stay
    consistent with the neighbours). Elsewhere the harmonic fill of the kept and frame-filled
    pixels (:func:`o3d_mvps.model.resampling.harmonic_fill`; a sensor that sees the rim from one
    side only). Without the fill a dropped pixel starts from its nearest kept one, at a
    self-occlusion often the other side's, and no prior pulls it back. Last, no value behind the
    reference's own nearest kept neighbour (:func:`foreground_side`): past a thin object's
    silhouette the frames agree on the wall behind it.

    depths: (n, h, w) metres (0 = missing); poses: (n, 4, 4); K: (3, 3) the depth grid's
    intrinsics; flagged: (h, w) bool (:func:`reference_depth_outliers`); noise_scale: its s (1/m);
    warped: (n - 1, h, w) :func:`frame_depths_in_reference` of these, if already made.
    """
    depths = np.asarray(depths, dtype=np.float64)
    z0 = depths[0]
    flagged = np.asarray(flagged, dtype=bool) & (z0 > 0)
    if warped is None:
        warped = frame_depths_in_reference(depths, poses, K)
    landed = warped > 0
    median = np.nan_to_num(nan_median(np.where(landed, warped, np.nan)))
    tolerance = outlier_tolerance(median, noise_scale)
    agree = (landed & (np.abs(warped - median) <= tolerance)).sum(axis=0)
    consistent = (agree >= OUTLIER_MIN_FRAMES) & (2 * agree >= landed.sum(axis=0)) & (median > 0)
    kept = (z0 > 0) & ~flagged
    offset, weight = masked_gaussian(z0 - median, kept & consistent & (np.abs(z0 - median) <= tolerance),
                                     FILL_OFFSET_SIGMA_PX)
    from_frames = flagged & consistent
    values = np.where(from_frames, median + np.where(weight > 1e-3, offset, 0.0), 0.0)
    rest = flagged & ~from_frames
    if rest.any():
        values = np.where(rest, harmonic_fill(np.where(from_frames, values, z0), kept | from_frames, rest), values)
    values, foreground = foreground_side(z0, kept, flagged, values, noise_scale)
    return np.where(flagged, values, 0.0), from_frames & ~foreground, foreground


#: a moving camera's reference depth pixel takes the mean of the frames (:func:`reference_depth_mean`)
#: where it and at least this many frames in all (itself included) agree within the outlier
#: tolerance: 4, frame 0 and the :data:`OUTLIER_MIN_FRAMES` a flying pixel's verdict needs
MEAN_MIN_FRAMES = OUTLIER_MIN_FRAMES + 1
#: the Gaussian (depth pixels) of the reference depth whose normals carry a frame's depth onto
#: the reference's rays (:func:`frame_depths_on_reference_rays`)
RAY_NORMAL_SIGMA_PX = 2.0
#: ... not where the surface is seen this close to edge-on from the reference (cosine of the angle
#: between its normal and the ray): there a millimetre along a frame's ray is centimetres along it
MIN_RAY_COSINE = 0.2


def surface_frame(depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, ...]:
    """What carries a frame's depth onto the rays of ``depth`` (h, w) metres (0 = none; intrinsics K
    (3, 3)): its valid pixels (v, u) (m,) each, their points (m, 3), the normals of the depth
    smoothed by :data:`RAY_NORMAL_SIGMA_PX` (m, 3), each normal's product with its ray of depth 1
    (m,) and ``steep`` (m,) bool, the pixels seen within :data:`MIN_RAY_COSINE` of edge-on."""
    v, u = np.nonzero(depth > 0)
    smooth, _ = masked_gaussian(depth, depth > 0, RAY_NORMAL_SIGMA_PX)
    normals = perspective_normals(np.where(depth > 0, smooth, 0.0), K)[0][v, u]
    rays = backproject(np.ones(len(v)), K, u.astype(np.float64), v.astype(np.float64))  # z = 1
    along = np.einsum("ij,ij->i", normals, rays)
    steep = np.abs(along) < MIN_RAY_COSINE * np.linalg.norm(rays, axis=1)
    return v, u, rays * depth[v, u][:, None], normals, along, steep


def carried_onto_rays(q: np.ndarray, scale: np.ndarray, T: np.ndarray, normals: np.ndarray, along: np.ndarray,
                      steep: np.ndarray) -> np.ndarray:
    """(m,) metres: the points ``q`` (m, 3) of frame T's camera (T: reference -> frame) moved along
    the frame's rays by ``scale`` (m,) (``q * scale``), carried onto the reference's rays along the
    planes of :func:`surface_frame`'s normals, as reference depths (NaN-free; meaningless where
    ``steep``)."""
    on_ray = transform(np.linalg.inv(T), q * scale[:, None])
    return np.einsum("ij,ij->i", normals, on_ray) / np.where(steep, 1.0, along)


def frame_depths_on_reference_rays(depths: np.ndarray, poses: np.ndarray, K: np.ndarray,
                                   noise_scale: float = 0.0) -> np.ndarray:
    """(n - 1, h, w) metres: what every other frame measures along the reference's rays; 0 where it
    does not.

    Each valid reference pixel's point is moved into frame i (``poses``: (n, 4, 4) reference ->
    frame i) and frame i's depth interpolated bilinearly there (its four depth pixels valid and
    within :func:`outlier_tolerance` of each other: not across a depth edge); the point frame i
    measures on its own ray is carried onto the reference's ray along the surface
    (:func:`carried_onto_rays`). Unlike a z-buffered splat (:func:`frame_depths_in_reference`,
    which keeps the nearest sample in a pixel: D415-like render, 1280x720, true poses, 0.07 to 0.69
    mm nearer than the truth, more the more a frame is turned), a plane is carried exactly.

    depths: (n, h, w) metres (0 = missing); K: (3, 3) the depth grid's intrinsics; noise_scale:
    s (1/m) of :func:`depth_noise_scale`.
    """
    depths = np.asarray(depths, dtype=np.float64)
    size = depths[0].shape
    out = np.zeros((len(depths) - 1, *size))
    v, u, points, normals, along, steep = surface_frame(depths[0], K)
    for k, (T, depth) in enumerate(zip(poses[1:], depths[1:])):
        q = transform(T, points)
        pu, pv, Z = project(q, K)
        seen = in_view(pu, pv, Z, size) & ~steep
        iu = np.clip(np.floor(np.where(seen, pu, 0)).astype(np.int64), 0, size[1] - 2)
        iv = np.clip(np.floor(np.where(seen, pv, 0)).astype(np.int64), 0, size[0] - 2)
        fu, fv = np.where(seen, pu - iu, 0.0), np.where(seen, pv - iv, 0.0)
        c00, c01, c10, c11 = depth[iv, iu], depth[iv, iu + 1], depth[iv + 1, iu], depth[iv + 1, iu + 1]
        low = np.minimum(np.minimum(c00, c01), np.minimum(c10, c11))
        high = np.maximum(np.maximum(c00, c01), np.maximum(c10, c11))
        seen &= (low > 0) & (high - low <= outlier_tolerance(low, noise_scale))
        measured = (1 - fv) * ((1 - fu) * c00 + fu * c01) + fv * ((1 - fu) * c10 + fu * c11)
        t = carried_onto_rays(q, measured / np.where(seen, Z, 1.0), T, normals, along, steep)
        seen &= t > 0
        out[k, v[seen], u[seen]] = t[seen]
    return out


def reference_depth_mean(depths: np.ndarray, poses: np.ndarray, K: np.ndarray,
                         noise_scale: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A moving camera's reference depth from all its frames: (depth (h, w) metres, 0 = none;
    averaged (h, w) bool, the pixels that took the frames' mean).

    What every frame measures along the reference's rays (:func:`frame_depths_on_reference_rays`);
    where frame 0 and at least :data:`MEAN_MIN_FRAMES` frames in all measure a pixel within
    :func:`outlier_tolerance` of their median, the pixel takes their mean; elsewhere frame 0's own
    depth stays, less its offset from the mean nearby (:func:`~.model.resampling.blend_into_mean`).
    A noisy sensor's error is new in every frame (D415-like: white disparity noise and terraces,
    and a low-frequency error of about 1 mm at 0.6 m), so the frames average it where frame 0
    alone would pass its own to the surface (docs/fidelity.md, "The frames' mean depth for a moving
    camera"). Frame 0's holes stay holes; its flying pixels best replaced first
    (:func:`reference_depth_fill`). ``RefineOptions(average_frames_depth="initial")`` ties the depth to it.

    depths: (n, h, w) metres (0 = missing); poses: (n, 4, 4) reference -> frame i; K: (3, 3) the
    depth grid's intrinsics; noise_scale: s (1/m) of :func:`depth_noise_scale`.
    """
    depths = np.asarray(depths, dtype=np.float64)
    z0 = depths[0]
    v, u = np.nonzero(z0 > 0)
    stack = np.concatenate([z0[None], frame_depths_on_reference_rays(depths, poses, K, noise_scale)])[:, v, u]
    valid = stack > 0
    median = nan_median(np.where(valid, stack, np.nan))  # frame 0's own: never NaN
    agree = valid & (np.abs(stack - median) <= outlier_tolerance(median, noise_scale))
    k = agree.sum(axis=0)
    use, mean = np.zeros(z0.shape, dtype=bool), np.zeros(z0.shape)
    use[v, u] = agree[0] & (k >= MEAN_MIN_FRAMES)
    mean[v, u] = np.where(agree, stack, 0.0).sum(axis=0) / np.maximum(k, 1)
    return blend_into_mean(z0, np.where(use, mean, 0.0), use, FILL_OFFSET_SIGMA_PX), use


def foreground_side(z0: np.ndarray, kept: np.ndarray, flagged: np.ndarray, values: np.ndarray,
                    noise_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """(values (h, w) metres, foreground (h, w) bool): ``values`` with each flagged pixel on a
    silhouette (its kept neighbours in the :data:`FOREGROUND_WINDOW_PX` window of the reference's
    own depth ``z0`` (h, w) metres, kept (h, w) bool, span more than :data:`SILHOUETTE_JUMP_REL`
    of the nearest) and farther than :func:`outlier_tolerance` behind the nearest of them given the
    mean of its kept neighbours within that tolerance of the nearest; ``foreground`` marks them.

    A flying pixel mixes the two sides of a depth edge: its footprint covers the nearer surface
    in part, and the mask and the depth prior (area-averaged over the object's colour pixels)
    belong to that surface. Where an object is a few depth pixels wide (the room scene's bunny at
    80 x 60 depth: an ear is 1-2 pixels), every frame's own edge pixels are flying or dropped too,
    so the frames see only the wall past the silhouette and agree on it: 28 of the 45 flagged
    pixels on the object were filled from the wall or table, 0.3 to 0.8 m behind it, and the
    harmonic fill across the edge put others in the empty space between (the 45: 507 mm RMS off
    the object's depth; with this 14 mm). Self-occlusions (smaller jumps) keep the frames' fill.
    flagged: (h, w) bool; values: (h, w) metres, the fill on ``flagged``; noise_scale: s (1/m).
    """
    r = FOREGROUND_WINDOW_PX // 2
    h, w = z0.shape
    pad = np.pad(np.where(kept, z0, np.inf), r, constant_values=np.inf)
    windows = np.stack([pad[dv:dv + h, du:du + w] for dv in range(2 * r + 1) for du in range(2 * r + 1)])
    near = windows.min(axis=0)
    far = np.where(np.isfinite(windows), windows, 0.0).max(axis=0)
    tolerance = outlier_tolerance(np.where(np.isfinite(near), near, 0.0), noise_scale)
    behind = flagged & (far > (1 + SILHOUETTE_JUMP_REL) * near) & (values > near + tolerance)
    side = windows <= near + tolerance  # kept neighbours on the nearest one's side (all inf: none kept, not used)
    mean = np.where(side, windows, 0.0).sum(axis=0) / np.maximum(side.sum(axis=0), 1)
    return np.where(behind, mean, values), behind


def flying_pixels_check(flagged: np.ndarray, from_frames: np.ndarray | None, valid: int, noise_scale: float,
                        foreground: np.ndarray | None = None) -> dict:
    """The run report's row ``{"name", "status", "detail"}`` (``info["inputs"]["checks"]``) of the
    reference's flying pixels: flagged (h, w) bool, from_frames and foreground (h, w) bool
    (:func:`reference_depth_fill`; from_frames None: flagged pixels kept, ``drop_depth_outliers``
    off), valid: the reference's valid depth pixels, noise_scale: s (1/m) of
    :func:`depth_noise_scale`. A warning when more than :data:`FLYING_WARNING_FRACTION` were flagged."""
    count = int(flagged.sum())
    share = count / max(valid, 1)
    detail = (f"{count} of the reference's {valid} depth pixels ({share:.2%}) contradicted by the other frames' depth "
              f"(flying pixels; noise {1000 * noise_scale:.2f} mm at 1 m): ")
    if from_frames is None:
        detail += "kept (RefineOptions(drop_depth_outliers=False); the default replaces them)" if count else "none"
    else:
        frames = int(from_frames.sum())
        near = 0 if foreground is None else int(foreground.sum())
        detail += (f"{frames} filled from the frames that agree there, {near} from the nearer side of the depth edge "
                   f"they lie on, {count - frames - near} from their kept neighbours")
    if share > FLYING_WARNING_FRACTION:
        return {"name": "flying pixels", "status": "warning",
                "detail": detail + "; so many suggest poorly registered frames or a depth filter that is off"}
    return {"name": "flying pixels", "status": "ok", "detail": detail}


def frames_mean_check(averaged: np.ndarray, valid: int) -> dict:
    """The run report's row ``{"name", "status", "detail"}`` of :func:`reference_depth_mean`:
    averaged (h, w) bool, the pixels that took the frames' mean; valid: the reference's valid depth
    pixels."""
    count = int(averaged.sum())
    return {"name": "frames' mean depth", "status": "ok",
            "detail": f"{count} of the reference's {valid} depth pixels ({count / max(valid, 1):.2%}) took the mean "
                      "of the frames that agree there (RefineOptions(average_frames_depth='initial')); the rest keep "
                      "frame 0's depth"}


@dataclass
class ViewSelection:
    """The frames chosen for a reference and why the others were left out.

    frames: chosen indices, the reference first. covisibility: {frame index: fraction of the
    reference surface seen}. left_out: {frame index: reason}.
    """

    frames: list
    covisibility: dict
    left_out: dict = field(default_factory=dict)

    def describe(self) -> str:
        """One line: the frames used and, per frame left out, why."""
        used = ", ".join(f"{i} ({self.covisibility[i]:.0%})" for i in self.frames[1:])
        line = f"reference {self.frames[0]}: refined with frames {used}"
        if self.left_out:
            line += "; left out " + ", ".join(f"{i} ({why})" for i, why in sorted(self.left_out.items()))
        return line

    def weak_coverage(self) -> str | None:
        """None when at least :data:`MIN_WELL_COVISIBLE` of the chosen frames see
        :data:`MOST_OF_REFERENCE` of the reference, else one sentence naming how many frames see
        how much (the frames chosen, best first)."""
        seen = sorted(((self.covisibility[i], i) for i in self.frames[1:]), reverse=True)
        well = sum(c >= MOST_OF_REFERENCE for c, _ in seen)
        if well >= MIN_WELL_COVISIBLE:
            return None
        listed = ", ".join(f"frame {i} {c:.0%}" for c, i in seen) or "none"
        return (f"only {well} of the {len(self.covisibility)} other frames see at least {MOST_OF_REFERENCE:.0%} of "
                f"reference frame {self.frames[0]}'s surface ({len(seen)} used: {listed}); "
                f"{MIN_WELL_COVISIBLE} are needed for photometric detail")

    @classmethod
    def from_dict(cls, d: dict) -> "ViewSelection":
        """The selection :meth:`to_dict` gave (e.g. a refinement's ``info["views"]``)."""
        return cls(list(d["frames"]), {int(i): c for i, c in d["covisibility"].items()},
                   {int(i): why for i, why in d["left_out"].items()})

    def to_dict(self) -> dict:
        """JSON-ready: {"frames", "covisibility", "left_out"} with string keys."""
        return {"frames": [int(i) for i in self.frames],
                "covisibility": {str(i): round(float(c), 4) for i, c in self.covisibility.items()},
                "left_out": {str(i): why for i, why in self.left_out.items()}}


def select_views(fractions: np.ndarray, reference: int = 0, *, min_covisibility: float = MIN_COVISIBILITY,
                 max_frames: int | None = None, frame_ids=None) -> ViewSelection:
    """Frames that see at least ``min_covisibility`` of the reference, the best ``max_frames`` of them.

    fractions: (n,) covisibility of each frame (the reference's own entry is ignored).
    frame_ids: names of the n frames in messages and in the result (default 0..n-1).

    Raises
    ------
    CaptureError
        Fewer than two frames besides the reference see enough of it.
    """
    ids = list(range(len(fractions))) if frame_ids is None else [int(i) for i in frame_ids]
    others = sorted((k for k in range(len(fractions)) if k != reference), key=lambda k: -fractions[k])
    chosen, left_out = [], {}
    for k in others:
        if fractions[k] < min_covisibility:
            left_out[ids[k]] = f"sees {fractions[k]:.0%} of the reference surface, below {min_covisibility:.0%}"
        elif max_frames is not None and len(chosen) >= max_frames:
            left_out[ids[k]] = f"sees {fractions[k]:.0%}, but {max_frames} frames that see more were chosen"
        else:
            chosen.append(k)
    covis = {ids[k]: float(fractions[k]) for k in range(len(fractions)) if k != reference}
    if len(chosen) < MIN_OTHER_FRAMES:
        best = ", ".join(f"frame {ids[k]} {fractions[k]:.0%}" for k in others[:4]) or "no other frame"
        raise CaptureError(f"only {len(chosen)} frame(s) see at least {min_covisibility:.0%} of reference frame "
                           f"{ids[reference]}'s surface ({best}); at least {MIN_OTHER_FRAMES} are needed: capture "
                           "frames closer to the reference (15-30 degrees apart) or lower min_covisibility")
    return ViewSelection([ids[reference]] + [ids[k] for k in sorted(chosen)], covis, left_out)


def frames_seeing_reference(capture, poses: np.ndarray, *, min_covisibility: float = MIN_COVISIBILITY,
                            max_frames: int | None = None, frame_ids=None, **options) -> ViewSelection:
    """:func:`select_views` for a :class:`~o3d_mvps.Capture`'s frame 0, from its sensor depth.

    poses: (n, 4, 4) reference -> frame i. The reference surface is frame 0's depth inside its
    mask (the mask block-averaged onto the depth grid, kept where more than half covers it);
    ``options`` go to :func:`covisibility`.
    """
    depth = capture.depth_array(0).astype(np.float64)
    mask = capture.mask_array(0)
    if mask is not None:
        mask = block_average(mask, capture.scale_factor) > 0.5
    points, normals = reference_surface(depth, capture.depth_K(), mask)
    depths = [capture.depth_array(i) for i in range(capture.n_frames)]
    fractions = covisibility(points, normals, np.asarray(poses, dtype=np.float64), capture.depth_K(),
                             capture.depth_size, depths, **options)
    selection = select_views(fractions, 0, min_covisibility=min_covisibility, max_frames=max_frames,
                             frame_ids=frame_ids)
    logger.info(selection.describe())
    return selection
