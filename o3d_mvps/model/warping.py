"""Warping reference pixels into other frames, bilinear sampling and the occlusion test.

A reference pixel p with depth z(p) back-projects to P = pi^-1(p, z); frame i sees it at
``w_i(p) = pi(R_i P + t_i)`` (paper Sec. 3.3). Pixel centres sit at integer coordinates.
"""

from __future__ import annotations

import cv2
import numba
import numpy as np

from .arrays import array_module
from .camera import project, transform

#: Channel counts OpenCV's remap interpolates in float (others use 1/32-pixel fixed point).
_REMAP_CHANNELS = (1, 3, 4)
_REMAP_WIDTH = 4096  # remap's maps must have fewer than 32767 columns


def sample_bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, C) of an (H, W, C) image at real pixel coordinates u, v (N,).

    Computed in the image's dtype. Coordinates are clamped to the image, so samples outside
    repeat the border; use :func:`in_view` to know which samples are genuine. float32
    host images with 1, 3 or 4 channels go through ``cv2.remap`` (about 10x faster;
    coordinates rounded to float32, i.e. 1e-4 px at 1280 px), others (CuPy images too)
    through the array module's gathers.
    """
    H, W = image.shape[:2]
    u = np.clip(u, 0.0, W - 1.0)
    v = np.clip(v, 0.0, H - 1.0)
    if (array_module(image) is np and image.dtype == np.float32 and image.ndim == 3
            and image.shape[2] in _REMAP_CHANNELS and max(H, W) < 32767):
        return _remap(image, u, v)
    flat = image.reshape(H * W, -1)
    u0 = np.minimum(u.astype(np.int64), max(W - 2, 0))
    v0 = np.minimum(v.astype(np.int64), max(H - 2, 0))
    a = (u - u0).astype(image.dtype)[:, None]
    b = (v - v0).astype(image.dtype)[:, None]
    i00 = v0 * W + u0
    du = 1 if W > 1 else 0
    dv = W if H > 1 else 0
    top = flat[i00]
    top += a * (flat[i00 + du] - top)
    bottom = flat[i00 + dv]
    bottom += a * (flat[i00 + dv + du] - bottom)
    top += b * (bottom - top)
    return top


def _remap(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """:func:`sample_bilinear` of a float32 image through cv2.remap (u, v already clamped)."""
    n = u.size
    rows = max(1, -(-n // _REMAP_WIDTH))
    width = _REMAP_WIDTH if rows > 1 else max(n, 1)
    maps = np.zeros((2, rows * width), np.float32)
    maps[0, :n] = u
    maps[1, :n] = v
    out = cv2.remap(image, maps[0].reshape(rows, width), maps[1].reshape(rows, width), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(rows * width, image.shape[2])[:n]


def warp(points_ref: np.ndarray, T: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reference points (N, 3) seen by a camera with pose T (4x4, reference -> frame).

    Returns (points in frame coordinates (N, 3), u (N,), v (N,), Z (N,)).
    """
    points = transform(T, points_ref)
    u, v, Z = project(points, K)
    return points, u, v, Z


def in_view(u: np.ndarray, v: np.ndarray, Z: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(N,) bool: in front of the camera and inside an image of size (H, W)."""
    H, W = size
    with np.errstate(invalid="ignore"):
        return (Z > 1e-6) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)


def visible(u: np.ndarray, v: np.ndarray, Z: np.ndarray, size: tuple[int, int], *, rel_tol: float = 0.02,
            sensor_depth: np.ndarray | None = None, sensor_uv: tuple[np.ndarray, np.ndarray] | None = None,
            frame_mask: np.ndarray | None = None, zbuffer: bool = True) -> np.ndarray:
    """Occlusion test: which warped reference points frame i really sees, (N,) bool.

    A point is visible when it is in view, it is the nearest reference point landing on its
    pixel (z-buffer of the warped reference surface, tolerance ``rel_tol * Z``), frame i's
    own depth measurement there (``sensor_depth`` (h, w) metres, sampled at ``sensor_uv``,
    nearest) is not in front of it by more than the tolerance, and it lies inside frame i's
    object mask (``frame_mask`` (H, W) bool) when one is given. zbuffer: False where no two
    points land on one pixel (the identity warp of a static camera): the z-buffer is skipped.
    """
    H, W = size
    empty = np.zeros((1, 1))
    sensor = sensor_depth is not None and sensor_uv is not None
    ok = np.empty(len(Z), dtype=bool)
    _visible_into(*(np.ascontiguousarray(a, dtype=np.float64) for a in (u, v, Z)), H, W, float(rel_tol), zbuffer,
                  np.ascontiguousarray(sensor_depth, dtype=np.float64) if sensor else empty,
                  *(np.ascontiguousarray(a, dtype=np.float64) for a in (sensor_uv if sensor else (empty[0], empty[0]))),
                  sensor, np.zeros((1, 1), bool) if frame_mask is None else np.ascontiguousarray(frame_mask, dtype=bool),
                  frame_mask is not None, ok)
    return ok


@numba.njit(cache=True)
def _visible_into(u, v, Z, H, W, rel_tol, zbuffer, sensor_depth, su, sv, sensor, frame_mask, masked,
                  ok):  # pragma: no cover - compiled
    """:func:`visible` written into ok (N,) bool in compiled passes (the NumPy form's dozen
    temporaries and ``np.minimum.at``: twice the time on 200 000 points): the same tests,
    comparisons and roundings (``np.rint``, half to even), so the same mask bit for bit. su, sv
    (N,): the sensor's pixel of each point where ``sensor``; frame_mask (H, W) where ``masked``."""
    N = Z.shape[0]
    for p in range(N):
        ok[p] = Z[p] > 1e-6 and u[p] >= 0 and u[p] <= W - 1 and v[p] >= 0 and v[p] <= H - 1
    if zbuffer:  # the nearest point landing on each pixel (its pixel rounded where it is read: no index arrays)
        zbuf = np.full(H * W, np.inf)
        for p in range(N):
            if ok[p]:
                f = np.int64(np.rint(v[p])) * W + np.int64(np.rint(u[p]))
                if Z[p] < zbuf[f]:
                    zbuf[f] = Z[p]
        for p in range(N):
            if ok[p]:
                ok[p] = Z[p] <= zbuf[np.int64(np.rint(v[p])) * W + np.int64(np.rint(u[p]))] + rel_tol * abs(Z[p])
    h, w = sensor_depth.shape
    for p in range(N):
        if ok[p] and sensor:  # the frame's own depth not in front of the point
            x, y = np.rint(su[p]), np.rint(sv[p])
            d = sensor_depth[np.int64(0.0 if y < 0 else (h - 1.0 if y > h - 1 else y)),
                             np.int64(0.0 if x < 0 else (w - 1.0 if x > w - 1 else x))]
            ok[p] = d <= 0 or Z[p] <= d + rel_tol * abs(Z[p])
        if ok[p] and masked:
            ok[p] = frame_mask[np.int64(np.rint(v[p])), np.int64(np.rint(u[p]))]
