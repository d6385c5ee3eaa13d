"""One UV atlas texture for the fused mesh, coloured texel by texel from the views' albedos.

Open3D's UVAtlas (``compute_uvatlas``: isochart charts packed in a square) lays the mesh out;
``bake_vertex_attr_textures`` rasterises the vertex positions and normals into the atlas
(each texel the barycentric blend over its triangle, the charts dilated by a margin so
filtering does not bleed the background in), and every covered texel is coloured like a
surface point (:class:`~.colour.ViewColours`): the texture carries the albedo at texel
resolution, not just the vertex colours. Texels no view sees take the nearest vertex's colour.
Texture coordinates follow OBJ (V up, row 0 of the image at V = 1), like
:func:`o3d_mvps.export.refinement_to_mesh`.
"""

from __future__ import annotations

import warnings

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from .colour import ViewColours

#: Triangles per UVAtlas partition (partitions are charted in parallel: a 20k-triangle mesh
#: takes 65 s in one partition, 3 s in ten).
TRIANGLES_PER_PARTITION = 2000
#: Empty texels between charts, and texels the charts are dilated by.
GUTTER_PX, MARGIN_PX = 4.0, 2.0


def texture_mesh(mesh: o3d.t.geometry.TriangleMesh, colouring: ViewColours, size: int) -> bool:
    """Give ``mesh`` (vertex positions, normals and colours, world frame) ``triangle.texture_uvs``
    (T, 3, 2) and a ``size`` x ``size`` sRGB albedo texture in its material; returns whether it did
    (UVAtlas fails on some non-manifold meshes: a warning, and the mesh keeps its vertex colours)."""
    atlas = o3d.t.geometry.TriangleMesh(mesh.vertex.positions, mesh.triangle.indices.to(o3d.core.int64))
    atlas.vertex.normals = mesh.vertex.normals
    atlas.vertex["coverage"] = o3d.core.Tensor(np.ones((len(mesh.vertex.positions), 1), dtype=np.float32))
    partitions = max(1, len(atlas.triangle.indices) // TRIANGLES_PER_PARTITION)
    try:
        atlas.compute_uvatlas(size, gutter=GUTTER_PX, parallel_partitions=partitions)
    except RuntimeError as error:
        warnings.warn(f"no texture atlas for this mesh ({error}); it keeps its vertex colours", stacklevel=2)
        return False
    baked = atlas.bake_vertex_attr_textures(size, {"positions", "normals", "coverage"}, margin=MARGIN_PX,
                                            update_material=False)
    covered = baked["coverage"].numpy()[..., 0] > 0.5
    points = baked["positions"].numpy()[covered].astype(np.float64)
    normals = baked["normals"].numpy()[covered].astype(np.float64)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    texels, seen = colouring.colours(points, normals)
    vertices = mesh.vertex.positions.numpy()
    if not seen.all():
        _, nearest = cKDTree(vertices).query(points[~seen])
        texels[~seen] = mesh.vertex.colors.numpy()[nearest]
    image = np.zeros((size, size, 3))
    image[covered] = texels
    image[~covered] = texels.mean(axis=0)  # mip levels blend towards the mean, not black
    mesh.triangle.texture_uvs = atlas.triangle.texture_uvs
    mesh.material.set_default_properties()
    mesh.material.texture_maps["albedo"] = o3d.t.geometry.Image(
        o3d.core.Tensor(np.ascontiguousarray(np.round(image * 255).astype(np.uint8))))
    return True
