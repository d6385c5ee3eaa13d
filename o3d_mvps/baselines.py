"""Baselines for depth super-resolution: bicubic and guided-filter upsampling (paper Sec. 5.1; docs/benchmarks.md).

Both upsample the reference frame's low-resolution depth (h x w, metres, 0 = missing) to the
colour grid (H x W = SF h x SF w) and return a :class:`~o3d_mvps.refinement.Refinement`
(normals are the perspective normals of the upsampled depth, albedo None).

Pixel centres follow :mod:`o3d_mvps.model.camera`: integer coordinates are pixel centres, so
the centre of low-resolution pixel j sits at high-resolution coordinate ``SF j + (SF - 1) / 2``
(the grid relation of :func:`~o3d_mvps.model.camera.scale_intrinsics`).

Why not ``cv2.resize(..., INTER_CUBIC)``: it uses the same centre alignment, but its cubic
kernel (Keys, a = -0.75) does not reproduce linear functions (a depth ramp of 1 mm per
low-resolution pixel comes back with a +-0.04 mm ripple). :func:`upsample_bicubic` uses the
Keys kernel with a = -0.5 (Catmull-Rom, MATLAB's ``imresize`` "bicubic"), which reproduces
quadratics exactly, with linear extrapolation beyond the image border.

Missing depth is never blended into valid depth: missing low-resolution pixels are first
filled with the nearest valid depth, the filled map is upsampled, and the result is masked.
"""

from __future__ import annotations

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from .errors import CaptureError
from .model.resampling import block_average, fill_nearest_valid
from .refinement import Refinement
from .solver.options import AUTO, DEFAULT_SMOOTHNESS

#: Rec. 709 luminance weights of linear RGB, for the guided filter's grey guide.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def _keys_weights(t: np.ndarray, a: float = -0.5) -> np.ndarray:
    """Cubic-convolution weights (..., 4) of the taps at offsets -1, 0, 1, 2 for fractions t in [0, 1)."""
    d = np.abs(np.stack([t + 1.0, t, 1.0 - t, 2.0 - t], axis=-1))
    near = (a + 2.0) * d**3 - (a + 3.0) * d**2 + 1.0
    far = a * d**3 - 5.0 * a * d**2 + 8.0 * a * d - 4.0 * a
    return np.where(d <= 1.0, near, np.where(d < 2.0, far, 0.0))


def cubic_upsampling_matrix(n: int, factor: int) -> sp.csr_matrix:
    """Sparse (factor n, n) matrix upsampling a 1-D signal of n samples by an integer factor.

    Output sample x takes the source coordinate ``(x + 0.5) / factor - 0.5`` (pixel centres
    at integer coordinates). Keys cubic kernel (a = -0.5); taps outside [0, n) are linearly
    extrapolated from the two border samples (clamped for n = 1).
    """
    if factor < 1 or n < 1:
        raise ValueError(f"cubic_upsampling_matrix: need n >= 1 and factor >= 1, got n={n}, factor={factor}")
    x = np.arange(n * factor)
    s = (x + 0.5) / factor - 0.5
    i0 = np.floor(s).astype(np.int64)
    weights = _keys_weights(s - i0)  # (N, 4)
    taps = i0[:, None] + np.arange(-1, 3)[None, :]  # (N, 4), may leave [0, n)
    rows = np.repeat(x, 4)
    taps, weights = taps.ravel(), weights.ravel()
    if n == 1:
        cols, data = np.zeros_like(taps), weights
    else:
        # f(-m) = (1 + m) f(0) - m f(1); f(n - 1 + m) = (1 + m) f(n - 1) - m f(n - 2)
        below, above = taps < 0, taps > n - 1
        m = np.where(below, -taps, np.where(above, taps - (n - 1), 0))
        edge = np.where(below, 0, np.where(above, n - 1, taps))
        inner = np.where(below, 1, n - 2)
        out = below | above
        rows = np.concatenate([rows, rows[out]])
        cols = np.concatenate([edge, inner[out]])
        data = np.concatenate([weights * np.where(out, 1 + m, 1), -weights[out] * m[out]])
    return sp.csr_matrix((data, (rows, cols)), shape=(n * factor, n))


def upsample_bicubic(image: np.ndarray, factor: int) -> np.ndarray:
    """Bicubic upsampling of an (h, w) array by an integer factor to (factor h, factor w), float64.

    See :func:`cubic_upsampling_matrix`; separable, exact for quadratic functions of (u, v)
    away from the border and for linear ones everywhere.
    """
    image = np.asarray(image, dtype=np.float64)
    h, w = image.shape
    rows = cubic_upsampling_matrix(h, factor)
    cols = cubic_upsampling_matrix(w, factor)
    return np.asarray((cols @ (rows @ image).T).T)


def _reference(capture) -> tuple[np.ndarray, np.ndarray, int]:
    """(bicubic depth (H, W) float64 metres, mask (H, W) bool, SF) of the reference frame."""
    depth_lr = capture.depth_array(0).astype(np.float64)
    sf = capture.scale_factor
    H, W = capture.color_size
    if depth_lr.shape[0] * sf != H or depth_lr.shape[1] * sf != W:
        raise CaptureError(
            f"colour {W}x{H} is not an integer multiple of depth {depth_lr.shape[1]}x{depth_lr.shape[0]}; "
            "crop the colour frames to SF times the depth size"
        )
    if not (depth_lr > 0).any():
        raise CaptureError(
            "the reference frame has no valid depth (all zeros); check depth_scale / depth_trunc or "
            "choose another reference frame"
        )
    depth = upsample_bicubic(fill_nearest_valid(depth_lr, depth_lr > 0), sf)
    mask = capture.mask_array(0)
    if mask is None:  # the depth sensor's coverage, each LR pixel covering its SF x SF block
        mask = np.kron(depth_lr > 0, np.ones((sf, sf), dtype=bool))
    return depth, mask & (depth > 0), sf


def bicubic(capture) -> Refinement:
    """Bicubic upsampling of the reference frame's depth to colour resolution.

    Parameters
    ----------
    capture : Capture
        Frame 0's depth (h, w) metres (0 = missing) is upsampled by SF to (H, W).

    Returns
    -------
    Refinement
        ``method="bicubic"``: depth (H, W) metres, perspective normals, mask = the reference
        object mask if the capture has one, else the sensor's coverage (valid LR pixels, each
        spread over its SF x SF block). Missing LR depth is filled with the nearest valid
        depth before upsampling, so no hole or background drags the depth toward 0.
    """
    depth, mask, _ = _reference(capture)
    return Refinement.from_arrays(depth, mask, capture.color_K(), method="bicubic", albedo=None)


def _box(image: np.ndarray, radius: int) -> np.ndarray:
    """Box sum over (2 radius + 1)^2 windows, zero outside the image, float64."""
    k = 2 * radius + 1
    return cv2.boxFilter(np.asarray(image, dtype=np.float64), cv2.CV_64F, (k, k), normalize=False,
                         borderType=cv2.BORDER_CONSTANT)


def guided_coefficients(guide: np.ndarray, source: np.ndarray, mask: np.ndarray, radius: int,
                        eps: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Window-averaged coefficients of the grey-guide guided filter (He, Sun, Tang, ECCV 2010), masked.

    In each (2 radius + 1)^2 window the source is fitted as ``a * guide + b`` (ridge eps on
    a); every pixel then takes the mean (a, b) of the windows covering it, and the filter
    output is ``A * guide + B``. All window statistics are averages over the window's mask
    pixels only (box filter of the masked image divided by the box filter of the mask), so
    pixels outside the mask (background, missing depth) neither enter nor leak.

    Parameters
    ----------
    guide : (h, w) array
        Guide image (any intensity units).
    source : (h, w) array
        Image to filter (e.g. depth in metres); read on the mask only.
    mask : (h, w) bool array
        Pixels that take part.
    radius : int
        Window radius in pixels.
    eps : float
        Regulariser in squared guide units: windows whose guide variance is well above eps
        follow the guide, flatter ones are smoothed.

    Returns
    -------
    A, B : (h, w) float64 arrays
        Mean coefficients (A in source units per guide unit, B in source units).
    covered : (h, w) bool array
        Pixels with at least one mask pixel in their window (A, B are 0 elsewhere).
    """
    m = np.asarray(mask, dtype=np.float64)
    I = np.asarray(guide, dtype=np.float64) * m
    offset = float(np.median(source[mask])) if mask.any() else 0.0  # affine-equivariant: centred for precision
    p = (np.asarray(source, dtype=np.float64) - offset) * m
    count = _box(m, radius)
    covered = count > 0.5
    count = np.maximum(count, 1.0)
    mean = lambda x: _box(x, radius) / count  # noqa: E731  average over the window's mask pixels
    mean_I, mean_p = mean(I), mean(p)
    var_I = np.maximum(mean(I * I) - mean_I**2, 0.0)
    a = (mean(I * p) - mean_I * mean_p) / (var_I + eps)
    b = mean_p - a * mean_I
    A, B = mean(a * m), mean(b * m) + offset
    return np.where(covered, A, 0.0), np.where(covered, B, 0.0), covered


def guided(capture, radius: int = 1, eps: float = 0.3) -> Refinement:
    """Guided-filter joint upsampling of the reference depth, the reference colour as guide.

    The guided filter is fitted on the depth grid and applied on the colour grid (He et al.'s
    joint upsampling): the luminance (Rec. 709, a grey guide) of the reference colour is
    area-averaged to depth resolution, the masked filter coefficients ``A, B`` are computed
    there from the valid low-resolution depth (:func:`guided_coefficients`), upsampled
    bicubically (:func:`upsample_bicubic`) and applied as ``z = A * I + B`` with the
    full-resolution luminance I. Because area averaging is linear, a depth step that
    coincides with a colour edge obeys the same linear model in its mixed low-resolution
    pixel as at full resolution, so the step comes back sharp. (Filtering the bicubic depth
    at full resolution instead leaves halos about as wide as the bicubic blur.)

    Parameters
    ----------
    capture : Capture
        As for :func:`bicubic`; frame 0's colour (H, W, 3) linear RGB is the guide.
    radius : int
        Window radius in low-resolution (depth) pixels.
    eps : float
        Regulariser relative to the guide's variance over the mask (dimensionless; the
        absolute eps is ``eps * var(luminance)``), so the result does not depend on exposure.
        Smaller values follow colour edges more closely but copy more albedo texture into
        depth; larger ones approach a box filter of the depth.

    Notes
    -----
    Measured on the synthetic bunny (640x480, SF 4, LED light, :func:`o3d_mvps.metrics.evaluate`):
    with sensor noise MAE 20.0 deg / RMSE 2.95 mm (bicubic 39.5 deg / 2.85 mm); without noise
    17.8 deg / 2.82 mm (bicubic 10.7 deg / 1.48 mm). The filter denoises normals but its
    locally constant offset biases depth on steep slopes near silhouettes (windows there are
    one-sided) and it copies albedo texture into depth.

    Returns
    -------
    Refinement
        ``method="guided"``, same mask as :func:`bicubic`.
    """
    if int(radius) < 1 or not eps > 0:
        raise ValueError(f"guided: need radius >= 1 and eps > 0, got radius={radius}, eps={eps}")
    depth_lr = capture.depth_array(0).astype(np.float64)
    _, mask, sf = _reference(capture)
    guide = capture.color_array(0).astype(np.float64) @ LUMINANCE
    guide_lr = block_average(guide, sf)
    valid_lr = depth_lr > 0
    eps_abs = eps * max(float(np.var(guide[mask])) if mask.any() else 0.0, 1e-12)
    A, B, covered = guided_coefficients(guide_lr, depth_lr, valid_lr, int(radius), eps_abs)
    A = upsample_bicubic(fill_nearest_valid(A, covered), sf)
    B = upsample_bicubic(fill_nearest_valid(B, covered), sf)
    depth = A * guide + B
    return Refinement.from_arrays(depth, mask & (depth > 0), capture.color_K(), method="guided", albedo=None)


def smooth_fit(capture, smoothness: float | str = DEFAULT_SMOOTHNESS["room"], tau: float = 10.0) -> Refinement:
    """The smooth fit of the sensor depth: the refinement's prior alone, no photometric term.

    Minimises ``tau ||D z - z0||^2 + mu ||S z||^2`` over the reference mask at colour resolution,
    with the solver's block average D, slope-weighted second differences S
    (:func:`o3d_mvps.solver.smoothness.smoothness_rows`) and weights normalised as the solver's
    (:func:`o3d_mvps.solver.driver.normalised_tau`, :func:`~o3d_mvps.solver.driver.normalised_smoothness`);
    what the refinement falls back to where the images say nothing (room light: the weights and
    slope-weighted rows are the room light model's defaults; smoothness "auto":
    :func:`o3d_mvps.solver.smoothness.auto_smoothness`). Starts from bicubic.
    """
    from .model.normals import masked_grid
    from .solver.driver import normalised_smoothness, normalised_tau
    from .solver.pyramid import depth_prior
    from .solver.smoothness import auto_smoothness, smoothness_rows

    start, mask, sf = _reference(capture)
    grid = masked_grid(mask)
    z0 = capture.depth_array(0).astype(np.float64)
    prior = depth_prior(grid, z0, sf)
    prior.S = smoothness_rows(grid, z0, capture.color_K(), sf)
    if smoothness == AUTO:
        smoothness = auto_smoothness(tau, z0, mask, sf, capture.color_K())
    # the common factor n mean(I)^2 |C| / mean(z0)^2 of both weights drops out of the minimiser
    hessian, rhs = prior.normal_equations(grid.gather(start), normalised_tau(tau, 1, 1.0, grid.size, 1.0, prior.rows),
                                          normalised_smoothness(smoothness, 1, 1.0, 1.0, 0))
    ridge = 1e-9 * float(hessian.diagonal().mean())  # pixels outside every full block and stencil stay put
    step = spsolve((hessian + ridge * sp.identity(grid.size)).tocsc(), rhs)
    depth = grid.scatter(grid.gather(start) + step)
    return Refinement.from_arrays(depth, mask, capture.color_K(), method="smooth fit", albedo=None)


#: Least accumulated weight (frames) of the fused surface (Open3D's default for meshes and ray casts).
FUSION_WEIGHT_THRESHOLD = 3.0


def tsdf_fusion(capture, voxel: float = 0.004, poses: np.ndarray | None = None,
                weight_threshold: float = FUSION_WEIGHT_THRESHOLD) -> Refinement:
    """TSDF fusion of every frame's sensor depth, ray cast into the reference colour view.

    The depth-only stage of volumetric RGB-D methods (KinectFusion; the fused volume of
    PSgradientSDF before its photometric step): each frame's low-resolution depth (its object
    mask's majority over each SF x SF block, where the capture has masks) is integrated with
    weight 1 per pixel into a :class:`~o3d_mvps.reconstruct.fusion.TSDFVolume` (Open3D
    ``VoxelBlockGrid``, truncation 4 voxels) with the frame's pose; the zero level's marching-cubes
    mesh is ray cast (``RaycastingScene``) from the reference colour camera at full resolution.
    (``VoxelBlockGrid.ray_cast`` left half of a fused plane's pixels unhit in Open3D 0.20, with
    Open3D's own ``integrate`` too.) Multi-view averaging removes the sensor's per-frame noise but the voxel grid
    and the truncation band blur relief narrower than a few voxels.

    Parameters
    ----------
    capture : Capture
        Frames' depth (h, w) metres with the depth intrinsics; the reference colour grid (H, W).
    voxel : float
        Voxel edge in metres (e.g. 0.004).
    poses : (n, 4, 4) array, optional
        Reference camera -> frame i camera (the refinement's convention); default: the
        registration :func:`o3d_mvps.odometry.initial_poses` (what ``refine`` starts from).
    weight_threshold : float
        Least accumulated weight (frames) of the fused surface's voxels.

    Returns
    -------
    Refinement
        ``method="tsdf fusion"``: depth (H, W) metres, perspective normals of it, mask = the
        bicubic baseline's mask; reference pixels whose ray misses the fused surface take the
        bicubic depth (their fraction in ``info["tsdf_fusion"]["missed_fraction"]``).
    """
    import open3d as o3d

    from .reconstruct.fusion import TSDFVolume

    if not (np.isfinite(voxel) and 0 < voxel <= 0.1):
        raise ValueError(f"tsdf_fusion: voxel must be a length in metres in (0, 0.1], got {voxel!r}; e.g. 0.004")
    n = capture.n_frames
    if poses is None:
        from .odometry import initial_poses
        poses = initial_poses(capture)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (n, 4, 4):
        raise ValueError(f"tsdf_fusion: poses must be ({n}, 4, 4) for the capture's {n} frames, got {poses.shape}")
    start, mask, sf = _reference(capture)
    K_lr = capture.depth_K()
    volume = TSDFVolume(voxel)
    for i in range(n):
        depth = capture.depth_array(i).astype(np.float64)
        frame_mask = capture.mask_array(i)
        keep = depth > 0
        if frame_mask is not None:
            keep &= block_average(frame_mask, sf) >= 0.5
        volume.integrate(depth, keep.astype(np.float32), K_lr, poses[i])
    H, W = capture.color_size
    K = capture.color_K()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(volume.extract_mesh(float(weight_threshold)))
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    rays = np.zeros((H, W, 6), np.float32)  # from the reference camera centre, direction z = 1: t_hit is z
    rays[..., 3], rays[..., 4], rays[..., 5] = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], 1.0
    fused = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    hit = np.isfinite(fused) & (fused > 0)
    missed = float((mask & ~hit).sum() / max(mask.sum(), 1))
    depth = np.where(hit, fused, start)
    return Refinement.from_arrays(depth, mask, capture.color_K(), method="tsdf fusion", albedo=None, poses=poses,
                                  info={"tsdf_fusion": {"voxel_mm": 1000 * float(voxel), "frames": int(n),
                                                        "weight_threshold": float(weight_threshold),
                                                        "missed_fraction": missed}})
