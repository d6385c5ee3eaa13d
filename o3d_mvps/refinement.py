"""The Refinement result type shared by the solver and the baselines."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from .capture import image_from_array
from .model.camera import as_intrinsic_matrix
from .model.normals import perspective_normals


@dataclass
class Refinement:
    """What a depth refinement method returns, at colour resolution (H, W).

    depth: (H, W, 1) float32 metres, 0 outside the mask. normals: (H, W, 3) float32 unit
    normals in the reference camera frame pointing to the camera, 0 outside the mask.
    albedo: (H, W, 3) float32 linear RGB, or None for methods that do not estimate it.
    mask: (H, W, 1) uint8, 255 where the method returns depth. intrinsic: (3, 3) float64
    colour intrinsics. poses: (n, 4, 4) float64 reference -> frame i, or None. lighting:
    (n, 4) float64 first-order SH per frame, or None. energy: rows {"level", "iteration",
    "energy"}. timings: seconds per stage. method: the method's name.
    """

    depth: o3d.t.geometry.Image
    normals: o3d.t.geometry.Image
    mask: o3d.t.geometry.Image
    intrinsic: o3d.core.Tensor
    albedo: o3d.t.geometry.Image | None = None
    poses: o3d.core.Tensor | None = None
    lighting: o3d.core.Tensor | None = None
    energy: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    method: str = "ours"
    info: dict = field(default_factory=dict)

    # numpy views -------------------------------------------------------------------------
    def depth_array(self) -> np.ndarray:
        """(H, W) float32 metres, 0 outside the mask."""
        a = self.depth.as_tensor().numpy()
        return np.asarray(a, dtype=np.float32).reshape(a.shape[0], a.shape[1])

    def normals_array(self) -> np.ndarray:
        """(H, W, 3) float32 unit normals, 0 outside the mask."""
        return np.asarray(self.normals.as_tensor().numpy(), dtype=np.float32)

    def mask_array(self) -> np.ndarray:
        """(H, W) bool."""
        a = self.mask.as_tensor().numpy()
        return a.reshape(a.shape[0], a.shape[1]) > 0

    def albedo_array(self) -> np.ndarray | None:
        """(H, W, 3) float32 linear RGB, or None."""
        return None if self.albedo is None else np.asarray(self.albedo.as_tensor().numpy(), dtype=np.float32)

    def intrinsic_matrix(self) -> np.ndarray:
        """(3, 3) float64 colour intrinsics."""
        return as_intrinsic_matrix(self.intrinsic)

    @classmethod
    def from_arrays(cls, depth: np.ndarray, mask: np.ndarray, K: np.ndarray, *, albedo=None, poses=None,
                    lighting=None, method: str = "ours", **kwargs) -> "Refinement":
        """Build a Refinement from numpy arrays; normals are computed from depth (DESIGN section 2).

        depth (H, W) metres, mask (H, W) bool, K (3, 3), albedo (H, W, 3) or None,
        poses (n, 4, 4) or None, lighting (n, 4) or None.
        """
        mask = np.asarray(mask, dtype=bool) & (np.asarray(depth) > 0)
        depth = np.where(mask, depth, 0.0).astype(np.float32)
        normals, _ = perspective_normals(depth, K, mask)
        tensor = lambda a: None if a is None else o3d.core.Tensor(np.asarray(a, dtype=np.float64))  # noqa: E731
        return cls(
            depth=image_from_array(depth[..., None]),
            normals=image_from_array(normals.astype(np.float32)),
            mask=image_from_array((mask.astype(np.uint8) * 255)[..., None]),
            intrinsic=o3d.core.Tensor(np.asarray(K, dtype=np.float64)),
            albedo=None if albedo is None else image_from_array(np.asarray(albedo, dtype=np.float32)),
            poses=tensor(poses),
            lighting=tensor(lighting),
            method=method,
            **kwargs,
        )
