"""The finest level's depth prior from every frame's depth (issue #32; docs/fidelity.md, "The
frames' mean depth for a moving camera").

The depth prior ties the surface to frame 0's depth alone, so frame 0's sensor noise reaches the
normals. Once the finest level's first sweep has given the surface that level's detail, each
frame's depth is compared with the surface as that frame's own depth pixels see it (the surface's
points moved into the frame and averaged over each depth pixel, as the sensor averages): the
residual is the frame's noise, not a difference of sampling (a frame's depth interpolated between
its pixels misses detail steep at the pixel's scale). The residuals, carried onto the reference's
rays, are averaged where frame 0 and enough frames agree, and the prior's target becomes the
surface's own depth pixels plus that mean. Each frame's rigid part is replaced by frame 0's: a pose
that is off (the registration's shared error; poses moved by a room-lit level's parallax) moves a
frame's residual rigidly, and frame 0 keeps holding the surface where its depth says.
"""

from __future__ import annotations

import numpy as np

from ..covisibility import MEAN_MIN_FRAMES, carried_onto_rays, outlier_tolerance, surface_frame
from ..model.camera import backproject, project, transform
from ..model.warping import in_view, sample_bilinear

#: the finest level's sweep at whose start its prior is re-made (after one sweep: the surface has
#: the level's detail; from level 1's surface, upsampled, a 40x30 depth of a 4 mm relief kept
#: 0.15-0.18 mm of error where frame 0's depth alone leaves 0.03)
RETARGET_SWEEP = 2
#: the least pixels a frame's rigid part is fitted on; a frame with fewer is left out
RIGID_MIN_PIXELS = 50


def frames_depth_target(z: np.ndarray, mask: np.ndarray, K: np.ndarray, depth_K: np.ndarray, scale_factor: int,
                        depths: np.ndarray, poses: np.ndarray, noise_scale: float,
                        z0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(target (h, w) metres, averaged (h, w) bool): the depth prior's target on the reference's
    depth grid, and the pixels that took the frames' mean (elsewhere ``z0``).

    z: (H, W) metres, the current surface on the colour grid (K); mask: (H, W) bool, the object;
    depth_K: (3, 3) the depth grid's intrinsics, scale_factor its colour pixels per depth pixel;
    depths: (n, h, w) metres, every frame's sensor depth (0 = none); poses: (n, 4, 4) reference ->
    frame i, the current ones; noise_scale: s (1/m) of
    :func:`~o3d_mvps.covisibility.depth_noise_scale`; z0: (h, w) metres, frame 0's depth as the
    prior has it.
    """
    h, w = z0.shape
    rows, cols = np.nonzero(mask & (z > 0))
    points = backproject(z[rows, cols], K, cols.astype(np.float64), rows.astype(np.float64))
    own = _depth_pixels(cols.astype(np.float64), rows.astype(np.float64), z[rows, cols],
                        np.ones(len(rows), dtype=bool), (h, w), scale_factor)
    v, u, centres, normals, along, steep = surface_frame(np.where(z0 > 0, own, 0.0), depth_K)
    residuals = [z0[v, u] - own[v, u]]
    for T, depth in zip(poses[1:], depths[1:]):
        pu, pv, Z = project(transform(T, points), K)
        measured = _sample(depth, pu, pv, scale_factor)
        seen = (measured > 0) & (np.abs(measured - Z) <= outlier_tolerance(Z, noise_scale))  # not hidden there
        predicted = _depth_pixels(pu, pv, Z, seen, (h, w), scale_factor)
        residual = np.where((predicted > 0) & (depth > 0), depth - predicted, np.nan)
        q = transform(T, centres)
        qu, qv, qz = project(q, depth_K)
        # NaN outside the frame and wherever a corner's residual is NaN
        carried = np.where(in_view(qu, qv, qz, residual.shape),
                           sample_bilinear(residual[..., None], qu, qv)[:, 0], np.nan) / np.where(qz > 0, qz, np.inf)
        moved = carried_onto_rays(q, 1.0 + np.nan_to_num(carried), T, normals, along, steep) - own[v, u]
        residuals.append(np.where(np.isfinite(carried) & (qz > 0) & ~steep, moved, np.nan))
    stack = _rigid_as_frame_0(np.array(residuals), centres, normals, along, steep,
                              outlier_tolerance(own[v, u], noise_scale))
    median = np.nanmedian(stack, axis=0)
    agree = np.isfinite(stack) & (np.abs(stack - median) <= outlier_tolerance(own[v, u], noise_scale))
    count = agree.sum(axis=0)
    use = agree[0] & (count >= MEAN_MIN_FRAMES)
    mean = np.where(agree, stack, 0.0).sum(axis=0) / np.maximum(count, 1)
    target, averaged = z0.astype(np.float64), np.zeros((h, w), dtype=bool)
    target[v[use], u[use]] = own[v[use], u[use]] + mean[use]
    averaged[v[use], u[use]] = True
    return target, averaged


def _depth_pixels(pu: np.ndarray, pv: np.ndarray, Z: np.ndarray, keep: np.ndarray, size: tuple[int, int],
                  scale_factor: int) -> np.ndarray:
    """(h, w) metres: what a depth pixel of ``size`` measures of the points at colour pixels (pu, pv)
    (m,) each at depths Z (m,) (``keep`` (m,) bool): the mean depth over its scale_factor x
    scale_factor colour pixel centres of the plane through the points that fall in it (a plane's
    1 / depth is linear in the pixels: fitted so, by least squares), where at least half its colour
    pixels' worth fall; the points' mean depth where they do not span a plane; 0 elsewhere. The
    points' own mean would be off by the slope times their centroid's offset from the pixel's
    centre (0.07 mm median on a plane at 0.6 m, 4 mm colour pixels, a 30 degree tilt)."""
    h, w = size
    k = scale_factor
    iu, iv = _depth_pixel_of(pu, pv, k)
    keep = keep & (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    index = iv[keep] * w + iu[keep]
    du = pu[keep] - (k * iu[keep] + (k - 1) / 2)  # from the depth pixel's centre, colour pixels
    dv = pv[keep] - (k * iv[keep] + (k - 1) / 2)
    inverse = 1.0 / Z[keep]
    sums = [np.bincount(index, weights, minlength=h * w) for weights in
            (None, du, dv, du * du, du * dv, dv * dv, inverse, du * inverse, dv * inverse)]
    n, su, sv, suu, suv, svv, s1, su1, sv1 = sums
    out = np.where(n > 0, np.bincount(index, Z[keep], minlength=h * w) / np.maximum(n, 1), 0.0)
    bins = np.nonzero(n >= 3)[0]
    gram = np.stack([np.stack([n[bins], su[bins], sv[bins]], -1), np.stack([su[bins], suu[bins], suv[bins]], -1),
                     np.stack([sv[bins], suv[bins], svv[bins]], -1)], -2)
    # the 3 x 3 determinants written out (np.linalg.det on every bin took a third of the pass)
    det = (gram[:, 0, 0] * (gram[:, 1, 1] * gram[:, 2, 2] - gram[:, 1, 2] ** 2)
           - gram[:, 0, 1] * (gram[:, 0, 1] * gram[:, 2, 2] - gram[:, 1, 2] * gram[:, 0, 2])
           + gram[:, 0, 2] * (gram[:, 0, 1] * gram[:, 1, 2] - gram[:, 1, 1] * gram[:, 0, 2]))
    good = np.abs(det) > 1e-9 * n[bins] ** 3
    plane = bins[good]
    if len(plane):
        rhs = np.stack([s1[plane], su1[plane], sv1[plane]], -1)[..., None]
        a, b, c = np.linalg.solve(gram[good], rhs)[..., 0].T
        offsets = np.arange(k) - (k - 1) / 2
        ou, ov = np.meshgrid(offsets, offsets)
        inverse_at = a[:, None] + b[:, None] * ou.ravel() + c[:, None] * ov.ravel()
        positive = (inverse_at > 0).all(axis=1)
        out[plane] = np.where(positive, (1.0 / np.where(inverse_at > 0, inverse_at, 1.0)).mean(axis=1), out[plane])
    return np.where(n >= max(1, k * k // 2), out, 0.0).reshape(h, w)


def _sample(depth: np.ndarray, pu: np.ndarray, pv: np.ndarray, scale_factor: int) -> np.ndarray:
    """(m,) metres: the depth pixel (h, w) each colour pixel (pu, pv) (m,) falls in; 0 outside."""
    h, w = depth.shape
    iu, iv = _depth_pixel_of(pu, pv, scale_factor)
    inside = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    return np.where(inside, depth[np.clip(iv, 0, h - 1), np.clip(iu, 0, w - 1)], 0.0)


def _depth_pixel_of(pu: np.ndarray, pv: np.ndarray, scale_factor: int) -> tuple[np.ndarray, np.ndarray]:
    """(column, row) (m,) int each: the depth pixel whose scale_factor x scale_factor colour pixels
    hold the colour pixel coordinates (pu, pv) (m,) (colour pixel centres at integers)."""
    return (np.floor((pu + 0.5) / scale_factor).astype(np.int64),
            np.floor((pv + 0.5) / scale_factor).astype(np.int64))


def _rigid_as_frame_0(stack: np.ndarray, points: np.ndarray, normals: np.ndarray, along: np.ndarray,
                      steep: np.ndarray, tolerance: np.ndarray) -> np.ndarray:
    """``stack`` (n, m) (frame 0's residuals first, NaN: none) with each other frame's least-squares
    rigid part replaced by frame 0's: the change of a residual along the reference's rays that a
    small motion (rotation w, translation t) makes, ``(w . (X x n) + t . n) / (n . r)`` (points X
    (m, 3), normals n (m, 3), along: n . r (m,)), fitted where a frame is within ``tolerance`` (m,)
    metres of frame 0. A frame with fewer than :data:`RIGID_MIN_PIXELS` such pixels is left out."""
    design = np.concatenate([np.cross(points, normals), normals], axis=1) / np.where(steep, 1.0, along)[:, None]
    out = np.full_like(stack, np.nan)
    out[0] = stack[0]
    fit0 = np.isfinite(stack[0]) & (np.abs(stack[0]) <= tolerance) & ~steep
    if fit0.sum() < RIGID_MIN_PIXELS:
        return out
    rigid0 = _least_squares(design[fit0], stack[0][fit0])
    for i in range(1, len(stack)):
        fit = np.isfinite(stack[i]) & (np.abs(stack[i] - stack[0]) <= tolerance) & ~steep
        if fit.sum() >= RIGID_MIN_PIXELS:
            out[i] = stack[i] - design @ (_least_squares(design[fit], stack[i][fit]) - rigid0)
    return out


def _least_squares(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(6,) the least-squares solution of A (m, 6) x = b (m,) by its normal equations (a tenth of
    an SVD's time on 20 000 rows; the columns, rotation and translation of a surface at about a
    metre, are of one scale)."""
    return np.linalg.solve(A.T @ A, A.T @ b)
