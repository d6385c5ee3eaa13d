"""Do the given poses fit the depth? Each frame's depth, moved by its pose, against the reference's.

Frame i's depth (on a coarse grid, at most :data:`COARSE_WIDTH` pixels wide) is back-projected
to points, moved into the reference camera by ``T_i^-1`` and projected into the reference's
depth map. A point *agrees* when it lands inside the reference image on valid depth and its z
lies within the depths of the reference's 3x3 neighbourhood, widened by :data:`TOLERANCE` x z
(so slopes and edges of the coarse grid do not count against it). A frame's *agreement* is the
fraction of its points that agree: near 1 for a neighbour under the right pose, small when the
pose is wrong (its points land off the object, in front of it or behind it).

When the given poses disagree, the usual mix-ups are tried (:func:`pose_candidates`): the
inverse (camera-to-world read as world-to-camera), the other TUM quaternion order, transposed
rotations, translations in millimetres, and frames listed in text order; the one that fits is
named with its fix. Every frame must also be *placed* by the given poses: its best agreement
with the reference or the frames looking its way (nearest optical axes), over the points both
cameras can see (no silhouettes, no grazing views), near the frames' median; and moved by
:data:`MOVE_DEG` about an axis of its camera or :data:`MOVE_MM` along one it must not fit clearly
better (a relative test: a wide-baseline frame may agree little with anything, but its true pose
still fits best). The moved poses are judged on a finer grid (:data:`MOVE_WIDTH`) with a graded
measure (:meth:`CoarseDepth.closeness`): a roll about the optical axis slides the points along
the surface by about a coarse pixel, which the 3x3 agreement cannot see. Identity poses are
checked apart: they must fit every frame (a static camera: same pixels, same depth), else the
camera moved.
Open3D-free: NumPy arrays in, NumPy arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.ndimage as ndi

from ..covisibility import MAX_VIEW_ANGLE_DEG
from ..errors import CaptureError
from ..model.camera import backproject, project, scale_intrinsics, transform
from ..model.normals import perspective_normals
from ..model.resampling import resample_valid
from ..model import se3
from ..model.se3 import relative_to_reference
from ..model.warping import in_view, sample_bilinear

#: Widest grid (pixels) the depth maps are compared on.
COARSE_WIDTH = 80
#: Depth margin of agreement, relative to z (2 % is 12 mm at 0.6 m, several sensor noise sigmas).
TOLERANCE = 0.02
#: Least agreement of a frame that counts as evidence (below it, the frame cannot be judged).
MIN_AGREEMENT = 0.25
#: Identity poses (a static camera): every frame shares at least this fraction of its valid depth
#: pixels with the reference (intersection over union) ...
STATIC_OVERLAP = 0.9
#: ... and its depth at those pixels differs by at most this much (median, relative); else the
#: camera moved (a 15-degree orbit of a 0.6 m object: 1-2 %, 0.88 overlap; sensor noise: 0.4 %).
STATIC_DEPTH_CHANGE = 0.015
#: A reading agrees "best" with a frame at this share of the best reading's agreement, and one
#: that does so for more frames than the given reading, with a median agreement higher by
#: CLEAR_MARGIN, is named as the mix-up (frames in text order agree loosely, 0.8 against 0.95).
CLOSE_RATIO, CLEAR_MARGIN = 0.9, 0.03
#: A frame whose best agreement (with the reference or the frames looking its way, over the pixels
#: both see) is below this share of the frames' median is placed wrongly (a 160x120 orbit's frame
#: turned 5 degrees off: 0.49 against 1.0; a 320x240 ring's frame 90 degrees from the reference,
#: true pose: 0.97, turned 5 degrees: 0.41).
OUTLIER_RATIO = 0.5
#: Frames (besides the reference) a frame is also placed on: those looking most nearly its way.
NEIGHBOURS = 3
#: A frame's pose is also off when, turned by MOVE_DEG degrees about an axis of its camera or shifted
#: by MOVE_MM millimetres along one, its :meth:`~CoarseDepth.closeness` to the depth it fits best is
#: higher by more than MOVED_BETTER_BY. Measured on 13 renders (rings, arcs, 45-degree elevation, D415
#: noise, armadillo, a table-and-wall scene, an orbit; 255 frames, docs/input-checks.md): true poses at
#: most 0.007 better (most 0.02-0.1 worse); 5 degrees off about x, y or z (the optical axis) at least
#: 0.016 better, where a frame has MIN_MOVE_POINTS points.
MOVE_DEG, MOVE_MM, MOVED_BETTER_BY = 5.0, 10.0, 0.01
#: Widest grid (pixels) of the moved-pose test (a 5-degree roll moves a point 40 px from the image
#: centre by 3.5 px on it).
MOVE_WIDTH = 160
#: Depth difference (relative to z) at which a point stops counting as close (:meth:`CoarseDepth.closeness`).
CLOSE_TOLERANCE = 0.01
#: Fewest points (seen by both cameras) for that margin; a frame of fewer, m, must fit better by 2 / sqrt(m)
#: (4 binomial sigmas: a 40x30 depth map holds ~20 points of a bunny; its true poses fit up to 0.19 better
#: moved, so 5 degrees off is caught only now and then).
MIN_MOVE_POINTS = 50
#: Most frames (share of those besides the reference) that a check drops for poses that do not place
#: them; more, and the pose file is refused.
MAX_DROPPED = 0.25
#: Least share of a frame's points facing the other camera under the pose for its agreement to count.
MIN_JUDGED = 0.1
#: Cosine of the largest angle between a surface normal and the direction to a camera that sees it.
COS_VIEW = float(np.cos(np.radians(MAX_VIEW_ANGLE_DEG)))
#: Most points taken from one frame.
MAX_POINTS = 4000


@dataclass
class CoarseDepth:
    """A depth map on the coarse grid: depth (h, w) metres (0 = none), K (3, 3), and the 3x3
    neighbourhood's least and largest valid depth (lo, hi; 0 where the pixel has no depth)."""

    depth: np.ndarray
    K: np.ndarray
    lo: np.ndarray = field(repr=False, default=None)
    hi: np.ndarray = field(repr=False, default=None)

    @classmethod
    def of(cls, depth: np.ndarray, K: np.ndarray, width: int = COARSE_WIDTH) -> "CoarseDepth":
        """Area-average ``depth`` (h, w) metres, 0 = none, with intrinsics K onto a grid at most
        ``width`` wide (blocks must be fully valid)."""
        depth = np.asarray(depth, dtype=np.float64)
        h, w = depth.shape
        k = -(-w // width)
        if k > 1:
            size = (h // k, w // k)
            depth, _ = resample_valid(depth, depth > 0, size, min_valid_fraction=1.0)
            K = scale_intrinsics(K, size[1] / w, size[0] / h)
        valid = depth > 0
        lo = ndi.minimum_filter(np.where(valid, depth, np.inf), size=3)
        hi = ndi.maximum_filter(np.where(valid, depth, -np.inf), size=3)
        return cls(depth, K, np.where(valid, lo, 0.0), np.where(valid, hi, 0.0))

    def points(self, visible: bool = False, limit: int = MAX_POINTS) -> tuple:
        """Camera-frame points (m, 3) of the valid pixels and None (every k-th, m <= ``limit``).

        ``visible``: only the pixels measured well enough to be seen from another camera, and
        their unit normals (m, 3, toward this camera) instead of None: all 3x3 neighbours have
        depth (no silhouette, where a sensor's flying pixels lie) and the surface faces this
        camera within :data:`~o3d_mvps.covisibility.MAX_VIEW_ANGLE_DEG` (no grazing view).
        """
        valid = self.depth > 0
        p = backproject(self.depth, self.K)
        keep, normals = valid, None
        if visible:
            normals, _ = perspective_normals(self.depth, self.K, valid)
            facing = -np.einsum("hwc,hwc->hw", normals, p) / np.maximum(np.linalg.norm(p, axis=2), 1e-12)
            keep = ndi.binary_erosion(valid, np.ones((3, 3), bool)) & (facing >= COS_VIEW)
        step = max(1, -(-int(keep.sum()) // limit))
        return p[keep][::step], None if normals is None else normals[keep][::step]

    def agreement(self, points, T: np.ndarray) -> float:
        """Fraction of ``points`` (:meth:`points`' pair, in frame i's camera) that agree with this
        (reference) depth once moved by ``T`` (4, 4; reference -> frame i) into the reference
        (module docstring). With normals, only the points whose surface faces the reference camera
        (within :data:`~o3d_mvps.covisibility.MAX_VIEW_ANGLE_DEG`) under the pose are judged: the
        others cannot be seen from it; when fewer than :data:`MIN_JUDGED` of them face it, 0."""
        q = _judged(points, T)
        if q is None:
            return 0.0
        u, v, Z = project(q, self.K)
        seen = in_view(u, v, Z, self.depth.shape)
        iu = np.rint(np.where(seen, u, 0)).astype(np.int64)
        iv = np.rint(np.where(seen, v, 0)).astype(np.int64)
        lo, hi = self.lo[iv, iu], self.hi[iv, iu]
        margin = TOLERANCE * np.abs(Z)
        with np.errstate(invalid="ignore"):
            hit = seen & (lo > 0) & (Z >= lo - margin) & (Z <= hi + margin)
        return float(hit.mean())

    def closeness(self, points, T: np.ndarray) -> float:
        """Graded :meth:`agreement`: the mean over ``points`` (judged likewise) of
        ``max(0, 1 - r^2)``, ``r`` the depth difference to this depth sampled bilinearly, relative to
        z, over :data:`CLOSE_TOLERANCE` (0 where a point lands off valid depth: outside, or next to
        a pixel without depth). A shift of a fraction of a pixel already lowers it."""
        q = _judged(points, T)
        if q is None:
            return 0.0
        u, v, Z = project(q, self.K)
        seen = in_view(u, v, Z, self.depth.shape)
        z = sample_bilinear(self.depth[..., None], u, v)[:, 0]
        on_depth = sample_bilinear((self.depth > 0).astype(np.float64)[..., None], u, v)[:, 0] > 1 - 1e-9
        r = (Z - z) / np.maximum(Z, 1e-12) / CLOSE_TOLERANCE
        return float(np.where(seen & on_depth, np.maximum(0.0, 1 - r * r), 0.0).mean())


def _judged(points, T: np.ndarray):
    """``points`` (:meth:`CoarseDepth.points`' pair, in frame i's camera) moved by ``T``^-1 into the
    reference camera (m', 3): with normals, only those facing the reference camera; None when there
    are none, or fewer than :data:`MIN_JUDGED` of them face it."""
    points, normals = points
    if len(points) == 0:
        return None
    Tinv = np.linalg.inv(T)
    q = transform(Tinv, points)
    if normals is None:
        return q
    n = normals @ Tinv[:3, :3].T
    judged = -np.einsum("ij,ij->i", n, q) / np.maximum(np.linalg.norm(q, axis=1), 1e-12) >= COS_VIEW
    return q[judged] if judged.mean() >= MIN_JUDGED else None


def frame_agreement(reference: CoarseDepth, frames: list, poses: np.ndarray) -> np.ndarray:
    """Agreement (n,) of each frame's points (``frames``: n (m, 3) arrays, entry 0 unused) under
    ``poses`` (n, 4, 4; reference -> frame i); entry 0 is 1."""
    return np.array([1.0] + [reference.agreement(frames[i], poses[i]) for i in range(1, len(poses))])


def _coarser(depth: np.ndarray, fine: CoarseDepth, K: np.ndarray) -> CoarseDepth:
    """:meth:`CoarseDepth.of` ``depth`` (h, w) at :data:`COARSE_WIDTH`, from its ``fine`` grid where
    whole blocks nest (the same averages of fully valid blocks: 640x360 gives 4 x 4 and 8 x 8 blocks)."""
    h, w = depth.shape
    k_fine, k = -(-w // MOVE_WIDTH), -(-w // COARSE_WIDTH)
    if h % k == 0 and w % k == 0 and k % k_fine == 0 and -(-fine.depth.shape[1] // COARSE_WIDTH) == k // k_fine:
        return CoarseDepth.of(fine.depth, fine.K)
    return CoarseDepth.of(depth, K)


@dataclass
class Candidate:
    """One reading of the given poses: name, world-to-camera matrices (n, 4, 4) of all the
    capture's frames, and the fix that makes the reader use it."""

    name: str
    world_to_camera: np.ndarray
    fix: str


def pose_candidates(given) -> list[Candidate]:
    """The given poses (:class:`~o3d_mvps.capture.poses.GivenPoses`) as read, then the usual
    mix-ups: inverse, the file's other variants (TUM quaternion order), transposed rotations,
    millimetres, frames in text order. Each with its fix, for a file or an array."""
    from .poses import POSE_CONVENTIONS
    from .reading import natural_key

    E = given.world_to_camera
    file = given.path is not None
    out = [Candidate("as given", E, "")]
    if file:
        current = given.options.get("convention") or _format_convention(given.path)
        other = POSE_CONVENTIONS[1 - POSE_CONVENTIONS.index(current)]
        out.append(Candidate(f"{other} (the inverse of what the file is read as, {current})", np.linalg.inv(E),
                             f"read it as {other}: --poses-convention {other} (Python: "
                             f"read_capture_poses(..., convention={other!r}))"))
        for name, variant in given.variants.items():
            out.append(Candidate(name, variant, f"read it with --{name} (Python: "
                                                f"read_capture_poses(..., quaternion_order={name.split()[-1]!r}))"))
    else:
        out.append(Candidate("inverse (camera-to-world given where reference -> frame was meant)", np.linalg.inv(E),
                             "pass the inverse matrices (np.linalg.inv(poses))"))
    transposed = E.copy()
    transposed[:, :3, :3] = np.swapaxes(E[:, :3, :3], 1, 2)
    out.append(Candidate("transposed rotations", transposed,
                         f"transpose the rotation block of every pose in {given.where} (row- and column-major "
                         "mixed up)"))
    if given.options.get("unit", "m") == "m":
        mm = E.copy()
        mm[:, :3, 3] *= 1e-3
        out.append(Candidate("translations in millimetres", mm,
                             "read them in millimetres: --poses-unit mm (Python: read_capture_poses(..., unit='mm'))"
                             if file else "divide the translations by 1000 (metres)"))
    names = given.frame_names
    if names is not None:
        text = sorted(range(len(names)), key=lambda k: names[k])
        natural = sorted(range(len(names)), key=lambda k: natural_key(names[k]))
        if text != natural:  # the file lists frame text[j] at position j: pose of frame natural[i] is E[pos]
            position = {frame: j for j, frame in enumerate(text)}
            order = [position[k] for k in natural]
            out.append(Candidate("frames in text order", E[order],
                                 f"{given.where} lists the poses in the text order of the frame files ("
                                 f"{', '.join(names[k] for k in text[:3])}, ...) but frames are read in natural "
                                 f"order ({', '.join(names[k] for k in natural[:3])}, ...): write the poses in "
                                 "natural order, or name the frames with zero padding (000001.png)"))
    return out


def _format_convention(path) -> str:
    from .poses import FORMAT_CONVENTION

    return FORMAT_CONVENTION[path.suffix.lower()]


@dataclass
class PoseCheck:
    """What :func:`check_poses` found: status "ok" or "warning", one line of detail, the
    agreement of each frame under the poses used, the conventions (JSON-ready), and the frames
    dropped ({index into the checked frames: why}; a few frames the given poses do not place)."""

    status: str
    detail: str
    agreement: list
    conventions: dict
    dropped: dict = field(default_factory=dict)


def check_poses(depths: list, depth_K: np.ndarray, given, frames: list, labels: list,
                min_frames: int = 1, trust: tuple | None = (0.0, 0.0)) -> PoseCheck:
    """Check the given poses against the frames' depth; CaptureError naming the mix-up and its fix.

    A few frames (at most :data:`MAX_DROPPED` of the others, leaving ``min_frames``) that the
    given poses do not place and no mix-up fits are dropped with a warning; more are an error.
    A frame that fits better moved by :data:`MOVES` counts as not placed only where the poses are
    trusted closer than those moves (``trust``); otherwise the refinement is free to move it that
    far, and the detail only says so.

    Parameters
    ----------
    depths : list of (h, w) arrays
        Depth (metres, 0 = none) of the frames used, the reference first.
    depth_K : (3, 3) array
        Depth intrinsics.
    given : GivenPoses
        The poses as given, one per frame of the whole capture.
    frames : list of int
        The capture's indices of ``depths``' frames (poses are picked and re-based on frames[0]).
    labels : list of str
        Each frame's name in messages (``frame 3 (frame_3.png)``).
    min_frames : int
        Least frames (the reference included) left after dropping.
    trust : (metres, radians) or None
        How far the refinement may move the given poses (``SolverInput.pose_trust``; None: freely).
    """
    fine = [CoarseDepth.of(d, depth_K, MOVE_WIDTH) for d in depths]  # for the moved-pose test
    coarse = [_coarser(d, f, depth_K) for d, f in zip(depths, fine)]
    reference, points = coarse[0], [None] + [c.points() for c in coarse[1:]]
    visible = [None] + [c.points(visible=True) for c in coarse[1:]]
    conventions = {"source": given.where, **{k: v for k, v in given.options.items() if v is not None}}
    if len(frames) < 2:
        return PoseCheck("ok", "one frame: nothing to compare", [1.0], conventions)
    poses = relative_to_reference(given.world_to_camera[frames])
    if np.allclose(poses, np.eye(4), atol=1e-9):
        return _check_identity(reference, depths, depth_K, given, labels, conventions)
    candidates = pose_candidates(given)
    scores = np.array([frame_agreement(reference, points, relative_to_reference(c.world_to_camera[frames]))
                       for c in candidates])[:, 1:]  # (candidates, n - 1)
    best = scores.max(axis=0)
    informative = best >= MIN_AGREEMENT
    close = (scores >= np.maximum(MIN_AGREEMENT, CLOSE_RATIO * best)) & informative  # the near-best readings
    close_count = close.sum(axis=1)
    conventions["agreement"] = {c.name: round(float(np.median(s)), 3) for c, s in zip(candidates, scores)}
    table = "; ".join(f"{c.name}: {np.median(s):.0%}" for c, s in zip(candidates, scores))
    k = int(np.argmax(close_count[1:])) + 1
    mixup = close_count[k] > close_count[0] and close_count[k] >= 0.5 * informative.sum()
    clearly = mixup and np.median(scores[k][informative]) > np.median(scores[0][informative]) + CLEAR_MARGIN

    def mixup_error():
        conventions["fits"] = candidates[k].name
        return CaptureError(
            f"the poses in {given.where} do not fit the depth as read, but they fit as {candidates[k].name}: "
            f"{close_count[k]} of {informative.sum()} frames agree best that way, {close_count[0]} as read (median "
            f"share of each frame's depth on the reference's: {table}). Fix: {candidates[k].fix}")

    if clearly:  # another reading fits clearly better: the given one is wrong even where it fits loosely
        raise mixup_error()
    if not informative.any():
        raise CaptureError(
            f"the poses in {given.where} put no frame's depth onto the reference's: at most "
            f"{best.max():.0%} of a frame's depth agrees with {labels[0]} under them or any usual mix-up "
            f"({', '.join(c.name for c in candidates[1:])}). The poses do not belong to these frames (check the "
            "file and the frame order), or the frames do not overlap; without the pose file, registration "
            "estimates the poses")
    # each frame placed under the given poses: on the reference, or on the frames looking its way (a
    # wide-baseline frame may share little with the reference but much with its ring neighbours) ...
    placed = np.array([max([scores[0][i - 1], *_neighbour_agreement(coarse, visible, poses, i)])
                       for i in range(1, len(poses))])
    floor = max(MIN_AGREEMENT, OUTLIER_RATIO * float(np.median(placed)))
    # ... and no better when moved a little: the given pose fits at least as well as its neighbours in SE(3)
    fine_visible = [None] + [c.points(visible=True) for c in fine[1:]]
    moved = [_moved_closeness(fine, fine_visible, poses, i) for i in range(1, len(poses))]
    judged = trust is not None and trust[0] < MOVE_MM * 1e-3 and trust[1] < np.radians(MOVE_DEG)
    better = [m.better and judged for m in moved]
    lost = [i for i in range(1, len(poses)) if placed[i - 1] < floor or better[i - 1]]
    if lost and mixup:
        raise mixup_error()
    if lost:
        why = {i: f"{placed[i - 1]:.0%} agrees" + (f", and {moved[i - 1].describe(labels)}" if better[i - 1] else "")
               for i in lost}
        message = (
            f"the poses in {given.where} do not place {', '.join(labels[i] for i in lost)}: moved by its pose, "
            f"its depth does not sit on {labels[0]}'s nor on that of the frames looking its way, or sits on them "
            f"better with the pose moved a little ("
            f"{'; '.join(f'{labels[i]}: {why[i]}' for i in lost)}; the frames' median {np.median(placed):.0%}), "
            f"and no usual mix-up ({', '.join(c.name for c in candidates[1:])}) fits it. Fix or remove that pose "
            "(and frame), or drop the pose file so registration estimates the poses"
            + ("; if the poses are only a rough start, let the refinement move them: --pose-trust MM DEG "
               f"({MOVE_MM:g} {MOVE_DEG:g} or more; Python: refine(..., pose_trust=(mm, deg)), or False)"
               if any(better[i - 1] for i in lost) else ""))
        if len(lost) > MAX_DROPPED * (len(poses) - 1) or len(poses) - len(lost) < min_frames:
            raise CaptureError(message)
        conventions["fits"] = "as given"
        conventions["dropped"] = {labels[i]: why[i] for i in lost}
        return PoseCheck("warning", f"dropped {len(lost)} frame(s): {message}", [1.0] + scores[0].round(3).tolist(),
                         conventions, {i: f"its pose in {given.where} does not fit its depth ({why[i]})"
                                       for i in lost})
    conventions["fits"] = "as given"
    detail = (f"every frame's depth agrees with the reference or the frames looking its way under the poses of "
              f"{given.where} (median {np.median(placed):.0%} of its pixels, least {placed.min():.0%})")
    rough = [i for i in range(1, len(poses)) if moved[i - 1].better and not judged]
    if rough:
        detail += (f"; {', '.join(f'{labels[i]} ({moved[i - 1].describe(labels)})' for i in rough)}: off by about "
                   "that much, which the refinement may correct (the poses are not trusted closer)")
    far = [i for i in range(1, len(poses)) if scores[0][i - 1] < floor]
    if far:
        detail += (f"; {', '.join(labels[i] for i in far)} overlap the reference too little to be checked "
                   "against it, but agree with the frames looking their way")
    return PoseCheck("ok", detail, [1.0] + scores[0].round(3).tolist(), conventions)


def _looking_its_way(poses: np.ndarray, i: int) -> list:
    """The reference (0) and the :data:`NEIGHBOURS` frames whose optical axes (third rows of
    ``poses``' rotations, (n, 4, 4) reference -> frame) are nearest to frame i's. Nearest in
    viewing direction, not in the list: a reference's frames are listed by index, so on a ring
    the frames next to i in the list may be on the far side of the object."""
    axes = poses[:, 2, :3] / np.linalg.norm(poses[:, 2, :3], axis=1, keepdims=True)
    return [0] + [int(j) for j in np.argsort(-(axes @ axes[i])) if j not in (0, i)][:NEIGHBOURS]


def _neighbour_agreement(coarse: list, points: list, poses: np.ndarray, i: int) -> list:
    """Agreement of frame i's ``points`` with the depth of :func:`_looking_its_way`'s frames j
    under the relative poses T_i T_j^-1 (frame j -> frame i)."""
    return [coarse[j].agreement(points[i], poses[i] @ np.linalg.inv(poses[j])) for j in _looking_its_way(poses, i)]


@dataclass
class Moved:
    """Frame i's :meth:`CoarseDepth.closeness` to frame j's depth (the best of
    :func:`_looking_its_way`'s under the given pose), ``given`` under its pose and ``best`` under
    the best of the moves (``move``, e.g. "turned 5 degrees about its z axis (the optical axis)");
    ``points``: how many of its points were judged."""

    j: int
    given: float
    best: float
    move: str
    points: int

    @property
    def better(self) -> bool:
        """The pose is off: a move fits clearly better (:data:`MOVED_BETTER_BY`, more for few points)."""
        margin = MOVED_BETTER_BY if self.points >= MIN_MOVE_POINTS else 2.0 / np.sqrt(max(self.points, 1))
        return self.best > self.given + margin

    def describe(self, labels: list) -> str:
        return (f"{self.move} it would fit {labels[self.j]}'s depth better ({self.best:.0%} of its points close "
                f"against {self.given:.0%})")


#: The moves of :func:`_moved_closeness`: (name, twist (6,) translation first, applied on the left of
#: a pose; the name says how the camera moves: the opposite way to the scene in its coordinates).
MOVES = [(f"with its camera {'turned' if r else 'shifted'} {MOVE_DEG if r else MOVE_MM:g} "
          f"{'degrees about' if r else 'mm along'} its {'+' if sign < 0 else '-'}{'xyz'[axis]} axis"
          + (" (the optical axis)" if r and axis == 2 else ""),
          np.eye(6)[3 * r + axis] * sign * (np.radians(MOVE_DEG) if r else MOVE_MM * 1e-3))
         for r in (1, 0) for axis in range(3) for sign in (-1.0, 1.0)]


def _moved_closeness(coarse: list, points: list, poses: np.ndarray, i: int) -> Moved:
    """Frame i's closeness under its pose to the depth of the frame it fits best among
    :func:`_looking_its_way`'s, and the most of it under that pose moved by each of :data:`MOVES`
    (turned about the camera's centre, or shifted, in its own axes). A right pose fits better than
    any moved one; a pose off by about a move fits better moved back."""
    js = _looking_its_way(poses, i)
    given = [coarse[j].closeness(points[i], poses[i] @ np.linalg.inv(poses[j])) for j in js]
    j = js[int(np.argmax(given))]
    relative = poses[i] @ np.linalg.inv(poses[j])
    scores = [coarse[j].closeness(points[i], se3.exp(twist) @ relative) for _, twist in MOVES]
    k = int(np.argmax(scores))
    return Moved(j, max(given), scores[k], MOVES[k][0], len(points[i][0]))


def _check_identity(reference, depths, depth_K, given, labels, conventions) -> PoseCheck:
    """Identity poses must fit every frame (a static camera): the same pixels, the same depth
    (:data:`STATIC_OVERLAP`, :data:`STATIC_DEPTH_CHANGE`); else the camera moved."""
    moved = []
    for i in range(1, len(depths)):
        d = CoarseDepth.of(depths[i], depth_K).depth
        a, b = d > 0, reference.depth > 0
        overlap = (a & b).sum() / max((a | b).sum(), 1)
        change = float(np.median(np.abs(d[a & b] / reference.depth[a & b] - 1))) if (a & b).any() else 1.0
        if overlap < STATIC_OVERLAP or change > STATIC_DEPTH_CHANGE:
            moved.append((change, overlap, i))
    conventions["fits"] = "identity (static camera)"
    if moved:
        change, overlap, i = max(moved)
        conventions["fits"] = None
        raise CaptureError(
            f"every pose in {given.where} is the identity (a static camera), but the frames moved: {labels[i]}'s "
            f"depth differs from {labels[0]}'s at the same pixels by {change:.1%} (median) and they share "
            f"{overlap:.0%} of their depth pixels ({len(moved)} of {len(depths) - 1} frames moved; a static camera "
            f"changes less than {STATIC_DEPTH_CHANGE:.1%} and shares over {STATIC_OVERLAP:.0%}). Remove the pose "
            "file (or initial_poses) so registration estimates the poses, or give the real poses")
    return PoseCheck("ok", "identity poses, and every frame's depth matches the reference's pixel for pixel: a "
                           "static camera", [1.0] * len(depths), conventions)
