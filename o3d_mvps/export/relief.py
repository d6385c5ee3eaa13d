"""The textured relief mesh of a refinement: the depth map triangulated on the pixel grid."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from ..colour import linear_to_srgb
from ..errors import ExportError
from ..model.camera import as_intrinsic_matrix, backproject, project
from ..model.warping import sample_bilinear
from .topology import mesh_arrays, unique, vertex_normals

#: Default discontinuity threshold of :func:`refinement_to_mesh`, in pixel footprints: an edge
#: between neighbouring pixels is cut when its depth step exceeds 10 footprints, i.e. where the
#: surface is steeper than atan(10) = 84 degrees to the image plane.
DEFAULT_MAX_DEPTH_JUMP = 10.0


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

    Cutting a quad at a depth jump (or dropping a bow-tie's triangles) leaves a crack, up to one
    pixel wide, through which the reference camera would see the background. With ``skirts``
    the far surface is extended under the near edge to close it: the missing triangles of a cut
    quad are added with their near corners moved back along their camera rays to the quad's far
    depth (extra vertices), and dropped bow-tie triangles are put back.
    Seen from the reference camera the mesh then covers every quad of the mask, and still no
    triangle joins the near and the far surface. A skirt can touch the relief at a single
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
    keep = drop_bowties(tri, height * width)
    tri, missing = tri[keep], np.concatenate([missing, tri[~keep]])  # skirts also fill bow-tie gaps
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
    ids, tri = compact_vertices(tri)
    v, u = np.divmod(ids % (height * width), width)
    positions = backproject(vertex_depth[ids], K, u.astype(np.float64), v.astype(np.float64))

    albedo = refinement.albedo_array()
    srgb = None if albedo is None else linear_to_srgb(albedo)

    if max_triangles is not None and len(tri) > max_triangles:
        positions, tri = _decimate(positions, tri, int(max_triangles))
        normals = vertex_normals(positions, tri)
        u, v, _ = project(positions, K)  # continuous pixel coordinates
        colours = None if srgb is None else sample_bilinear(srgb.astype(np.float64), u, v)
    else:
        normals = refinement.normals_array()[v, u].astype(np.float64)
        length = np.linalg.norm(normals, axis=1)
        bad = ~(length > 0.5)
        if bad.any():  # zero normals (should not happen inside the mask): use the triangles'
            normals[bad] = vertex_normals(positions, tri)[bad]
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


def drop_bowties(tri: np.ndarray, n_vertices: int) -> np.ndarray:
    """Which triangles (T,) bool to keep so that no vertex joins separate triangle fans.

    For a triangulation embedded in the image plane, the link of vertex p (the edges opposite
    p) has L(p) vertices (distinct neighbours) and T(p) edges (incident triangles); it is one
    path or one cycle, i.e. p is manifold, exactly when ``L(p) - T(p) <= 1``. The triangles
    around other vertices are dropped, repeatedly until none is left (each pass only drops
    triangles, so it terminates).
    """
    keep = np.ones(len(tri), dtype=bool)
    while keep.any():
        kept = tri[keep]
        edges = np.sort(kept[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        keys = unique(edges[:, 0] * n_vertices + edges[:, 1])[0]
        link = np.bincount(keys // n_vertices, minlength=n_vertices) + np.bincount(keys % n_vertices, minlength=n_vertices)
        fans = link - np.bincount(kept.ravel(), minlength=n_vertices)
        bad = fans >= 2
        if not bad.any():
            break
        keep[np.flatnonzero(keep)[bad[kept].any(axis=1)]] = False
    return keep


def compact_vertices(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Used vertex ids (n,) in increasing order and the triangles (T, 3) re-indexed into them."""
    occupied = np.zeros(int(tri.max()) + 1, dtype=bool)
    occupied[tri] = True
    used = np.flatnonzero(occupied)
    new_index = np.cumsum(occupied) - 1
    return used, new_index[tri].astype(np.int64)


def simplify_mesh(mesh, max_triangles: int) -> o3d.t.geometry.TriangleMesh:
    """``mesh`` quadric-decimated to at most ``max_triangles`` triangles (unchanged below that).

    Geometry only is decimated: vertex colours are taken from the nearest original vertex,
    normals recomputed from the triangles; texture coordinates are dropped (vertex colours
    remain). For any mesh (e.g. a whole-object reconstruction); a refinement's relief has its
    own, exact texture re-projection (:func:`refinement_to_mesh`'s ``max_triangles``).
    """
    positions, tri, _, colours, _, _ = mesh_arrays(mesh)
    if int(max_triangles) < 1:
        raise ExportError(f"max_triangles must be a positive integer, got {max_triangles}")
    if len(tri) <= max_triangles:
        return mesh if isinstance(mesh, o3d.t.geometry.TriangleMesh) else o3d.t.geometry.TriangleMesh.from_legacy(mesh)
    new_positions, tri = _decimate(positions.astype(np.float64), tri, int(max_triangles))
    out = o3d.t.geometry.TriangleMesh()
    out.vertex.positions = o3d.core.Tensor(new_positions.astype(np.float32))
    out.vertex.normals = o3d.core.Tensor(vertex_normals(new_positions, tri).astype(np.float32))
    out.triangle.indices = o3d.core.Tensor(tri)
    if colours is not None:
        from scipy.spatial import cKDTree

        _, nearest = cKDTree(positions).query(new_positions)
        out.vertex.colors = o3d.core.Tensor(np.ascontiguousarray(colours[nearest], dtype=np.float32))
    return out


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
