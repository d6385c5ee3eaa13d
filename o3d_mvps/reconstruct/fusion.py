"""Weighted TSDF fusion of depth maps in an Open3D ``VoxelBlockGrid``.

Open3D's ``VoxelBlockGrid.integrate`` gives every pixel the same weight; here each pixel
carries its own (:func:`pixel_weights`), so the update is done on the grid's attribute arrays:
for every voxel of the blocks the depth map touches, the signed distance along the ray
``sdf = depth(u, v) - z`` (metres, positive in front of the surface) is truncated to
``[-trunc, trunc]``, divided by ``trunc`` and averaged in with the pixel's weight; voxels more
than ``trunc`` behind the surface are left alone. Marching cubes of the zero level
(``extract_triangle_mesh``) gives the mesh.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import scipy.ndimage as ndi

from ..model.camera import backproject, project, transform
from ..model.normals import perspective_normals

#: Truncation distance in voxels.
TRUNCATION_VOXELS = 4.0
#: Largest depth (metres) a depth map is fused to.
DEPTH_MAX_M = 3.0
#: Grazing-angle exponent of the weights: raw sensor depth degrades as cos(angle) at grazing
#: views; refined depth (photometric normals) much less.
GRAZING_EXPONENT = {"raw": 1.0, "refined": 0.25}


def pixel_weights(depth: np.ndarray, mask: np.ndarray, K: np.ndarray, grazing_exponent: float,
                  edge_px: float) -> np.ndarray:
    """Fusion weights (H, W) in [0, 1] of a depth map: cos(view angle)^grazing_exponent times a ramp
    from 0 at the silhouette to 1 at ``edge_px`` pixels inside it; 0 outside ``mask`` or without depth.

    depth: (H, W) metres; mask: (H, W) bool; K: (3, 3) intrinsics of that grid.
    """
    valid = mask & (depth > 0)
    normals, _ = perspective_normals(depth, K, valid)
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], axis=-1)
    cos = np.clip(-np.sum(normals * rays, axis=-1) / np.linalg.norm(rays, axis=-1), 0.0, 1.0)
    inside = ndi.distance_transform_edt(valid)  # 1 at the outermost object pixels
    ramp = np.clip(inside / max(edge_px, 1e-9), 0.0, 1.0)
    return np.where(valid, cos**grazing_exponent * ramp, 0.0)


class TSDFVolume:
    """A VoxelBlockGrid of ``tsdf`` and ``weight`` with per-pixel weighted integration.

    voxel: edge length in metres; world frame: the capture's reference camera.
    """

    def __init__(self, voxel: float, block_count: int = 40000):
        self.voxel = float(voxel)
        self.trunc = TRUNCATION_VOXELS * self.voxel
        self.grid = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3d.core.float32, o3d.core.float32),
                                                  ((1), (1)), self.voxel, 8, block_count, o3d.core.Device("CPU:0"))

    def integrate(self, depth: np.ndarray, weights: np.ndarray, K: np.ndarray, world_to_camera: np.ndarray) -> None:
        """Fuse one depth map (H, W) metres (0 = none) with its weights (H, W) seen from ``world_to_camera`` (4, 4)."""
        depth = np.where(weights > 0, depth, 0.0).astype(np.float32)
        if not (depth > 0).any():
            return
        # the blocks within the truncation of every pixel's point (the depth-image overload samples
        # every 4th pixel: on a low-resolution depth map it left whole blocks of the surface out)
        v, u = np.nonzero((depth > 0) & (depth <= DEPTH_MAX_M))
        points = transform(np.linalg.inv(np.asarray(world_to_camera, dtype=np.float64)),
                           backproject(depth[v, u].astype(np.float64), K, u.astype(np.float64), v.astype(np.float64)))
        cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(points.astype(np.float32)))
        coords = self.grid.compute_unique_block_coordinates(cloud, TRUNCATION_VOXELS)
        hashmap = self.grid.hashmap()
        created, is_new = hashmap.activate(coords)
        created = created.numpy()[is_new.numpy()]
        for name in ("tsdf", "weight"):  # a new block's memory may hold an earlier block's values
            self.grid.attribute(name).numpy()[created] = 0
        buffers, _ = hashmap.find(coords)
        centres, indices = self.grid.voxel_coordinates_and_flattened_indices(buffers)
        centres, indices = centres.numpy().astype(np.float64), indices.numpy().reshape(-1)
        u, v, z = project(transform(np.asarray(world_to_camera, dtype=np.float64), centres), K)
        H, W = depth.shape
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & (u > -0.5) & (u < W - 0.5) & (v > -0.5) & (v < H - 0.5)
        iu = np.rint(np.where(inside, u, 0)).astype(np.int64)
        iv = np.rint(np.where(inside, v, 0)).astype(np.int64)
        d, w = depth[iv, iu], weights[iv, iu].astype(np.float32)
        sdf = d - z
        update = inside & (d > 0) & (w > 0) & (sdf >= -self.trunc)
        indices, w = indices[update], w[update]
        value = (np.minimum(sdf[update], self.trunc) / self.trunc).astype(np.float32)
        tsdf = self.grid.attribute("tsdf").numpy().reshape(-1)  # views of the grid's memory
        weight = self.grid.attribute("weight").numpy().reshape(-1)
        total = weight[indices] + w
        tsdf[indices] = (tsdf[indices] * weight[indices] + value * w) / total
        weight[indices] = total

    def extract_mesh(self, weight_threshold: float) -> o3d.t.geometry.TriangleMesh:
        """Marching-cubes mesh of the zero level where the accumulated weight reaches ``weight_threshold``."""
        return self.grid.extract_triangle_mesh(weight_threshold=weight_threshold)
