"""The fused mesh cleaned and coloured: largest piece, small holes closed, albedo per vertex."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from ..colour import linear_to_srgb
from ..model.camera import project, transform
from ..model.warping import sample_bilinear
from .fusion import pixel_weights

#: Relative depth margin within which a view's depth confirms that it sees a vertex.
VISIBILITY_TOLERANCE = 0.01


def clean_mesh(mesh: o3d.t.geometry.TriangleMesh, hole_size: float) -> o3d.t.geometry.TriangleMesh:
    """The largest connected piece of ``mesh`` (by triangle count), holes up to ``hole_size``
    metres across closed, vertex normals recomputed."""
    legacy = mesh.to_legacy()
    labels, counts, _ = legacy.cluster_connected_triangles()
    labels = np.asarray(labels)
    if len(counts) > 1:
        legacy.remove_triangles_by_mask(labels != int(np.argmax(counts)))
        legacy.remove_unreferenced_vertices()
    positions, tri = fill_small_holes(np.asarray(legacy.vertices), np.asarray(legacy.triangles), hole_size)
    cleaned = o3d.t.geometry.TriangleMesh(o3d.core.Tensor(positions.astype(np.float32)),
                                          o3d.core.Tensor(tri.astype(np.int32)))
    cleaned.compute_vertex_normals()
    return cleaned


def boundary_loops(tri: np.ndarray) -> list[list[int]]:
    """Closed loops of boundary edges (edges of one triangle) of a mesh's triangles (T, 3), as vertex lists."""
    a, b = tri.ravel(), tri[:, [1, 2, 0]].ravel()
    directed = set(zip(a.tolist(), b.tolist()))
    following = {u: v for u, v in directed if (v, u) not in directed}  # a hole runs its edges once
    loops = []
    while following:
        start, loop = next(iter(following)), []
        vertex = start
        while vertex in following:
            loop.append(vertex)
            vertex = following.pop(vertex)
        if vertex == start and len(loop) >= 3:
            loops.append(loop)
    return loops


def fill_small_holes(positions: np.ndarray, tri: np.ndarray, hole_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Close every boundary loop whose extent is below ``hole_size`` metres with a fan around its centroid."""
    new_points, new_tri = [], []
    n = len(positions)
    for loop in boundary_loops(tri):
        ring = positions[loop]
        if np.ptp(ring, axis=0).max() >= hole_size:
            continue
        centre = n + len(new_points)
        new_points.append(ring.mean(axis=0))
        # the loop runs opposite to the hole's missing triangles: (v_k+1, v_k, centre) matches the mesh
        new_tri += [[loop[(k + 1) % len(loop)], loop[k], centre] for k in range(len(loop))]
    if not new_points:
        return positions, tri
    return np.vstack([positions, new_points]), np.vstack([tri, np.asarray(new_tri, dtype=tri.dtype)])


def colour_vertices(positions: np.ndarray, normals: np.ndarray, views: list, edge_px: float) -> np.ndarray:
    """sRGB colours (n, 3) in [0, 1] of mesh vertices from the views' albedos.

    Each vertex takes the albedo of the view that sees it best (facing angle times the
    silhouette ramp of :func:`~.fusion.pixel_weights`, seen = its depth there within 1 %); the
    views' albedos are first brought to a common scale (each refinement fixes its albedo only
    up to a factor) by the median ratio over vertices seen by several views. Vertices no view
    sees take their nearest coloured neighbour's colour. positions, normals: (n, 3) world frame.
    """
    n, k = len(positions), len(views)
    samples = np.zeros((k, n, 3))
    scores = np.zeros((k, n))
    for j, view in enumerate(views):
        q = transform(view.world_to_camera, positions)
        u, v, z = project(q, view.K)
        H, W = view.depth.shape
        inside = (z > 0) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        iu, iv = np.rint(np.where(inside, u, 0)).astype(int), np.rint(np.where(inside, v, 0)).astype(int)
        seen = inside & view.mask[iv, iu] & (np.abs(view.depth[iv, iu] - z) < VISIBILITY_TOLERANCE * z)
        facing = -np.einsum("ij,ij->i", normals @ view.world_to_camera[:3, :3].T, q) / np.linalg.norm(q, axis=1)
        weight = pixel_weights(view.depth, view.mask, view.K, 1.0, edge_px)[iv, iu]
        scores[j] = np.where(seen, np.clip(facing, 0, 1) * weight, 0.0)
        samples[j] = sample_bilinear(view.albedo, np.where(inside, u, 0), np.where(inside, v, 0))
    gains = np.ones(k)
    luminance = samples.mean(axis=2)
    for _ in range(3):  # blend, rescale each view to the blend, repeat
        blend = (scores * gains[:, None] * luminance).sum(0) / np.maximum(scores.sum(0), 1e-12)
        for j in range(k):
            shared = (scores[j] > 0) & ((scores > 0).sum(0) > 1) & (luminance[j] > 1e-4)
            if shared.sum() >= 10:
                gains[j] = np.median(blend[shared] / luminance[j][shared])
    best = np.argmax(scores, axis=0)
    colours = samples[best, np.arange(n)] * gains[best][:, None]
    coloured = scores.max(axis=0) > 0
    if coloured.any() and not coloured.all():
        _, nearest = cKDTree(positions[coloured]).query(positions[~coloured])
        colours[~coloured] = colours[coloured][nearest]
    return linear_to_srgb(np.clip(colours / max(np.percentile(colours, 99.5), 1e-6), 0.0, 1.0))
