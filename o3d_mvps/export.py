"""Meshes from a Refinement: a textured surface for viewers and a watertight solid for printing.

Two products (DESIGN section 1):

- :func:`refinement_to_mesh` -- the refined depth back-projected into the reference camera
  frame (metres) and triangulated on the pixel grid, with vertex normals, per-vertex sRGB
  colours, texture coordinates and the albedo image as the material's albedo texture.
- :func:`printable_solid` -- that relief closed into a watertight, consistently oriented solid
  in millimetres, ready for a slicer.

Writers: :func:`write_mesh` (``.obj`` + ``.mtl`` + texture PNG, ``.glb``, ``.ply``, ``.stl``) and
:func:`write_stl`. Every writer refuses to replace an existing file unless ``overwrite=True``
and writes atomically (temporary files renamed into place), so a failure leaves no
half-written output.

Conventions
-----------
Pixel (u, v) is column u, row v, with pixel centres at integer coordinates
(:mod:`o3d_mvps.model.camera`). Texture coordinates follow OBJ (and Open3D's in-memory
convention, which its glTF writer converts): ``U = (u + 0.5) / W``, ``V = 1 - (v + 0.5) / H``,
origin at the bottom-left of the image. Colours (``vertex.colors`` and the texture) are
sRGB-encoded, ready for display; the albedo itself is linear RGB.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import scipy.sparse as sp
from scipy.ndimage import map_coordinates
from scipy.optimize import brentq
from scipy.sparse.csgraph import connected_components

from .colour import linear_to_srgb
from .errors import ExportError
from .fileio import atomic_files, write_png
from .model.camera import as_intrinsic_matrix, backproject

__all__ = [
    "DEFAULT_MAX_DEPTH_JUMP",
    "MESH_SUFFIXES",
    "refinement_to_mesh",
    "printable_solid",
    "check_solid",
    "solid_volume",
    "write_mesh",
    "write_stl",
    "mesh_arrays",
]

#: Default discontinuity threshold of :func:`refinement_to_mesh`, in pixel footprints: an edge
#: between neighbouring pixels is cut when its depth step exceeds 10 footprints, i.e. where the
#: surface is steeper than atan(10) = 84 degrees to the image plane.
DEFAULT_MAX_DEPTH_JUMP = 10.0

#: File suffixes :func:`write_mesh` writes.
MESH_SUFFIXES = (".obj", ".glb", ".ply", ".stl")

PIECES = ("largest", "all")


# ------------------------------------------------------------------------------------------
# Textured mesh
# ------------------------------------------------------------------------------------------
def refinement_to_mesh(refinement, *, max_depth_jump: float | None = DEFAULT_MAX_DEPTH_JUMP,
                       max_triangles: int | None = None, skirts: bool = True) -> o3d.t.geometry.TriangleMesh:
    """Triangulate a refinement's depth into a textured mesh in the reference camera frame.

    Every mask pixel with positive depth is back-projected to a vertex (metres, reference
    camera coordinates: x right, y down, z forward). Each 2x2 pixel quad gives two triangles
    when its four corners are usable, or one when three are; the quad's diagonal is the one
    with the smaller depth difference. A triangle is dropped when one of its edges spans a
    depth discontinuity (see ``max_depth_jump``). Vertices joining two otherwise separate
    triangle fans ("bow-ties") lose their triangles, so the relief is edge- and
    vertex-manifold, and all triangles face the camera.

    Cutting a quad at a depth jump leaves a crack, up to one pixel wide, through which the
    reference camera would see the background. With ``skirts`` the far surface is extended
    under the near edge to close it: the missing triangles of a cut quad are added with their
    near corners moved back along their camera rays to the quad's far depth (extra vertices).
    Seen from the reference camera the mesh then covers every quad of the mask, and still no
    triangle joins the near and the far surface. A skirt can touch the relief at a single far
    vertex (not vertex-manifold there); :func:`printable_solid`, which needs a manifold relief,
    meshes without skirts.

    Parameters
    ----------
    refinement : Refinement
        depth (H, W, 1) metres, mask (H, W, 1), intrinsic (3, 3), albedo (H, W, 3) linear RGB
        or None.
    max_depth_jump : float or None
        Largest depth step allowed along a triangle edge, in pixel footprints: an edge between
        pixels p and q (offset (du, dv) pixels) is kept when
        ``|z_p - z_q| <= max_depth_jump * min(z_p, z_q) * hypot(du / fx, dv / fy)``.
        A footprint is the lateral size of the pixel step at that depth, so the threshold is the
        tangent of the steepest surface slope kept (10 -> 84 degrees); it is independent of
        distance and resolution. None keeps every edge.
    max_triangles : int or None
        Triangle budget. When exceeded, the mesh is simplified by quadric decimation (Open3D,
        legacy implementation); decimation keeps geometry only, so texture coordinates are
        recomputed by projecting the vertices into the reference camera (exact for this
        texture), colours are re-sampled bilinearly from the albedo and normals are recomputed
        from the triangles.
    skirts : bool
        Close the cracks at depth jumps (see above). :func:`printable_solid` meshes without.

    Returns
    -------
    o3d.t.geometry.TriangleMesh
        ``vertex.positions`` (n, 3) float32 metres; ``vertex.normals`` (n, 3) float32 unit,
        toward the camera (the refinement's normals, or the triangles' after decimation);
        ``triangle.indices`` (T, 3) int64, counter-clockwise seen from the camera.
        With albedo: ``vertex.colors`` (n, 3) float32 sRGB in [0, 1]; ``triangle.texture_uvs``
        (T, 3, 2) float32 (OBJ convention, V up); ``material.texture_maps["albedo"]`` (H, W, 3)
        uint8 sRGB image.

    Raises
    ------
    ExportError
        When no triangle can be built (empty mask, no valid depth, or every edge cut).
    """
    depth = refinement.depth_array().astype(np.float64)
    mask = refinement.mask_array() & np.isfinite(depth) & (depth > 0)
    K = as_intrinsic_matrix(refinement.intrinsic)
    height, width = depth.shape
    if max_depth_jump is not None and not (np.isfinite(max_depth_jump) and max_depth_jump > 0):
        raise ExportError(f"max_depth_jump must be a positive number of pixel footprints or None, got {max_depth_jump}")
    if max_triangles is not None and int(max_triangles) < 1:
        raise ExportError(f"max_triangles must be a positive integer, got {max_triangles}")
    if not mask.any():
        raise ExportError("the refinement's mask is empty (no pixel with positive depth); nothing to mesh")

    tri, missing = _grid_triangles(depth, mask, K, max_depth_jump)
    tri = _drop_bowties(tri, height * width)
    vertex_depth = depth.ravel()
    if skirts and missing.size and len(tri):
        skirt, far_depth = _skirt_triangles(depth, missing)
        tri = np.concatenate([tri, skirt])
        vertex_depth = np.concatenate([vertex_depth, far_depth])  # vertex HW + p: pixel p moved back
    if len(tri) == 0:
        raise ExportError(
            f"no triangle could be built from {int(mask.sum())} mask pixels: the mask has no 2x2 block "
            "of valid pixels, or every edge exceeds max_depth_jump (raise it, or pass None)"
        )
    ids, tri = _compact(tri)
    v, u = np.divmod(ids % (height * width), width)
    positions = backproject(vertex_depth[ids], K, u.astype(np.float64), v.astype(np.float64))

    albedo = refinement.albedo_array()
    srgb = None if albedo is None else linear_to_srgb(albedo)

    if max_triangles is not None and len(tri) > max_triangles:
        positions, tri = _decimate(positions, tri, int(max_triangles))
        normals = _vertex_normals(positions, tri)
        u, v = _project(positions, K)  # continuous pixel coordinates
        colours = None if srgb is None else _bilinear(srgb, u, v)
    else:
        normals = refinement.normals_array()[v, u].astype(np.float64)
        length = np.linalg.norm(normals, axis=1)
        bad = ~(length > 0.5)
        if bad.any():  # zero normals (should not happen inside the mask): use the triangles'
            normals[bad] = _vertex_normals(positions, tri)[bad]
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        colours = None if srgb is None else srgb[v, u]

    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(positions.astype(np.float32))
    mesh.vertex.normals = o3d.core.Tensor(normals.astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(tri.astype(np.int64))
    if srgb is not None:
        uv = np.stack([(u + 0.5) / width, 1.0 - (v + 0.5) / height], axis=1).astype(np.float32)
        mesh.vertex.colors = o3d.core.Tensor(np.ascontiguousarray(colours, dtype=np.float32))
        mesh.triangle.texture_uvs = o3d.core.Tensor(np.ascontiguousarray(uv[tri]))
        texture = np.round(srgb * 255.0).astype(np.uint8)
        mesh.material.set_default_properties()
        mesh.material.texture_maps["albedo"] = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(texture)))
    return mesh


def _grid_triangles(depth: np.ndarray, mask: np.ndarray, K: np.ndarray,
                    max_depth_jump: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Triangles (T, 3) int64 of flat pixel indices (v * W + u), counter-clockwise seen from the
    camera, and the triangles (M, 3) of quads inside the mask that were cut at a depth jump.

    Quad corners: a = (u, v), b = (u + 1, v), c = (u, v + 1), d = (u + 1, v + 1). The quad is
    split along b-c into (a, c, b) + (b, c, d) or along a-d into (a, d, b) + (a, c, d); a
    triangle exists when its three corners are in the mask and its three edges pass the
    discontinuity test. The diagonal giving more triangles wins, then the one with the
    smaller depth difference, so two triangles of one quad never overlap.
    """
    height, width = depth.shape
    fx, fy = K[0, 0], K[1, 1]
    corners = {
        "a": (slice(0, -1), slice(0, -1)), "b": (slice(0, -1), slice(1, None)),
        "c": (slice(1, None), slice(0, -1)), "d": (slice(1, None), slice(1, None)),
    }
    z = {k: depth[s] for k, s in corners.items()}
    m = {k: mask[s] for k, s in corners.items()}

    def edge(p: str, q: str, du: int, dv: int) -> np.ndarray:
        ok = m[p] & m[q]
        if max_depth_jump is not None:
            footprint = np.minimum(z[p], z[q]) * np.hypot(du / fx, dv / fy)
            ok &= np.abs(z[p] - z[q]) <= float(max_depth_jump) * footprint
        return ok

    ab, cd = edge("a", "b", 1, 0), edge("c", "d", 1, 0)
    ac, bd = edge("a", "c", 0, 1), edge("b", "d", 0, 1)
    ad, bc = edge("a", "d", 1, 1), edge("b", "c", 1, 1)
    t_abc, t_bcd = ab & ac & bc, bc & bd & cd  # diagonal b-c
    t_abd, t_acd = ab & bd & ad, ac & cd & ad  # diagonal a-d
    n_bc = t_abc.astype(np.int8) + t_bcd
    n_ad = t_abd.astype(np.int8) + t_acd
    with np.errstate(invalid="ignore"):
        shorter_ad = np.abs(z["a"] - z["d"]) < np.abs(z["b"] - z["c"])
    use_ad = (n_ad > n_bc) | ((n_ad == n_bc) & shorter_ad)

    index = np.arange(height * width, dtype=np.int64).reshape(height, width)
    ia, ib, ic, id_ = (index[s] for s in corners.values())
    inside = m["a"] & m["b"] & m["c"] & m["d"]
    parts, missing = [], []
    for exists, chosen, (p, q, r) in (
        (t_abc, ~use_ad, (ia, ic, ib)), (t_bcd, ~use_ad, (ib, ic, id_)),
        (t_abd, use_ad, (ia, id_, ib)), (t_acd, use_ad, (ia, ic, id_)),
    ):
        for keep, out in ((exists & chosen, parts), (~exists & chosen & inside, missing)):
            out.append(np.stack([p[keep], q[keep], r[keep]], axis=1))
    return np.concatenate(parts, axis=0), np.concatenate(missing, axis=0)


def _skirt_triangles(depth: np.ndarray, missing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles closing the cracks of cut quads, and the depths (HW,) of the moved-back vertices.

    ``missing`` (M, 3) triangles of flat pixel indices left out at depth jumps. In each, the
    corners nearer than its farthest corner by more than 1 % of the depth become vertex
    ``HW + p`` (pixel p at depth ``far_depth[p]``, the largest far depth of its skirts).
    """
    n = depth.size
    z = depth.ravel()[missing]  # (M, 3)
    far = z.max(axis=1, keepdims=True)
    near = z < far * 0.99
    far_depth = depth.ravel().copy()
    np.maximum.at(far_depth, missing[near], np.broadcast_to(far, z.shape)[near])
    return np.where(near, missing + n, missing), far_depth


def _drop_bowties(tri: np.ndarray, n_vertices: int) -> np.ndarray:
    """Remove the triangles around vertices where separate triangle fans meet.

    For a triangulation embedded in the image plane, the link of vertex p (the edges opposite
    p) has L(p) vertices (distinct neighbours) and T(p) edges (incident triangles); it is one
    path or one cycle, i.e. p is manifold, exactly when ``L(p) - T(p) <= 1``. Repeats until no
    such vertex is left (each pass only removes triangles, so it terminates).
    """
    while len(tri):
        edges = np.sort(tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        keys = _unique(edges[:, 0] * n_vertices + edges[:, 1])[0]
        link = np.bincount(keys // n_vertices, minlength=n_vertices) + np.bincount(keys % n_vertices, minlength=n_vertices)
        fans = link - np.bincount(tri.ravel(), minlength=n_vertices)
        bad = fans >= 2
        if not bad.any():
            break
        tri = tri[~bad[tri].any(axis=1)]
    return tri


def _compact(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Used vertex ids (n,) in increasing order and the triangles (T, 3) re-indexed into them."""
    occupied = np.zeros(int(tri.max()) + 1, dtype=bool)
    occupied[tri] = True
    used = np.flatnonzero(occupied)
    new_index = np.cumsum(occupied) - 1
    return used, new_index[tri].astype(np.int64)


def _unique(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


def _contains(sorted_table: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Boolean (N,): which queries occur in a sorted 1-D array."""
    if len(sorted_table) == 0:
        return np.zeros(len(queries), dtype=bool)
    at = np.minimum(np.searchsorted(sorted_table, queries), len(sorted_table) - 1)
    return sorted_table[at] == queries


def _triangle_cross(positions: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(T, 3) cross products (p1 - p0) x (p2 - p0): normal directions, length = 2 x area."""
    p0, p1, p2 = (positions[tri[:, k]] for k in range(3))
    return np.cross(p1 - p0, p2 - p0)


def _vertex_normals(positions: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (n, 3) float64 of a triangle mesh."""
    cross = _triangle_cross(positions, tri)
    normals = np.zeros_like(positions, dtype=np.float64)
    for k in range(3):
        normals[:, k] = sum(np.bincount(tri[:, c], weights=cross[:, k], minlength=len(positions)) for c in range(3))
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def _project(points: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (u, v), each (n,), of camera-frame points (n, 3)."""
    return K[0, 0] * points[:, 0] / points[:, 2] + K[0, 2], K[1, 1] * points[:, 1] / points[:, 2] + K[1, 2]


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples (n, C) of an (H, W, C) image at pixel coordinates (u, v), clamped to the image."""
    coords = np.stack([v, u])
    return np.stack([map_coordinates(image[..., c], coords, order=1, mode="nearest") for c in range(image.shape[2])], axis=1)


def _decimate(positions: np.ndarray, tri: np.ndarray, max_triangles: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric-decimate a mesh to at most ``max_triangles`` triangles; returns (positions, triangles)."""
    legacy = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(positions), o3d.utility.Vector3iVector(tri.astype(np.int32)))
    simple = legacy.simplify_quadric_decimation(target_number_of_triangles=int(max_triangles))
    simple.remove_degenerate_triangles()
    simple.remove_unreferenced_vertices()
    tri = np.asarray(simple.triangles, dtype=np.int64)
    if len(tri) == 0:
        raise ExportError(f"decimation to {max_triangles} triangles left no triangle; raise max_triangles")
    return np.asarray(simple.vertices, dtype=np.float64), tri


# ------------------------------------------------------------------------------------------
# Print-ready solid
# ------------------------------------------------------------------------------------------
def printable_solid(source, *, size_mm: float = 120.0, base_mm: float = 4.0, pieces: str = "largest",
                    max_depth_jump: float | None = DEFAULT_MAX_DEPTH_JUMP,
                    max_triangles: int | None = None) -> o3d.t.geometry.TriangleMesh:
    """Close a scanned relief into a watertight solid for 3D printing, in millimetres.

    The relief (the mesh of :func:`refinement_to_mesh`, in the reference camera frame) is
    extruded away from the camera to a flat back plate perpendicular to the optical axis at
    ``z = max_z + base``: the bottom is the relief's triangulation projected along the camera
    rays onto the plate (reversed), and a wall along the rays joins every boundary loop of the
    relief (outer outlines and holes) to the plate. Extruding along the rays rather than along
    z keeps the solid free of self-intersections for any depth map (a surface seen at a
    grazing angle folds over when pushed straight back along z); the walls are therefore
    tilted by the viewing angle (at most half the field of view).

    The solid is then scaled so that the largest extent of its bounding box is ``size_mm``
    (the plate thickness behind the deepest point is ``base_mm`` after scaling), and placed in
    a print frame: the camera frame turned 180 degrees about its x axis, so the plate lies on
    z = 0 with the relief pointing up (+z) and image "up" along +y, and the bounding box's
    minimum corner at the origin.

    Parameters
    ----------
    source : Refinement or o3d.t.geometry.TriangleMesh or o3d.geometry.TriangleMesh
        A refinement, or a relief mesh in the reference camera frame (every z > 0, each camera
        ray crossing it at most once, as for the meshes of :func:`refinement_to_mesh`).
    size_mm : float
        Largest bounding-box extent of the solid, millimetres.
    base_mm : float
        Thickness of the plate behind the deepest point of the relief, millimetres.
    pieces : {"largest", "all"}
        Keep the connected piece of the relief with the largest area, or every piece (each
        becomes its own closed shell on the common plate level).
    max_depth_jump, max_triangles
        Passed to :func:`refinement_to_mesh` when ``source`` is a refinement. With
        ``max_triangles`` the relief is decimated first; the solid has about twice as many
        triangles plus its walls.

    Returns
    -------
    o3d.t.geometry.TriangleMesh
        ``vertex.positions`` (n, 3) float32 millimetres, ``triangle.indices`` (T, 3) int64
        with outward (counter-clockwise) orientation, ``triangle.normals`` (T, 3) float32.
        It passes :func:`check_solid`.

    Raises
    ------
    ExportError
        Bad options, an empty relief, or a solid failing one of :func:`check_solid`'s checks.
    """
    if not (np.isfinite(size_mm) and size_mm > 0):
        raise ExportError(f"size_mm must be a positive number of millimetres, got {size_mm}")
    if not (np.isfinite(base_mm) and base_mm > 0):
        raise ExportError(f"base_mm must be a positive number of millimetres, got {base_mm}")
    if pieces not in PIECES:
        raise ExportError(f"pieces must be one of {PIECES}, got {pieces!r}")

    if isinstance(source, (o3d.t.geometry.TriangleMesh, o3d.geometry.TriangleMesh)):
        positions, tri = mesh_arrays(source)[:2]
        positions = positions.astype(np.float64)
        if len(tri) == 0:
            raise ExportError("the mesh has no triangles; nothing to close into a solid")
        if not np.all(positions[:, 2] > 0):
            raise ExportError("the relief mesh must lie in front of the camera (every z > 0), "
                              "in the reference camera frame as refinement_to_mesh returns it")
        tri = _drop_bowties(_orient_toward_camera(positions, tri), len(positions))
    else:
        mesh = refinement_to_mesh(source, max_depth_jump=max_depth_jump, max_triangles=max_triangles, skirts=False)
        positions, tri = mesh_arrays(mesh)[:2]
        positions = positions.astype(np.float64)
        if max_triangles is not None:
            tri = _drop_bowties(_orient_toward_camera(positions, tri), len(positions))
    if len(tri) == 0:
        raise ExportError("no triangle is left after removing non-manifold vertices; nothing to close into a solid")
    tri = _select_pieces(positions, tri, pieces)
    used, tri = _compact(tri)
    top = positions[used]

    scale, plate_z = _print_scale(top, size_mm, base_mm)
    n = len(top)
    bottom = top * (plate_z / top[:, 2:3])  # the same rays, at the plate
    cam = np.concatenate([top, bottom], axis=0)
    solid = np.empty_like(cam)
    solid[:, 0] = scale * cam[:, 0]
    solid[:, 1] = -scale * cam[:, 1]
    solid[:, 2] = scale * (plate_z - cam[:, 2])
    solid[n:, 2] = 0.0  # the plate, exactly
    solid[:, :2] -= solid[:, :2].min(axis=0)

    a, b = _boundary_edges(tri)
    faces = np.concatenate([
        tri,                                   # relief, facing the camera (outward)
        tri[:, ::-1] + n,                      # plate, facing away
        np.stack([b, a, a + n], axis=1),       # walls: each boundary edge a->b of the relief
        np.stack([b, a + n, b + n], axis=1),   # becomes the quad b, a, a', b'
    ]).astype(np.int64)

    check_solid(solid, faces)
    out = o3d.t.geometry.TriangleMesh()
    out.vertex.positions = o3d.core.Tensor(solid.astype(np.float32))
    out.triangle.indices = o3d.core.Tensor(faces)
    cross = _triangle_cross(solid, faces)
    out.triangle.normals = o3d.core.Tensor((cross / np.linalg.norm(cross, axis=1, keepdims=True)).astype(np.float32))
    return out


def _orient_toward_camera(positions: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """The triangles, reversed if most of their area faces away from the camera at the origin."""
    cross = _triangle_cross(positions, tri)
    centroid = positions[tri].mean(axis=1)
    facing = np.einsum("ij,ij->i", cross, centroid)  # < 0 when facing the camera
    return tri[:, ::-1].copy() if facing.sum() > 0 else tri


def _select_pieces(positions: np.ndarray, tri: np.ndarray, pieces: str) -> np.ndarray:
    """The triangles of the largest-area connected piece ("largest") or all of them ("all")."""
    if pieces == "all":
        return tri
    n = len(positions)
    edges = tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    graph = sp.coo_matrix((np.ones(len(edges), dtype=np.int8), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    tri_label = labels[tri[:, 0]]
    area = np.linalg.norm(_triangle_cross(positions, tri), axis=1)
    return tri[tri_label == np.argmax(np.bincount(tri_label, weights=area))]


def _boundary_edges(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Directed boundary edges (a -> b, as the triangle runs) whose reverse is in no triangle."""
    n = int(tri.max()) + 1
    a, b = tri.ravel(), tri[:, [1, 2, 0]].ravel()
    boundary = ~_contains(np.sort(a * n + b), b * n + a)
    return a[boundary], b[boundary]


def _print_scale(top: np.ndarray, size_mm: float, base_mm: float) -> tuple[float, float]:
    """Scale s (mm per metre) and plate depth (metres) making the solid's largest extent size_mm.

    With the plate ``b = base_mm / s`` metres behind the deepest point, the solid spans the
    relief (n, 3) and its projection along the rays onto z = z_max + b. Solves
    ``s * extent(base_mm / s) = size_mm`` for s by Brent's method.
    """
    zmin, zmax = top[:, 2].min(), top[:, 2].max()
    ratio = top[:, :2] / top[:, 2:3]
    rlo, rhi = ratio.min(axis=0), ratio.max(axis=0)
    tlo, thi = top[:, :2].min(axis=0), top[:, :2].max(axis=0)

    def extent(b: float) -> float:
        plate = zmax + b
        lateral = np.maximum(thi, rhi * plate) - np.minimum(tlo, rlo * plate)
        return max(float(lateral.max()), zmax + b - zmin)

    def excess(s: float) -> float:
        return s * extent(base_mm / s) - size_mm

    s_hi = size_mm / extent(0.0)  # excess(s_hi) >= 0: the extent only grows with the plate
    s_lo = s_hi * 1e-9
    if excess(s_lo) >= 0:
        raise ExportError(f"size_mm={size_mm} is too small for base_mm={base_mm}: the plate alone would exceed it; "
                          "raise size_mm or lower base_mm")
    scale = s_hi if excess(s_hi) == 0 else brentq(excess, s_lo, s_hi, xtol=1e-14 * s_hi, rtol=4 * np.finfo(float).eps)
    return scale, zmax + base_mm / scale


def solid_volume(positions: np.ndarray, triangles: np.ndarray) -> float:
    """Signed volume of a closed triangle mesh (positions (n, 3), triangles (T, 3)), in cubed units.

    Positive when the triangles are oriented outward (counter-clockwise seen from outside).
    """
    p = np.asarray(positions, dtype=np.float64)
    p = p - p.mean(axis=0)  # better conditioned; the volume of a closed mesh does not change
    t = np.asarray(triangles)
    return float(np.einsum("ij,ij->i", p[t[:, 0]], np.cross(p[t[:, 1]], p[t[:, 2]])).sum() / 6.0)


def check_solid(mesh_or_positions, triangles: np.ndarray | None = None) -> None:
    """Check that a mesh is a valid printable solid; raise ExportError naming the first failed check.

    Checks, in order: not empty; edge-manifold (no edge in more than two triangles);
    watertight (no edge in only one triangle); consistently oriented, hence orientable (the
    two triangles of every edge run it in opposite directions); vertex-manifold (the
    triangles around every vertex form a single fan); positive signed volume (outward
    orientation). Vectorised numpy; the equivalent Open3D legacy methods (``is_watertight``,
    ``is_orientable``, ...) take minutes on a full-resolution solid, and Open3D's
    self-intersection test is quadratic, so it is not run here (the construction of
    :func:`printable_solid` cannot self-intersect).

    Parameters
    ----------
    mesh_or_positions : o3d.t.geometry.TriangleMesh, o3d.geometry.TriangleMesh or ndarray (n, 3)
    triangles : ndarray (T, 3), only with positions
    """
    if triangles is None:
        positions, tri = mesh_arrays(mesh_or_positions)[:2]
    else:
        positions, tri = np.asarray(mesh_or_positions), np.asarray(triangles, dtype=np.int64)
    if len(tri) == 0:
        raise ExportError("solid check failed (not empty): the mesh has no triangles")
    n = len(positions)
    a, b = tri.ravel(), tri[:, [1, 2, 0]].ravel()  # half-edge k of triangle t (a -> b) is row 3t + k
    undirected = np.minimum(a, b) * n + np.maximum(a, b)
    order = np.argsort(undirected, kind="stable")  # the half-edges of one edge become neighbours
    ordered = undirected[order]
    starts = np.flatnonzero(np.concatenate([[True], ordered[1:] != ordered[:-1]]))
    counts = np.diff(np.append(starts, len(ordered)))
    if (counts > 2).any():
        raise ExportError(f"solid check failed (edge-manifold): {int((counts > 2).sum())} edges are shared by more than two triangles")
    if (counts < 2).any():
        raise ExportError(f"solid check failed (watertight): {int((counts < 2).sum())} boundary edges (used by one triangle only)")
    first, second = order[0::2], order[1::2]  # every edge now has exactly two half-edges
    if np.any(a[first] == a[second]):
        raise ExportError("solid check failed (orientable / consistently oriented): some edges are run in the same "
                          "direction by both of their triangles")
    # Vertex-manifold: link every corner (t, k) at vertex a = tri[t, k] to the corner at a of the
    # triangle across the edge a -> b; the corners around a then form one cycle per fan.
    twin = np.empty_like(order)
    twin[first], twin[second] = second, first   # the half-edge b -> a
    twin_corner = 3 * (twin // 3) + (twin % 3 + 1) % 3    # its end corner, at vertex a
    m = 3 * len(tri)
    graph = sp.coo_matrix((np.ones(m, dtype=np.int8), (np.arange(m), twin_corner)), shape=(m, m))
    n_fans, _ = connected_components(graph, directed=False)
    n_used = int(np.count_nonzero(np.bincount(tri.ravel())))
    if n_fans != n_used:
        raise ExportError(f"solid check failed (vertex-manifold): {n_fans - n_used} extra triangle fans meet at shared vertices")
    volume = solid_volume(positions, tri)
    if not volume > 0:
        raise ExportError(f"solid check failed (positive volume): signed volume {volume:.6g} <= 0 (inward orientation)")


# ------------------------------------------------------------------------------------------
# Writers
# ------------------------------------------------------------------------------------------
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
        texture = _as_uint8(mesh.material.texture_maps["albedo"].as_tensor().numpy())
    return positions, tri, normals, colours, uvs, texture


def write_mesh(mesh, path, *, overwrite: bool = False) -> list[Path]:
    """Write a mesh; the format follows the suffix. Returns the paths written.

    - ``.obj``: written here (not by Open3D, whose 0.19 drops OBJ textures): ``v``/``vt``/``vn``/``f``
      records, with ``<stem>.mtl`` (``map_Kd``) and the albedo texture ``<stem>_albedo.png``
      (8-bit sRGB) beside it when the mesh has texture coordinates and a texture.
    - ``.glb``: binary glTF with the texture embedded (Open3D / ASSIMP); vertex colours only when
      there is no texture (glTF would multiply them into it).
    - ``.ply``: binary PLY with vertex normals and 8-bit vertex colours (no texture).
    - ``.stl``: binary STL via :func:`write_stl` (the mesh must pass :func:`check_solid`).

    Raises
    ------
    ExportError
        Unknown suffix, empty mesh, or the writer failed.
    OutputExistsError
        One of the files exists and ``overwrite`` is False; nothing is written.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ExportError(f"cannot write {path.name!r}: unknown mesh format {path.suffix!r}; use one of {', '.join(MESH_SUFFIXES)}")
    if suffix == ".stl":
        return write_stl(mesh, path, overwrite=overwrite)
    positions, tri, normals, colours, uvs, texture = mesh_arrays(mesh)
    if len(tri) == 0:
        raise ExportError("the mesh has no triangles; nothing to write")
    if suffix == ".obj":
        textured = uvs is not None and texture is not None
        paths = [path.with_suffix(".mtl"), path.with_name(path.stem + "_albedo.png"), path] if textured else [path]
        with atomic_files(paths, overwrite) as tmp:
            if textured:
                write_png(tmp[1], _as_uint8(texture))
                tmp[0].write_text(_mtl_text(paths[1].name))
                _write_obj(tmp[2], positions, tri, normals, uvs, paths[0].name)
            else:
                _write_obj(tmp[0], positions, tri, normals, None, None)
        return paths
    t_mesh = mesh if isinstance(mesh, o3d.t.geometry.TriangleMesh) else o3d.t.geometry.TriangleMesh.from_legacy(mesh)
    if suffix == ".ply":  # PLY carries no material nor UVs: write the vertex attributes only
        t_mesh = _vertex_attributes_only(t_mesh)
    # glTF multiplies COLOR_0 into the base colour texture: with a texture, leave the
    # (identical) vertex colours out, or viewers would show the albedo squared.
    textured = uvs is not None and texture is not None
    with atomic_files([path], overwrite) as tmp:
        if not o3d.t.io.write_triangle_mesh(str(tmp[0]), t_mesh, write_vertex_colors=not (suffix == ".glb" and textured)):
            raise ExportError(f"Open3D could not write {path}")
    return [path]


def write_stl(mesh, path, *, overwrite: bool = False, check: bool = True) -> list[Path]:
    """Write a binary STL (little-endian, float32, facet normals; units are the mesh's, mm for a print solid).

    Parameters
    ----------
    mesh : o3d.t.geometry.TriangleMesh or o3d.geometry.TriangleMesh
    path : str or Path, ``.stl``
    overwrite : bool
        Replace an existing file.
    check : bool
        Run :func:`check_solid` first (STL is for printing: a mesh that is not a closed solid
        is refused with the failed check).

    Returns
    -------
    list of Path
        ``[path]``.
    """
    path = Path(path)
    if path.suffix.lower() != ".stl":
        raise ExportError(f"write_stl writes .stl files, got {path.name!r}")
    positions, tri = mesh_arrays(mesh)[:2]
    if len(tri) == 0:
        raise ExportError("the mesh has no triangles; nothing to write")
    if check:
        check_solid(positions, tri)
    p = positions.astype(np.float64)
    cross = _triangle_cross(p, tri)
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    record = np.dtype([("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])
    data = np.zeros(len(tri), dtype=record)
    data["normal"] = np.divide(cross, length, out=np.zeros_like(cross), where=length > 0)
    data["vertices"] = p[tri]
    header = b"o3d_mvps print solid, binary STL, millimetres".ljust(80, b" ")
    with atomic_files([path], overwrite) as tmp:
        with open(tmp[0], "wb") as fh:
            fh.write(header)
            fh.write(np.uint32(len(tri)).astype("<u4").tobytes())
            fh.write(data.tobytes())
    return [path]


def _vertex_attributes_only(mesh: o3d.t.geometry.TriangleMesh) -> o3d.t.geometry.TriangleMesh:
    """A mesh with the same positions, normals, colours and triangles, and nothing else."""
    plain = o3d.t.geometry.TriangleMesh()
    for name in ("positions", "normals", "colors"):
        if name in mesh.vertex:
            plain.vertex[name] = mesh.vertex[name]
    plain.triangle.indices = mesh.triangle.indices
    return plain


def _as_uint8(image: np.ndarray) -> np.ndarray:
    """An (H, W, C) uint8 image from uint8, uint16 or float [0, 1] data."""
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None]
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        return (image // 257).astype(np.uint8)
    return np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)


def _mtl_text(texture_name: str) -> str:
    return (
        "# o3d_mvps material: albedo texture (sRGB)\n"
        "newmtl albedo\n"
        "Ka 1.000000 1.000000 1.000000\n"
        "Kd 1.000000 1.000000 1.000000\n"
        "Ks 0.000000 0.000000 0.000000\n"
        "d 1.0\n"
        "illum 1\n"
        f"map_Kd {texture_name}\n"
    )


# OBJ text is formatted with vectorised numpy (a character table per block of rows): a
# formatted Python string per record takes ~10 s for a 1280x720 mesh, this well under 2 s.
_ROWS_PER_BLOCK = 1 << 17


def _write_obj(path: Path, positions: np.ndarray, tri: np.ndarray, normals: np.ndarray | None,
               uvs: np.ndarray | None, mtl_name: str | None) -> None:
    """Write a Wavefront OBJ: v (n), vt (deduplicated corner UVs), vn (n), f v/vt/vn (1-based)."""
    n = len(positions)
    corner_uv = None
    if uvs is not None:
        uv_table, corner_uv = _deduplicate_uvs(tri, uvs)
    scale = float(np.abs(positions).max(initial=1.0))
    decimals = int(np.clip(15 - np.ceil(np.log10(max(scale, 1.0))), 3, 9))
    with open(path, "wb") as fh:
        fh.write(f"# o3d_mvps mesh: {n} vertices, {len(tri)} triangles\n".encode())
        if mtl_name is not None:
            fh.write(f"mtllib {mtl_name}\nusemtl albedo\n".encode())
        _write_records(fh, b"v", [positions[:, k] for k in range(3)], decimals)
        if corner_uv is not None:
            _write_records(fh, b"vt", [uv_table[:, 0], uv_table[:, 1]], 7)
        if normals is not None:
            _write_records(fh, b"vn", [normals[:, k] for k in range(3)], 6)
        # Every index is formatted once, into a table gathered per face corner.
        n_ids = max(n, len(uv_table) if corner_uv is not None else 0)
        id_chars, id_used = _int_chars(np.arange(1, n_ids + 1))
        for start in range(0, len(tri), _ROWS_PER_BLOCK):
            block = tri[start:start + _ROWS_PER_BLOCK]
            block_uv = None if corner_uv is None else corner_uv[start:start + _ROWS_PER_BLOCK]
            pieces = [b"f"]
            for k in range(3):
                vertex = (id_chars[block[:, k]], id_used[block[:, k]])
                pieces += [b" ", vertex]
                if block_uv is not None:
                    pieces += [b"/", (id_chars[block_uv[:, k]], id_used[block_uv[:, k]])]
                if normals is not None:
                    pieces += [b"/" if block_uv is not None else b"//", vertex]
            pieces.append(b"\n")
            fh.write(_join_rows(pieces, len(block)))


def _deduplicate_uvs(tri: np.ndarray, uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique UVs (m, 2) and each corner's index (T, 3) into them.

    Fast path: when the corner UVs are a function of the vertex (meshes of
    :func:`refinement_to_mesh`), the table is per vertex and indices equal vertex indices.
    """
    uvs = np.asarray(uvs, dtype=np.float32).reshape(len(tri), 3, 2)
    per_vertex = np.zeros((int(tri.max()) + 1, 2), dtype=np.float32)
    per_vertex[tri] = uvs
    if np.array_equal(per_vertex[tri], uvs):
        return per_vertex, tri
    bits = np.ascontiguousarray(uvs.reshape(-1, 2)).view(np.uint32).astype(np.uint64)
    table_keys, inverse, _ = _unique((bits[:, 0] << np.uint64(32)) | bits[:, 1])
    table = np.stack([(table_keys >> np.uint64(32)).astype(np.uint32), (table_keys & np.uint64(0xFFFFFFFF)).astype(np.uint32)], axis=1)
    return table.view(np.float32).reshape(-1, 2), inverse.reshape(len(tri), 3)


def _write_records(fh, tag: bytes, columns: list[np.ndarray], decimals: int) -> None:
    """Write lines ``tag x y ...`` of fixed-point numbers, block by block."""
    n = len(columns[0])
    for start in range(0, n, _ROWS_PER_BLOCK):
        sl = slice(start, start + _ROWS_PER_BLOCK)
        pieces = [tag]
        for col in columns:
            pieces += [b" ", _fixed_chars(np.asarray(col[sl], dtype=np.float64), decimals)]
        pieces.append(b"\n")
        fh.write(_join_rows(pieces, len(columns[0][sl])))


def _int_chars(x: np.ndarray, width: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """ASCII digits of non-negative integers (N,) below 1e15: right-aligned (N, width) uint8 and a used-column mask."""
    x = np.asarray(x, dtype=np.float64)  # float division is exact here and much faster than int64's
    if width is None:
        width = len(str(int(x.max(initial=0))))
    powers = 10.0 ** np.arange(width - 1, -1, -1)
    digits = np.floor(x[:, None] / powers) % 10.0 + ord("0")
    n_digits = np.maximum((x[:, None] >= powers).sum(axis=1), 1)
    used = np.arange(width) >= (width - n_digits)[:, None]
    return digits.astype(np.uint8), used


def _fixed_chars(x: np.ndarray, decimals: int) -> tuple[np.ndarray, np.ndarray]:
    """ASCII fixed-point text ``[-]int.frac`` of floats (N,): (N, w) uint8 and a used-column mask."""
    unit = 10.0 ** decimals
    scaled = np.rint(np.abs(x) * unit)  # an exact integer in float64 (below 2**53)
    whole = np.floor(scaled / unit)
    frac = scaled - whole * unit
    w_chars, w_used = _int_chars(whole)
    f_chars, _ = _int_chars(frac, decimals)
    negative = (x < 0) & (scaled > 0)
    sign = np.where(negative, ord("-"), ord(" ")).astype(np.uint8)[:, None]
    dot = np.full((len(x), 1), ord("."), dtype=np.uint8)
    chars = np.concatenate([sign, w_chars, dot, f_chars], axis=1)
    used = np.concatenate([negative[:, None], w_used, np.ones((len(x), 1 + decimals), dtype=bool)], axis=1)
    return chars, used


def _join_rows(pieces: list, n: int) -> bytes:
    """Concatenate per-row pieces -- constant ``bytes`` or (chars, used) tables -- into n text rows."""
    chars, used = [], []
    for piece in pieces:
        if isinstance(piece, bytes):
            constant = np.frombuffer(piece, dtype=np.uint8)
            chars.append(np.broadcast_to(constant, (n, constant.size)))
            used.append(np.ones((n, constant.size), dtype=bool))
        else:
            chars.append(piece[0])
            used.append(piece[1])
    return np.concatenate(chars, axis=1)[np.concatenate(used, axis=1)].tobytes()
