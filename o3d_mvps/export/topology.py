"""Triangle meshes as numpy arrays: views of Open3D meshes, sorted unique keys, membership, normals."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from ..errors import ExportError


def unique(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sorted unique values of a 1-D integer array, the inverse index and the counts.

    Sort-based: numpy 2.x's ``np.unique`` / ``np.isin`` take seconds on millions of int64
    keys (hash-based paths), a plain sort a fraction of a second.
    """
    keys = np.asarray(keys).ravel()
    order = np.argsort(keys, kind="stable")
    ordered = keys[order]
    starts = np.empty(len(keys), dtype=bool)
    starts[:1] = True
    np.not_equal(ordered[1:], ordered[:-1], out=starts[1:])
    group = np.cumsum(starts) - 1
    inverse = np.empty(len(keys), dtype=np.int64)
    inverse[order] = group
    return ordered[starts], inverse, np.bincount(group) if len(keys) else np.zeros(0, dtype=np.int64)


def contains(sorted_table: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Boolean (N,): which queries occur in a sorted 1-D array."""
    if len(sorted_table) == 0:
        return np.zeros(len(queries), dtype=bool)
    at = np.minimum(np.searchsorted(sorted_table, queries), len(sorted_table) - 1)
    return sorted_table[at] == queries


def triangle_cross(positions: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(T, 3) cross products (p1 - p0) x (p2 - p0): normal directions, length = 2 x area."""
    p0, p1, p2 = (positions[tri[:, k]] for k in range(3))
    return np.cross(p1 - p0, p2 - p0)


def vertex_normals(positions: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (n, 3) float64 of a triangle mesh."""
    cross = triangle_cross(positions, tri)
    normals = np.zeros_like(positions, dtype=np.float64)
    for k in range(3):
        normals[:, k] = sum(np.bincount(tri[:, c], weights=cross[:, k], minlength=len(positions)) for c in range(3))
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """numpy views of a mesh: positions (n, 3), triangles (T, 3) int64, normals (n, 3) or None,
    colours (n, 3) or None, texture_uvs (T, 3, 2) or None, albedo texture (H, W, C) uint8 or None.

    Accepts an ``o3d.t.geometry.TriangleMesh`` or a legacy ``o3d.geometry.TriangleMesh``.
    """
    if isinstance(mesh, o3d.geometry.TriangleMesh):
        mesh = o3d.t.geometry.TriangleMesh.from_legacy(mesh)
    if not isinstance(mesh, o3d.t.geometry.TriangleMesh):
        raise ExportError(f"expected an Open3D TriangleMesh, got {type(mesh).__name__}")
    positions = mesh.vertex.positions.numpy() if "positions" in mesh.vertex else np.zeros((0, 3))
    tri = mesh.triangle.indices.numpy().astype(np.int64) if "indices" in mesh.triangle else np.zeros((0, 3), np.int64)
    normals = mesh.vertex.normals.numpy() if "normals" in mesh.vertex else None
    colours = mesh.vertex.colors.numpy() if "colors" in mesh.vertex else None
    uvs = mesh.triangle.texture_uvs.numpy() if "texture_uvs" in mesh.triangle else None
    texture = None
    if mesh.has_valid_material() and "albedo" in mesh.material.texture_maps:
        texture = as_uint8(mesh.material.texture_maps["albedo"].as_tensor().numpy())
    return positions, tri, normals, colours, uvs, texture


def as_uint8(image: np.ndarray) -> np.ndarray:
    """An (H, W, C) uint8 image from uint8, uint16 or float [0, 1] data."""
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None]
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        return (image // 257).astype(np.uint8)
    return np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)
