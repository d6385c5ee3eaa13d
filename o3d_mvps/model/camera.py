"""Pinhole camera: intrinsics, back-projection and projection.

Conventions (used across the package): pixel (u, v) is column u, row v; integer
coordinates are pixel centres (Open3D's convention); depth z is along the optical
axis in metres; K is a 3x3 float64 matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]].
"""

from __future__ import annotations

import numpy as np

from .arrays import fused, like


def as_intrinsic_matrix(intrinsic) -> np.ndarray:
    """Return a 3x3 float64 numpy matrix from an o3d Tensor, PinholeCameraIntrinsic or array."""
    if hasattr(intrinsic, "intrinsic_matrix"):  # o3d.camera.PinholeCameraIntrinsic
        intrinsic = intrinsic.intrinsic_matrix
    if hasattr(intrinsic, "numpy"):  # o3d.core.Tensor
        intrinsic = intrinsic.numpy()
    K = np.asarray(intrinsic, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(
            f"intrinsics must be a finite 3x3 matrix with positive focal lengths, got {K.tolist()}; "
            "pass [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels"
        )
    return K


def scale_intrinsics(K: np.ndarray, sx: float, sy: float | None = None) -> np.ndarray:
    """Intrinsics of the same camera on a grid resampled by (sx, sy) (new size = old size * s).

    Pixel centres are kept consistent: a grid downsampled by area averaging by an integer
    factor k has s = 1/k, f' = f/k and c' = (c + 0.5)/k - 0.5.
    """
    sy = sx if sy is None else sy
    K2 = np.array(K, dtype=np.float64, copy=True)
    K2[0, 0] *= sx
    K2[1, 1] *= sy
    K2[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K2[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K2


def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v), each (height, width) float64: u the column, v the row."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return u, v


def backproject(z: np.ndarray, K: np.ndarray, u: np.ndarray | None = None, v: np.ndarray | None = None) -> np.ndarray:
    """3D points (..., 3) in metres of depth z at pixels (u, v); the full grid if u, v are None."""
    if u is None or v is None:
        u, v = pixel_grid(*z.shape)
    x, y = _backproject_xy(u, v, z, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    return np.stack([x, y, z], axis=-1)


@fused
def _backproject_xy(u, v, z, fx, fy, cx, cy):
    """x, y (metres) of depth z at pixels (u, v) (one kernel on a GPU)."""
    return (u - cx) / fx * z, (v - cy) / fy * z


def project(points: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project camera-frame points (..., 3) to pixel coordinates; returns (u, v, Z)."""
    X, Y, Z = points[..., 0], points[..., 1], points[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * X / Z + K[0, 2]
        v = K[1, 1] * Y / Z + K[1, 2]
    return u, v, Z


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform (host array) to points (..., 3) (host or device)."""
    return points @ like(T[:3, :3].T, points) + like(T[:3, 3], points)
