"""Rendering one frame: ray casting, normals, albedo and shading at colour resolution."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from .scene import SyntheticScene, apply_matrix


@dataclass
class FrameRender:
    """Noise-free buffers of one frame at colour resolution (H, W), camera-frame quantities.

    ``mask`` (H, W) bool hit; ``depth`` (H, W) float64 z metres (0 off the object);
    ``points`` (H, W, 3) camera-frame hit points; ``normals`` (H, W, 3) unit face normals,
    camera frame, pointing to the camera; ``albedo`` (H, W, 3) linear RGB;
    ``color`` (H, W, 3) linear RGB ``albedo * shading`` (not clipped). Zero off the object.
    """

    mask: np.ndarray
    depth: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    color: np.ndarray


def render_frame(scene: SyntheticScene, pose: np.ndarray, light) -> FrameRender:
    """Ray-cast one frame with ``pose`` (4, 4) reference -> frame; one ray per pixel centre.

    ``light`` is a :class:`PointLight` or :class:`DirectionalLight` (see :func:`make_light`).
    """
    W, H = scene.size
    R_c2r = pose[:3, :3].T
    C = -R_c2r @ pose[:3, 3]
    d_cam = scene.rays
    rays = np.empty((H * W, 6), dtype=np.float32)
    rays[:, :3] = C
    rays[:, 3:] = apply_matrix(R_c2r.astype(np.float32), scene.rays32)
    hit = scene.raycaster.cast_rays(o3d.core.Tensor(rays), nthreads=0)
    t = hit["t_hit"].numpy()  # distance along the unit ray
    index = np.flatnonzero(np.isfinite(t))
    d_hit = d_cam[index]
    points = t[index, None].astype(np.float64) * d_hit
    smooth = scene.smooth_normals(hit["primitive_ids"].numpy()[index].astype(np.int64),
                                  hit["primitive_uvs"].numpy()[index].astype(np.float64))
    normals = apply_matrix(R_c2r.T, smooth)
    normals *= np.where(np.einsum("ij,ij->i", normals, d_hit) > 0, -1.0, 1.0)[:, None]  # face the camera
    albedo = scene.albedo(scene.object_coordinates(apply_matrix(R_c2r, points) + C))

    def image(values: np.ndarray) -> np.ndarray:
        out = np.zeros((H * W,) + values.shape[1:])
        out[index] = values
        return out.reshape((H, W) + values.shape[1:])

    mask = np.zeros(H * W, dtype=bool)
    mask[index] = True
    frame = FrameRender(
        mask=mask.reshape(H, W),
        depth=image(points[:, 2]),
        points=image(points),
        normals=image(normals),
        albedo=image(albedo),
        color=np.zeros((H, W, 3)),
    )
    frame.color[frame.mask] = albedo * light.shading(scene, pose, frame)[:, None]
    return frame
