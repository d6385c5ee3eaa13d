"""A closed, printable solid of a reconstruction: the views' depths carve a voxel block.

Every voxel of a block around the fused mesh starts solid; a view carves away the voxels it
sees as empty (projecting outside its object mask, or in front of its depth by more than
``margin``). What no view can see (the inside, the unseen bottom of a ring, the back of an
arc) stays solid, so the block's own faces close it flat. The occupancy is smoothed by one
voxel and its 0.5 level contoured (VTK flying edges via pyvista) into a closed surface, then
scaled to the print size in millimetres with the capture's up axis along +z.
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
import scipy.ndimage as ndi

from ..export import check_solid, solid_volume
from ..model.camera import project, transform

#: Least distance of the smoothed occupancy from the contoured level at any grid point.
LEVEL_CLEARANCE = 1e-3


def carve(views: list, lower: np.ndarray, upper: np.ndarray, voxel: float, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Occupancy (nx, ny, nz) float32 in {0, 1} of voxels over the box [lower, upper] (world, metres)
    and the box's origin (3,): 1 where no view sees empty space."""
    shape = np.maximum(np.ceil((upper - lower) / voxel).astype(int) + 1, 2)
    axes = [lower[i] + voxel * np.arange(shape[i]) for i in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    solid = np.ones(len(points), dtype=bool)
    for view in views:
        u, v, z = project(transform(view.world_to_camera, points), view.K)
        H, W = view.mask.shape
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & (u > -0.5) & (u < W - 0.5) & (v > -0.5) & (v < H - 0.5)
        iu, iv = np.rint(np.where(inside, u, 0)).astype(int), np.rint(np.where(inside, v, 0)).astype(int)
        on_object = view.mask[iv, iu]
        in_front = on_object & (z < view.depth[iv, iu] - margin)
        solid &= ~(inside & (~on_object | in_front))
    return solid.reshape(shape).astype(np.float32), lower


def contour(occupancy: np.ndarray, origin: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Closed surface (positions (n, 3) metres, triangles (T, 3)) of the smoothed occupancy's 0.5 level."""
    import pyvista as pv

    field = np.pad(ndi.gaussian_filter(occupancy, 1.0), 1)  # an empty layer all round closes the surface
    # no grid point on or within LEVEL_CLEARANCE of the level: a crossing that near a grid point
    # puts the vertices of that point's edges within float32 rounding of one another, and a
    # slicer that merges equal STL vertices would then see a non-manifold surface
    near = np.abs(field - 0.5) < LEVEL_CLEARANCE
    field[near] = np.where(field[near] < 0.5, 0.5 - LEVEL_CLEARANCE, 0.5 + LEVEL_CLEARANCE)
    grid = pv.ImageData(dimensions=field.shape, spacing=(voxel,) * 3, origin=tuple(origin - voxel))
    grid.point_data["occupancy"] = field.ravel(order="F")
    surface = grid.contour([0.5], scalars="occupancy").triangulate().clean()
    faces = surface.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
    return np.asarray(surface.points, dtype=np.float64), faces


def print_frame(positions: np.ndarray, up: np.ndarray, size_mm: float) -> np.ndarray:
    """Positions (n, 3) turned so ``up`` is +z, scaled so the largest extent is ``size_mm``, minimum corner at 0."""
    z = up / np.linalg.norm(up)
    x = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    turned = positions @ R.T
    turned -= turned.min(axis=0)
    return turned * (size_mm / turned.max())


def closed_solid(views: list, mesh_positions: np.ndarray, up: np.ndarray, voxel: float,
                 size_mm: float) -> o3d.t.geometry.TriangleMesh:
    """The print solid (millimetres, +z up) of the views around a fused mesh; checked by
    :func:`o3d_mvps.export.check_solid` (ExportError when it fails)."""
    lower, upper = mesh_positions.min(axis=0) - 2 * voxel, mesh_positions.max(axis=0) + 2 * voxel
    occupancy, origin = carve(views, lower, upper, voxel, margin=2 * voxel)
    labels, count = ndi.label(occupancy > 0.5)
    if count > 1:  # keep the largest solid piece
        sizes = np.bincount(labels.ravel())[1:]
        occupancy = (labels == 1 + int(np.argmax(sizes))).astype(np.float32)
    positions, triangles = contour(occupancy, origin, voxel)
    return mesh_solid(positions, triangles, up, size_mm)


def mesh_solid(positions: np.ndarray, triangles: np.ndarray, up: np.ndarray,
               size_mm: float) -> o3d.t.geometry.TriangleMesh:
    """A closed mesh (positions (n, 3) metres, triangles (T, 3)) as a print solid: millimetres, ``up``
    turned to +z, largest extent ``size_mm`` (:func:`print_frame`), outward triangles; checked by
    :func:`o3d_mvps.export.check_solid` (ExportError naming the defect when the mesh is open)."""
    positions = print_frame(np.asarray(positions, dtype=np.float64), np.asarray(up, dtype=np.float64), size_mm)
    triangles = np.asarray(triangles, dtype=np.int64)
    if solid_volume(positions, triangles) < 0:  # outward orientation
        triangles = triangles[:, ::-1]
    check_solid(positions, triangles)
    mesh = o3d.t.geometry.TriangleMesh(o3d.core.Tensor(positions.astype(np.float32)),
                                       o3d.core.Tensor(triangles.astype(np.int32)))
    mesh.compute_vertex_normals()
    return mesh
