"""Depth-to-colour registration without upsampling: keep the sensor's native depth resolution.

A RealSense D415 measures depth with its stereo (left infrared) camera and colour with a
separate RGB camera a few centimetres away. The solver needs depth *registered* to the colour
camera, on the low-resolution grid ``Ω_LR`` (colour grid / SF; docs/method.md), so that every
depth pixel area-averages SF x SF colour pixels. Open3D's ``RSBagReader`` and librealsense's
``align`` upsample depth to colour resolution instead, which invents samples the sensor never
measured; :func:`register_depth` reprojects each measured sample once.

Conventions are those of :mod:`o3d_mvps.model.camera`: integer pixel coordinates are pixel
centres, K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels, depth is z in metres, 0 = missing.
"""

from __future__ import annotations

import numpy as np

from .model.camera import (
    as_intrinsic_matrix,
    backproject,
    project,
    scale_intrinsics,
    transform,
)


def register_depth(
    depth: np.ndarray,
    depth_K,
    color_K,
    depth_to_color: np.ndarray,
    out_size: tuple[int, int],
    *,
    scale_factor: float = 1,
    footprint: float = 1.2,
) -> np.ndarray:
    """Reproject a depth image into the colour camera, on a grid of colour resolution / SF.

    Every measured depth pixel is back-projected to 3D, moved into the colour camera by the
    extrinsic and projected onto the target grid, whose intrinsics are the colour intrinsics
    scaled by 1/SF (:func:`o3d_mvps.capture.default_depth_intrinsic`). Each sample is splatted
    over its *footprint*: the source pixel's square as seen from the colour camera
    (``s = f_target / f_source · z_source / z_target`` target pixels wide), enlarged by
    ``footprint`` so that neighbouring samples of a continuous surface overlap and leave no
    pinholes. A z-buffer keeps the nearest sample in every target pixel, so surfaces hidden
    from the colour camera disappear. Target pixels that no footprint reaches, such as
    background the depth camera could not see behind a foreground object, stay 0: nothing is
    interpolated across occlusion boundaries, and the depth is not upsampled.

    Parameters
    ----------
    depth : (h_d, w_d) array_like
        Raw depth in metres in the depth camera, 0 (or non-finite) = no measurement.
    depth_K : (3, 3) array_like
        Depth-camera intrinsics in pixels (numpy array, o3d Tensor or PinholeCameraIntrinsic).
    color_K : (3, 3) array_like
        Colour-camera intrinsics in pixels at full colour resolution.
    depth_to_color : (4, 4) array_like
        Rigid transform mapping depth-camera coordinates to colour-camera coordinates (metres).
    out_size : (int, int)
        ``(w, h)`` of the target grid: colour width and height divided by ``scale_factor``.
    scale_factor : float, optional
        SF, the colour grid's resolution over the target grid's. 1 registers at colour
        resolution; with SF = 2 the target intrinsics are ``scale_intrinsics(color_K, 1/2)``.
    footprint : float, optional
        Footprint enlargement (>= 1). 1 splats exactly the projected pixel square; the
        default 1.2 tolerates the small spacing changes of slanted surfaces and rounding
        while fattening foreground edges by at most 0.1 target pixel.

    Returns
    -------
    (h, w) float32 ndarray
        Depth (z along the colour camera's optical axis) in metres on the target grid,
        0 where no sample lands.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[..., 0]
    if depth.ndim != 2:
        raise ValueError(f"depth must be an (h, w) image in metres, got shape {depth.shape}")
    w_out, h_out = (int(v) for v in out_size)
    if w_out <= 0 or h_out <= 0:
        raise ValueError(f"out_size must be a positive (width, height), got {out_size}")
    if footprint < 1.0:
        raise ValueError(f"footprint must be >= 1 to avoid pinholes, got {footprint}")
    T = np.asarray(depth_to_color, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"depth_to_color must be a finite 4x4 rigid transform, got shape {T.shape}")
    Kd = as_intrinsic_matrix(depth_K)
    Kt = scale_intrinsics(as_intrinsic_matrix(color_K), 1.0 / float(scale_factor))

    out = np.full(h_out * w_out, np.inf)
    valid = np.isfinite(depth) & (depth > 0)
    v_src, u_src = np.nonzero(valid)
    if v_src.size == 0:
        return np.zeros((h_out, w_out), dtype=np.float32)
    z_src = depth[v_src, u_src]
    points = transform(T, backproject(z_src, Kd, u_src.astype(np.float64), v_src.astype(np.float64)))
    u, v, z = project(points, Kt)
    in_front = z > 1e-6
    u, v, z, z_src = u[in_front], v[in_front], z[in_front], z_src[in_front]

    # Half-widths of each sample's footprint in target pixels; the pixel centres inside
    # [u - hx, u + hx) x [v - hy, v + hy) receive the sample.
    hx = 0.5 * footprint * Kt[0, 0] / Kd[0, 0] * z_src / z
    hy = 0.5 * footprint * Kt[1, 1] / Kd[1, 1] * z_src / z
    u0 = np.ceil(u - hx).astype(np.int64)
    v0 = np.ceil(v - hy).astype(np.int64)
    nu = np.ceil(u + hx).astype(np.int64) - u0  # number of covered columns
    nv = np.ceil(v + hy).astype(np.int64) - v0
    for du in range(int(nu.max(initial=0))):
        for dv in range(int(nv.max(initial=0))):
            col, row = u0 + du, v0 + dv
            hit = (du < nu) & (dv < nv) & (col >= 0) & (col < w_out) & (row >= 0) & (row < h_out)
            np.minimum.at(out, row[hit] * w_out + col[hit], z[hit])
    out[~np.isfinite(out)] = 0.0
    return out.reshape(h_out, w_out).astype(np.float32)
