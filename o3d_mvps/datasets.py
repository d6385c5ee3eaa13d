"""Meshes shipped with the package (Stanford 3D Scanning Repository; see data/PROVENANCE.md)."""

from __future__ import annotations

from pathlib import Path

import open3d as o3d

DATA_DIR = Path(__file__).resolve().parent / "data"
MESHES = {"bunny": "bunny.ply", "armadillo": "armadillo_50k.obj"}


def mesh_path(name: str) -> Path:
    """Path of a shipped mesh: ``"bunny"`` or ``"armadillo"``."""
    if name not in MESHES:
        raise ValueError(f"unknown mesh {name!r}; shipped meshes are {sorted(MESHES)}, or pass a file path")
    return DATA_DIR / MESHES[name]


def load_mesh(name_or_path) -> o3d.t.geometry.TriangleMesh:
    """A shipped mesh by name, or any mesh file Open3D reads, as a tensor TriangleMesh (float64)."""
    path = mesh_path(name_or_path) if str(name_or_path) in MESHES else Path(name_or_path)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file {path} does not exist; give a .ply/.obj/.stl path or one of {sorted(MESHES)}")
    legacy = o3d.io.read_triangle_mesh(str(path))
    if len(legacy.triangles) == 0:
        raise ValueError(f"{path} holds no triangles (corrupt or not a mesh); give a triangle mesh file")
    return o3d.t.geometry.TriangleMesh.from_legacy(legacy, vertex_dtype=o3d.core.float64)
