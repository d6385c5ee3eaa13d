"""The fused mesh cleaned: its largest piece kept, small holes closed."""

from __future__ import annotations

import numpy as np
import open3d as o3d


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
