"""Automatic object masks from depth alone, for captures without a ``mask/`` folder.

The rule: the object is what the camera points at. Depths inside a range (given, or around the
depth at the image centre) are kept; large background planes (a table top, a wall) are found by
RANSAC and cut together with everything behind them; the connected region nearest the image
centre is the object.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from ..errors import CaptureError
from ..model.camera import backproject
from ..model.resampling import repeat_pixels

#: Half-width of the default depth range, as a fraction of the depth at the image centre
#: (0.35 at 0.8 m: 0.52-1.08 m, room for an object up to ~0.3 m deep and its table).
DEFAULT_RANGE_FRACTION = 0.35
#: Points closer than PLANE_TOLERANCE_M + PLANE_TOLERANCE_PER_M2 * z^2 (metres) to a background
#: plane belong to it: a few mm plus about 3 sigma of a structured-light sensor's noise, which
#: grows with the square of the depth z.
PLANE_TOLERANCE_M = 0.004
PLANE_TOLERANCE_PER_M2 = 0.005
#: A plane is background when it holds at least this share of the in-range points and reaches
#: the image border (an object's flat face does neither).
PLANE_MIN_SHARE = 0.10
MAX_PLANES = 3
#: Depth pixels of thin parts (ears, handles) the clean-up's opening removed that are grown back,
#: within the kept depths, from the object region.
REGROW_PX = 3
RANSAC_ITERATIONS = 300
RANSAC_SAMPLES = 6000


def default_depth_range(depth: np.ndarray) -> tuple[float, float] | None:
    """(near, far) metres around the median valid depth of the central ninth of ``depth`` (h, w);
    None when that window has no valid depth."""
    h, w = depth.shape
    centre = depth[h // 3: h - h // 3, w // 3: w - w // 3]
    valid = centre[centre > 0]
    if valid.size == 0:
        return None
    z = float(np.median(valid))
    return (z * (1 - DEFAULT_RANGE_FRACTION), z * (1 + DEFAULT_RANGE_FRACTION))


def object_mask(depth: np.ndarray, K_depth: np.ndarray, depth_range=None, seed: int = 0) -> np.ndarray:
    """The object's pixels in a depth map: (h, w) bool (all False when nothing is left).

    depth: (h, w) metres, 0 = missing. K_depth: (3, 3) intrinsics of the depth grid (pixels).
    depth_range: (near, far) metres, or None for :func:`default_depth_range`.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth_range is None:
        depth_range = default_depth_range(depth)
        if depth_range is None:
            return np.zeros(depth.shape, dtype=bool)
    near, far = depth_range
    keep = (depth > 0) & (depth >= near) & (depth <= far)
    points = backproject(depth, K_depth)
    rng = np.random.default_rng(seed)
    for _ in range(MAX_PLANES):
        plane = _background_plane(points, keep, rng)
        if plane is None:
            break
        keep &= _in_front_of(plane, points, depth)
    region = _region_nearest_centre(ndi.binary_opening(keep, structure=np.ones((3, 3), dtype=bool)))
    return region | ndi.binary_dilation(region, structure=np.ones((3, 3), dtype=bool), iterations=REGROW_PX,
                                        mask=keep)


def _background_plane(points: np.ndarray, keep: np.ndarray, rng) -> np.ndarray | None:
    """RANSAC's largest plane (n, d) with n . X + d = 0, |n| = 1, n . X + d > 0 on the camera side,
    over the kept points, when it is background (PLANE_MIN_SHARE, touches the border); else None."""
    candidates = points[keep]
    if len(candidates) < 3:
        return None
    sample = candidates[rng.choice(len(candidates), min(len(candidates), RANSAC_SAMPLES), replace=False)]
    tolerance = _plane_tolerance(sample[:, 2])
    best, best_count = None, 0
    for _ in range(RANSAC_ITERATIONS):
        a, b, c = sample[rng.choice(len(sample), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n /= norm
        count = int((np.abs(sample @ n - n @ a) < tolerance).sum())
        if count > best_count:
            best, best_count = (n, -n @ a), count
    if best is None or best_count < PLANE_MIN_SHARE * len(sample):
        return None
    n, d = best
    inliers = np.abs(sample @ n + d) < tolerance
    centroid = sample[inliers].mean(axis=0)  # least-squares refit on the inliers
    n = np.linalg.svd(sample[inliers] - centroid, full_matrices=False)[2][-1]
    d = -n @ centroid
    if d < 0:  # the camera (origin) on the positive side
        n, d = -n, -d
    on_plane = keep & (np.abs(points @ n + d) < _plane_tolerance(points[..., 2]))
    border = np.zeros_like(on_plane)
    border[[0, -1], :] = border[:, [0, -1]] = True
    if not (on_plane & border).any():
        return None
    return np.append(n, d)


def _plane_tolerance(z: np.ndarray) -> np.ndarray:
    """Distance (metres) within which points at depth z (metres) lie on a plane."""
    return PLANE_TOLERANCE_M + PLANE_TOLERANCE_PER_M2 * z**2


def _in_front_of(plane: np.ndarray, points: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(h, w) bool: points on the camera side of ``plane`` by more than the plane tolerance."""
    return points @ plane[:3] + plane[3] > _plane_tolerance(depth)


def _region_nearest_centre(keep: np.ndarray) -> np.ndarray:
    """The 8-connected region of ``keep`` (h, w) nearest the image centre, holes filled and
    edges closed; all False when ``keep`` is."""
    labels, count = ndi.label(keep, structure=np.ones((3, 3), dtype=bool))
    if count == 0:
        return np.zeros_like(keep)
    h, w = keep.shape
    v, u = np.nonzero(labels)
    distance = np.hypot(v - (h - 1) / 2, u - (w - 1) / 2)
    region = labels == labels[v[np.argmin(distance)], u[np.argmin(distance)]]
    region = ndi.binary_closing(region, structure=np.ones((3, 3), dtype=bool))
    return ndi.binary_fill_holes(region)


def auto_masks(depths: list, K_depth: np.ndarray, scale_factor: int, depth_range=None) -> list:
    """Automatic masks of every frame: (H, W) bool each, colour resolution (nearest upsampling).

    depths: n (h, w) arrays in metres. Raises CaptureError naming the frame, the depth range
    and the fix when a frame's mask is empty.
    """
    masks = []
    for i, depth in enumerate(depths):
        mask = object_mask(depth, K_depth, depth_range)
        if not mask.any():
            used = depth_range if depth_range is not None else default_depth_range(np.asarray(depth))
            where = "no valid depth near the image centre" if used is None else (
                f"nothing but background planes in the depth range {used[0]:.2f}-{used[1]:.2f} m")
            raise CaptureError(
                f"the automatic object mask of frame {i} is empty ({where}); give the object's depth range "
                "with --depth-range NEAR FAR (read_capture(..., depth_range=(near, far))), aim the camera at "
                "the object, or provide masks in mask/"
                + ("" if used is None else "; a surface that fills the frame (a quilt, a relief) is taken for a "
                   "background plane: use --mask none (read_capture(..., mask=\"none\")) or masks")
            )
        masks.append(repeat_pixels(mask, scale_factor))
    return masks
