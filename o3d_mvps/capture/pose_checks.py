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
named with its fix. Identity poses are checked apart: they must fit every frame (a static
camera: same pixels, same depth), else the camera moved. Open3D-free: NumPy arrays in, NumPy arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.ndimage as ndi

from ..errors import CaptureError
from ..model.camera import backproject, project, scale_intrinsics, transform
from ..model.resampling import resample_valid
from ..model.se3 import relative_to_reference
from ..model.warping import in_view

#: Widest grid (pixels) the depth maps are compared on.
COARSE_WIDTH = 80
#: Depth margin of agreement, relative to z (2 % is 12 mm at 0.6 m, several sensor noise sigmas).
TOLERANCE = 0.02
#: Least agreement of a frame that counts as evidence (below it, the frame cannot be judged).
MIN_AGREEMENT = 0.25
#: A convention fits a frame when its agreement is at least this share of the best convention's.
FIT_RATIO = 0.6
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
#: A frame whose best agreement (with the reference or a neighbour) is below this share of the
#: frames' median is placed wrongly (a frame turned 5 degrees off: 0.39 against 0.95).
OUTLIER_RATIO = 0.5
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

    def points(self, limit: int = MAX_POINTS) -> np.ndarray:
        """(m, 3) camera-frame points of the valid pixels (every k-th, m <= ``limit``)."""
        p = backproject(self.depth, self.K)[self.depth > 0]
        return p[::max(1, -(-len(p) // limit))]

    def agreement(self, points: np.ndarray, T: np.ndarray) -> float:
        """Fraction of ``points`` (m, 3), in frame i's camera, that agree with this (reference)
        depth once moved by ``T`` (4, 4; reference -> frame i) into the reference (module docstring)."""
        if len(points) == 0:
            return 0.0
        q = transform(np.linalg.inv(T), points)
        u, v, Z = project(q, self.K)
        seen = in_view(u, v, Z, self.depth.shape)
        iu = np.rint(np.where(seen, u, 0)).astype(np.int64)
        iv = np.rint(np.where(seen, v, 0)).astype(np.int64)
        lo, hi = self.lo[iv, iu], self.hi[iv, iu]
        margin = TOLERANCE * np.abs(Z)
        with np.errstate(invalid="ignore"):
            hit = seen & (lo > 0) & (Z >= lo - margin) & (Z <= hi + margin)
        return float(hit.mean())


def frame_agreement(reference: CoarseDepth, frames: list, poses: np.ndarray) -> np.ndarray:
    """Agreement (n,) of each frame's points (``frames``: n (m, 3) arrays, entry 0 unused) under
    ``poses`` (n, 4, 4; reference -> frame i); entry 0 is 1."""
    return np.array([1.0] + [reference.agreement(frames[i], poses[i]) for i in range(1, len(poses))])


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
    agreement of each frame under the poses used, and the conventions (JSON-ready)."""

    status: str
    detail: str
    agreement: list
    conventions: dict


def check_poses(depths: list, depth_K: np.ndarray, given, frames: list, labels: list) -> PoseCheck:
    """Check the given poses against the frames' depth; CaptureError naming the mix-up and its fix.

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
    """
    coarse = [CoarseDepth.of(d, depth_K) for d in depths]
    reference, points = coarse[0], [None] + [c.points() for c in coarse[1:]]
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
    fits = (scores >= np.maximum(MIN_AGREEMENT, FIT_RATIO * best)) & informative
    count = fits.sum(axis=1)
    close = (scores >= np.maximum(MIN_AGREEMENT, CLOSE_RATIO * best)) & informative  # the near-best readings
    close_count = close.sum(axis=1)
    k = int(np.argmax(close_count[1:])) + 1
    if close_count[k] > close_count[0] and close_count[k] >= 0.5 * informative.sum() and \
            np.median(scores[k][informative]) > np.median(scores[0][informative]) + CLEAR_MARGIN:
        count[0] = 0  # another reading fits clearly better: the given one is wrong even where it fits loosely
    conventions["agreement"] = {c.name: round(float(np.median(s)), 3) for c, s in zip(candidates, scores)}
    others = labels[1:]
    if not informative.any():
        raise CaptureError(
            f"the poses in {given.where} put no frame's depth onto the reference's: at most "
            f"{best.max():.0%} of a frame's depth agrees with {labels[0]} under them or any usual mix-up "
            f"({', '.join(c.name for c in candidates[1:])}). The poses do not belong to these frames (check the "
            "file and the frame order), or the frames do not overlap; without the pose file, registration "
            "estimates the poses")
    if count[0] == informative.sum():
        conventions["fits"] = "as given"
        detail = (f"every frame's depth agrees with the reference under the poses of {given.where} (median "
                  f"{np.median(scores[0]):.0%} of its pixels)")
        far = [j + 1 for j in np.flatnonzero(~informative)]  # frames apart from the reference: their neighbours
        placed = np.array([max(scores[0][i - 1], *_neighbour_agreement(coarse, points, poses, i))
                           for i in range(1, len(poses))])
        floor = max(MIN_AGREEMENT, OUTLIER_RATIO * float(np.median(placed)))
        lost = [i for i in range(1, len(poses)) if placed[i - 1] < floor]
        if lost:
            raise CaptureError(
                f"the poses in {given.where} do not place {', '.join(labels[i] for i in lost)}: moved by its pose, "
                f"its depth meets neither {labels[0]}'s nor its neighbours' (at most "
                f"{max(placed[i - 1] for i in lost):.0%} agrees, the frames' median {np.median(placed):.0%}), "
                f"and no usual mix-up ({', '.join(c.name for c in candidates[1:])}) fits it. Fix or remove that "
                "pose (and frame), or drop the pose file so registration estimates the poses")
        if far:
            detail += (f"; {', '.join(labels[i] for i in far)} overlap the reference too little to be checked "
                       "against it, but agree with their neighbours")
        return PoseCheck("ok", detail, [1.0] + scores[0].round(3).tolist(), conventions)
    k = int(np.argmax(close_count[1:])) + 1
    table = "; ".join(f"{c.name}: {np.median(s):.0%}" for c, s in zip(candidates, scores))
    if close_count[k] > close_count[0] and close_count[k] >= 0.5 * informative.sum():
        conventions["fits"] = candidates[k].name
        raise CaptureError(
            f"the poses in {given.where} do not fit the depth as read, but they fit as {candidates[k].name}: "
            f"{close_count[k]} of {informative.sum()} frames agree best that way, {close_count[0]} as read (median "
            "share of each "
            f"frame's depth on the reference's: {table}). Fix: {candidates[k].fix}")
    wrong = np.flatnonzero(informative & ~fits[0])
    raise CaptureError(
        f"the poses in {given.where} do not fit {', '.join(others[j] for j in wrong)}: their depth, moved by the "
        f"pose, disagrees with {labels[0]}'s (agreement {', '.join(f'{scores[0][j]:.0%}' for j in wrong)}"
        f"; best under a mix-up {', '.join(f'{best[j]:.0%}' for j in wrong)}), "
        f"and no usual mix-up ({', '.join(c.name for c in candidates[1:])}) fits them all. Fix or remove those "
        "poses and frames, or drop the pose file so registration estimates the poses")


def _neighbour_agreement(coarse: list, points: list, poses: np.ndarray, i: int) -> list:
    """Agreement of frame i's points with its neighbours' depth (frames i - 1 and i + 1) under
    the relative poses T_i T_j^-1 (frame j -> frame i)."""
    return [coarse[j].agreement(points[i], poses[i] @ np.linalg.inv(poses[j]))
            for j in (i - 1, i + 1) if 0 <= j < len(poses)]


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
