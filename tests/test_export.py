"""Textured mesh, print-ready solid, writers, preview and the export subcommand (o3d_mvps.export)."""

from __future__ import annotations

import json
import struct

import numpy as np
import open3d as o3d
import pytest
import trimesh

import o3d_mvps.export as export
import o3d_mvps.refinement as refinement_module
from o3d_mvps.cli import main
from o3d_mvps.colour import linear_to_srgb
from o3d_mvps.errors import ExportError, OutputExistsError
from o3d_mvps.export import (
    check_solid,
    printable_solid,
    refinement_to_mesh,
    write_mesh,
    write_stl,
)
from o3d_mvps.model.camera import backproject
from o3d_mvps.refinement import Refinement


# ---------------------------------------------------------------------------- fixtures
def intrinsics(width: int, height: int) -> np.ndarray:
    f = 100.0 * width / 120.0
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def bump_depth(width: int, height: int) -> np.ndarray:
    """A smooth Gaussian bump (3 cm high, sigma 5 cm) on a fronto-parallel plane at 0.6 m."""
    K = intrinsics(width, height)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x, y = (u - K[0, 2]) / K[0, 0] * 0.6, (v - K[1, 2]) / K[1, 1] * 0.6
    return 0.6 - 0.03 * np.exp(-(x**2 + y**2) / (2 * 0.05**2))


def albedo_pattern(width: int, height: int) -> np.ndarray:
    """Linear RGB: red in the top half, blue in the bottom half, green stripes on the left."""
    v, u = np.mgrid[0:height, 0:width]
    albedo = np.full((height, width, 3), 0.05)
    albedo[: height // 2, :, 0] = 0.8
    albedo[height // 2:, :, 2] = 0.8
    albedo[:, : width // 2, 1] = np.where(u[:, : width // 2] % 8 < 4, 0.6, 0.1)
    albedo[..., 0] += 0.1 * v / height  # a gradient, so no two rows are alike
    return albedo


def hole_mask(width: int, height: int) -> np.ndarray:
    """A rectangle with a rectangular hole."""
    mask = np.zeros((height, width), dtype=bool)
    mask[height // 9: -height // 9, width // 12: -width // 12] = True
    mask[height // 3: 2 * height // 3, 3 * width // 8: 5 * width // 8] = False
    return mask


def two_piece_mask(width: int, height: int) -> np.ndarray:
    """A large and a small rectangle, apart."""
    mask = np.zeros((height, width), dtype=bool)
    mask[height // 6: -height // 6, width // 12: width // 2] = True
    mask[height // 3: 2 * height // 3, 2 * width // 3: -width // 12] = True
    return mask


def make_refinement(mask: np.ndarray, depth: np.ndarray | None = None, albedo: bool = True) -> Refinement:
    height, width = mask.shape
    depth = bump_depth(width, height) if depth is None else depth
    return Refinement.from_arrays(depth, mask, intrinsics(width, height),
                                  albedo=albedo_pattern(width, height) if albedo else None)


@pytest.fixture(scope="module")
def holed():
    """(refinement, mesh) on 120 x 90 pixels, mask with a hole."""
    refinement = make_refinement(hole_mask(120, 90))
    return refinement, refinement_to_mesh(refinement)


def pixel_of(points: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest pixel (u, v) of camera-frame points (n, 3)."""
    u = np.rint(K[0, 0] * points[:, 0] / points[:, 2] + K[0, 2]).astype(int)
    v = np.rint(K[1, 1] * points[:, 1] / points[:, 2] + K[1, 2]).astype(int)
    return u, v


def expected_triangles(mask: np.ndarray) -> int:
    """Triangles of a depth map without discontinuities: 2 per 4-corner quad, 1 per 3-corner quad."""
    corners = mask[:-1, :-1].astype(int) + mask[:-1, 1:] + mask[1:, :-1] + mask[1:, 1:]
    return int(2 * (corners == 4).sum() + (corners == 3).sum())


def geometry_error(points: np.ndarray, refinement: Refinement) -> float:
    """Largest distance (m) between points and the back-projection of their pixels' depth."""
    K = refinement.intrinsic_matrix()
    u, v = pixel_of(points, K)
    truth = backproject(refinement.depth_array().astype(np.float64)[v, u], K, u.astype(float), v.astype(float))
    return float(np.abs(points - truth).max())


def separated(t1: np.ndarray, t2: np.ndarray, gap: float = 1e-9) -> bool:
    """Separating-axis test: True when two triangles (3, 3) are disjoint by more than ``gap``.

    Axes: both normals, the 9 edge-edge cross products and the 6 in-plane edge normals (these
    separate coplanar triangles).
    """
    e1, e2 = np.roll(t1, -1, axis=0) - t1, np.roll(t2, -1, axis=0) - t2
    n1, n2 = np.cross(e1[0], e1[1]), np.cross(e2[0], e2[1])
    axes = [n1, n2, *np.cross(e1[:, None], e2[None]).reshape(-1, 3), *np.cross(n1, e1), *np.cross(n2, e2)]
    for axis in axes:
        length = np.linalg.norm(axis)
        if length < 1e-12:
            continue
        a, b = t1 @ (axis / length), t2 @ (axis / length)
        if a.max() + gap < b.min() or b.max() + gap < a.min():
            return True
    return False


def as_trimesh(path) -> trimesh.Trimesh:
    loaded = trimesh.load(str(path), process=False)
    if isinstance(loaded, trimesh.Scene):
        (loaded,) = loaded.geometry.values()
    return loaded


# ---------------------------------------------------------------------------- textured mesh
def test_mesh_vertices_triangles_and_attributes(holed):
    refinement, mesh = holed
    mask, K = refinement.mask_array(), refinement.intrinsic_matrix()
    positions = mesh.vertex.positions.numpy()
    tri = mesh.triangle.indices.numpy()
    assert positions.shape == (mask.sum(), 3) and positions.dtype == np.float32
    assert len(tri) == expected_triangles(mask)
    assert geometry_error(positions.astype(np.float64), refinement) < 1e-6

    # Triangles and vertex normals face the camera (at the origin).
    p = positions.astype(np.float64)
    cross = np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]])
    assert np.all(np.einsum("ij,ij->i", cross, p[tri].mean(axis=1)) < 0)
    normals = mesh.vertex.normals.numpy()
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    assert np.all(np.einsum("ij,ij->i", normals, p) < 0)

    # Colours are the sRGB-encoded albedo at each vertex's pixel; UVs address the same pixel.
    u, v = pixel_of(p, K)
    srgb = linear_to_srgb(refinement.albedo_array())
    np.testing.assert_allclose(mesh.vertex.colors.numpy(), srgb[v, u], atol=1e-6)
    uvs = mesh.triangle.texture_uvs.numpy()
    assert uvs.shape == (len(tri), 3, 2) and uvs.dtype == np.float32
    np.testing.assert_allclose(uvs[:, :, 0], (u[tri] + 0.5) / 120, atol=1e-6)
    np.testing.assert_allclose(uvs[:, :, 1], 1 - (v[tri] + 0.5) / 90, atol=1e-6)
    texture = mesh.material.texture_maps["albedo"].as_tensor().numpy()
    assert texture.shape == (90, 120, 3) and texture.dtype == np.uint8
    np.testing.assert_array_equal(texture, np.round(srgb * 255).astype(np.uint8))

    legacy = mesh.to_legacy()
    assert legacy.is_edge_manifold() and legacy.is_vertex_manifold() and legacy.is_orientable()


def test_no_triangle_spans_a_depth_step():
    height, width = 45, 60
    depth = np.full((height, width), 0.6)
    depth[:, 30:] = 0.8                       # a 20 cm step: ~17 pixel footprints (f = 50 px: 12 mm at 0.6 m)
    depth[:, 40:] += 0.004 * np.arange(20)    # then a slope of ~0.3 footprint per pixel, kept
    refinement = make_refinement(np.ones((height, width), dtype=bool), depth)
    K = refinement.intrinsic_matrix()

    def sides(mesh):  # which corners lie on the far side of the step
        return mesh.vertex.positions.numpy()[mesh.triangle.indices.numpy(), 2] > 0.7

    right = sides(refinement_to_mesh(refinement))
    assert not np.any(right.any(axis=1) & ~right.all(axis=1))  # no triangle with corners on both sides
    assert len(refinement_to_mesh(refinement, skirts=False).triangle.indices) == 2 * (height - 1) * (width - 2)
    # the skirt closes the cut column of quads at the far depth: 2 triangles per quad, none at 0.6 m
    skirted = refinement_to_mesh(refinement)
    assert len(skirted.triangle.indices) == 2 * (height - 1) * (width - 1)
    new_rows = skirted.triangle.indices.numpy()[2 * (height - 1) * (width - 2):]
    assert skirted.vertex.positions.numpy()[new_rows, 2].min() > 0.79
    # Absolute check of the documented rule: every kept edge's step is within 10 footprints.
    mesh = refinement_to_mesh(refinement, max_depth_jump=10.0)
    p, tri = mesh.vertex.positions.numpy().astype(np.float64), mesh.triangle.indices.numpy()
    for i, j in ((0, 1), (1, 2), (2, 0)):
        u, v = pixel_of(p[tri[:, i]], K)
        u2, v2 = pixel_of(p[tri[:, j]], K)
        footprint = np.minimum(p[tri[:, i], 2], p[tri[:, j], 2]) * np.hypot((u - u2) / K[0, 0], (v - v2) / K[1, 1])
        assert np.all(np.abs(p[tri[:, i], 2] - p[tri[:, j], 2]) <= 10.0 * footprint + 1e-9)
    spanning = sides(refinement_to_mesh(refinement, max_depth_jump=None))
    assert np.any(spanning.any(axis=1) & ~spanning.all(axis=1))  # None keeps every edge


def test_bow_tie_pixels_give_a_vertex_manifold_mesh():
    mask = np.zeros((20, 20), dtype=bool)
    mask[2:8, 2:8] = True
    mask[8:14, 8:14] = True   # touches the first square at one corner pixel only
    mask[14:18, 2:6] = True
    mask[13, 6] = True        # a diagonal neighbour creating a lone 3-corner triangle
    mesh = refinement_to_mesh(make_refinement(mask, np.full((20, 20), 0.6)), skirts=False)
    legacy = mesh.to_legacy()
    assert legacy.is_edge_manifold() and legacy.is_vertex_manifold()


def test_decimation_keeps_texture_coordinates_consistent(holed):
    refinement, _ = holed
    mesh = refinement_to_mesh(refinement, max_triangles=1500)
    tri = mesh.triangle.indices.numpy()
    assert 0 < len(tri) <= 1500
    p = mesh.vertex.positions.numpy().astype(np.float64)
    K = refinement.intrinsic_matrix()
    uvs = mesh.triangle.texture_uvs.numpy()
    assert uvs.shape == (len(tri), 3, 2)
    u = K[0, 0] * p[:, 0] / p[:, 2] + K[0, 2]
    np.testing.assert_allclose(uvs[:, :, 0], (u[tri] + 0.5) / 120, atol=1e-5)  # projection-based UVs
    assert mesh.vertex.colors.numpy().shape == p.shape
    assert np.all(np.einsum("ij,ij->i", mesh.vertex.normals.numpy(), p) < 0)


def test_refinement_without_albedo_gives_an_untextured_mesh(tmp_path):
    mesh = refinement_to_mesh(make_refinement(hole_mask(40, 30), albedo=False))
    assert "colors" not in mesh.vertex and "texture_uvs" not in mesh.triangle
    assert [p.name for p in write_mesh(mesh, tmp_path / "plain.obj")] == ["plain.obj"]
    assert len(o3d.t.io.read_triangle_mesh(str(tmp_path / "plain.obj")).triangle.indices) == len(mesh.triangle.indices)


# ---------------------------------------------------------------------------- writers
@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_textured_files_read_back_with_texture(holed, tmp_path, suffix):
    refinement, mesh = holed
    n_tri = len(mesh.triangle.indices)
    written = write_mesh(mesh, tmp_path / f"scan{suffix}")
    if suffix == ".obj":
        assert sorted(p.name for p in written) == ["scan.mtl", "scan.obj", "scan_albedo.png"]
        assert "map_Kd scan_albedo.png" in (tmp_path / "scan.mtl").read_text()

    back = o3d.t.io.read_triangle_mesh(str(tmp_path / f"scan{suffix}"))
    assert back.triangle.texture_uvs.shape == (n_tri, 3, 2)                      # 3 UVs per triangle
    assert back.material.texture_maps["albedo"].as_tensor().numpy().shape[:2] == (90, 120)
    assert len(back.vertex.positions) == refinement.mask_array().sum()
    assert geometry_error(back.vertex.positions.numpy().astype(np.float64), refinement) < 1e-6

    if suffix == ".glb":  # COLOR_0 would be multiplied into the texture by glTF viewers
        data = (tmp_path / "scan.glb").read_bytes()
        header = json.loads(data[20:20 + struct.unpack("<I", data[12:16])[0]])
        (primitive,) = header["meshes"][0]["primitives"]
        assert "TEXCOORD_0" in primitive["attributes"] and "COLOR_0" not in primitive["attributes"]
        assert "baseColorTexture" in header["materials"][0]["pbrMetallicRoughness"]

    # Independent reader: sampling the texture at each vertex's UV gives that pixel's albedo,
    # which pins the UV convention (origin, v flip) end to end.
    tm = as_trimesh(tmp_path / f"scan{suffix}")
    assert len(tm.faces) == n_tri and tm.visual.uv.shape == (len(tm.vertices), 2)
    u, v = pixel_of(np.asarray(tm.vertices), refinement.intrinsic_matrix())
    expected = np.round(linear_to_srgb(refinement.albedo_array()) * 255)[v, u]
    assert np.abs(tm.visual.to_color().vertex_colors[:, :3] - expected).max() <= 1


def test_ply_has_vertex_colours(holed, tmp_path):
    refinement, mesh = holed
    write_mesh(mesh, tmp_path / "scan.ply")
    tm = as_trimesh(tmp_path / "scan.ply")
    assert len(tm.faces) == len(mesh.triangle.indices)
    u, v = pixel_of(np.asarray(tm.vertices), refinement.intrinsic_matrix())
    expected = linear_to_srgb(refinement.albedo_array())[v, u] * 255
    assert np.abs(tm.visual.vertex_colors[:, :3] - expected).max() <= 1


def test_writers_refuse_to_overwrite_and_leave_files_intact(holed, tmp_path):
    _, mesh = holed
    first = write_mesh(mesh, tmp_path / "scan.obj")
    before = {p: p.read_bytes() for p in first}
    small = refinement_to_mesh(make_refinement(hole_mask(40, 30)))
    with pytest.raises(OutputExistsError, match="overwrite"):
        write_mesh(small, tmp_path / "scan.obj")
    assert {p: p.read_bytes() for p in first} == before
    (tmp_path / "scan.mtl").unlink()  # any one existing companion file blocks the write too
    with pytest.raises(OutputExistsError):
        write_mesh(small, tmp_path / "scan.obj")
    assert (tmp_path / "scan.obj").read_bytes() == before[tmp_path / "scan.obj"]
    write_mesh(small, tmp_path / "scan.obj", overwrite=True)
    assert (tmp_path / "scan.obj").read_bytes() != before[tmp_path / "scan.obj"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scan.mtl", "scan.obj", "scan_albedo.png"]


def test_failed_write_leaves_no_output(holed, tmp_path, monkeypatch):
    _, mesh = holed

    def broken(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(export.writers, "write_obj", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        write_mesh(mesh, tmp_path / "scan.obj")
    assert list(tmp_path.iterdir()) == []  # neither the texture, the .mtl nor temporary files


def test_wrong_extension_and_empty_mask_are_errors(holed, tmp_path):
    _, mesh = holed
    with pytest.raises(ExportError, match=r"\.fbx"):
        write_mesh(mesh, tmp_path / "scan.fbx")
    with pytest.raises(ExportError, match="empty"):
        refinement_to_mesh(make_refinement(np.zeros((30, 40), dtype=bool)))
    with pytest.raises(ExportError, match="pieces"):
        printable_solid(mesh, pieces="biggest")
    with pytest.raises(ExportError, match="watertight"):
        write_stl(mesh, tmp_path / "relief.stl")  # an open relief is not a printable solid
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------- print solid
@pytest.fixture(scope="module")
def solids():
    """Small solids (48 x 36 pixels) so that Open3D's quadratic self-intersection test stays fast."""
    hole = make_refinement(hole_mask(48, 36))
    pieces = make_refinement(two_piece_mask(48, 36))
    return {
        "hole": printable_solid(hole, size_mm=100.0, base_mm=3.0),
        "all": printable_solid(pieces, size_mm=80.0, base_mm=4.0, pieces="all"),
        "largest": printable_solid(pieces, size_mm=80.0, base_mm=4.0, pieces="largest"),
    }


@pytest.mark.parametrize("name, size_mm, base_mm, n_bodies, euler",
                         [("hole", 100.0, 3.0, 1, 0), ("all", 80.0, 4.0, 2, 4), ("largest", 80.0, 4.0, 1, 2)])
def test_print_solid_is_a_closed_volume_of_the_requested_size(solids, name, size_mm, base_mm, n_bodies, euler):
    solid = solids[name]
    legacy = solid.to_legacy()
    # Open3D's is_watertight() = closed edge-manifold + vertex-manifold + not self-intersecting.
    assert legacy.is_edge_manifold(allow_boundary_edges=False) and legacy.is_vertex_manifold()
    assert legacy.is_orientable()
    # Its self-intersection test (Guigue-Devillers in floating point) gives false positives on
    # nearly coplanar triangles, such as neighbouring wall strips along a straight outline:
    # every pair it flags must be one that a separating-axis test proves disjoint.
    p = solid.vertex.positions.numpy().astype(np.float64)
    tri = solid.triangle.indices.numpy()
    flagged = np.asarray(legacy.get_self_intersecting_triangles())
    assert all(separated(p[tri[i]], p[tri[j]]) for i, j in flagged)
    assert len(flagged) > 0 or legacy.is_watertight()

    tm = trimesh.Trimesh(p, tri, process=False)
    assert tm.is_watertight and tm.is_winding_consistent and tm.is_volume and tm.volume > 0
    assert tm.euler_number == euler  # a hole makes a torus (0); two bodies are two spheres (4)
    assert len(tm.split(only_watertight=False)) == n_bodies

    extent = p.max(axis=0) - p.min(axis=0)
    assert abs(extent.max() - size_mm) <= 1e-6 * size_mm
    np.testing.assert_allclose(p.min(axis=0), 0.0, atol=1e-9)
    relief = p[:, 2] > 1e-9
    assert abs(p[relief, 2].min() - base_mm) < 1e-4        # plate thickness behind the deepest point
    assert np.count_nonzero(~relief) == np.count_nonzero(relief)  # every relief vertex has its plate twin


def test_print_solid_keeps_the_hole_and_the_largest_piece(solids):
    tm_all = trimesh.Trimesh(solids["all"].vertex.positions.numpy(), solids["all"].triangle.indices.numpy())
    tm_largest = trimesh.Trimesh(solids["largest"].vertex.positions.numpy(), solids["largest"].triangle.indices.numpy())
    bodies = sorted(tm_all.split(only_watertight=False), key=lambda body: body.volume)
    assert bodies[1].volume > 2 * bodies[0].volume
    assert len(tm_largest.faces) == len(bodies[1].faces)  # "largest" keeps just the larger piece
    # The hole goes through the plate: a ray down through the hole's centre misses the solid.
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(solids["hole"])
    lo, hi = solids["hole"].vertex.positions.numpy().min(axis=0), solids["hole"].vertex.positions.numpy().max(axis=0)
    centre = (lo + hi) / 2
    down = o3d.core.Tensor([[centre[0], centre[1], 50.0, 0.0, 0.0, -1.0]], dtype=o3d.core.float32)
    beside = o3d.core.Tensor([[lo[0] + 1.0, lo[1] + 1.0, 50.0, 0.0, 0.0, -1.0]], dtype=o3d.core.float32)
    assert scene.count_intersections(down).numpy()[0] == 0
    assert scene.count_intersections(beside).numpy()[0] == 2  # relief, then plate


def test_stl_round_trip(solids, tmp_path):
    solid = solids["hole"]
    write_stl(solid, tmp_path / "print.stl")
    data = (tmp_path / "print.stl").read_bytes()
    assert len(data) == 84 + 50 * len(solid.triangle.indices)
    tm = trimesh.load(str(tmp_path / "print.stl"))  # merges the STL's per-facet vertices
    assert tm.is_watertight and tm.is_volume
    assert abs(tm.extents.max() - 100.0) < 1e-4
    with pytest.raises(OutputExistsError):
        write_mesh(solid, tmp_path / "print.stl")
    assert (tmp_path / "print.stl").read_bytes() == data


def test_check_solid_names_the_failed_check(solids):
    solid = solids["hole"]
    p, tri = solid.vertex.positions.numpy(), solid.triangle.indices.numpy()
    check_solid(p, tri)
    with pytest.raises(ExportError, match="watertight"):
        check_solid(p, tri[1:])
    with pytest.raises(ExportError, match="positive volume"):
        check_solid(p, tri[:, ::-1])
    with pytest.raises(ExportError, match="orient"):
        check_solid(p, np.concatenate([tri[:1, ::-1], tri[1:]]))
    with pytest.raises(ExportError, match="edge-manifold"):
        check_solid(p, np.concatenate([tri, tri[:1]]))


def test_print_solid_from_a_mesh_matches_the_one_from_the_refinement():
    refinement = make_refinement(hole_mask(48, 36))
    a = printable_solid(refinement)
    b = printable_solid(refinement_to_mesh(refinement))
    np.testing.assert_allclose(a.vertex.positions.numpy(), b.vertex.positions.numpy(), atol=1e-4)
    with pytest.raises(ExportError, match="size_mm"):
        printable_solid(refinement, size_mm=2.0, base_mm=4.0)


# ---------------------------------------------------------------------------- preview and CLI
def test_preview_png_shows_the_texture(holed, tmp_path):
    import cv2

    from o3d_mvps.viz import render_preview

    _, mesh = holed
    path = render_preview(mesh, tmp_path / "preview.png", size=(160, 120))
    assert path.stat().st_size > 0
    image = cv2.imread(str(path))[..., ::-1].astype(float)
    assert image.shape == (120, 160, 3) and image.var() > 0
    top, bottom = image[20:50, 30:130], image[70:100, 30:130]
    assert top[..., 0].mean() > top[..., 2].mean() + 30        # red half on top, as in the image
    assert bottom[..., 2].mean() > bottom[..., 0].mean() + 30  # blue half at the bottom
    with pytest.raises(OutputExistsError):
        render_preview(mesh, path)


def background_inside(image: np.ndarray) -> int:
    """Pixels of the white background enclosed by the rendered mesh (not connected to the border)."""
    from scipy import ndimage

    labels, _ = ndimage.label((image >= 250).all(axis=2))
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    return int(np.count_nonzero((labels > 0) & ~np.isin(labels, border)))


def test_preview_has_no_cracks_at_depth_jumps(tmp_path):
    """A square 10 cm in front of a plane: the cut quads around it must not show the background."""
    import cv2

    from o3d_mvps.viz import render_preview

    height, width = 45, 60
    depth = np.full((height, width), 0.6)
    depth[15:30, 20:40] = 0.5
    refinement = Refinement.from_arrays(depth, np.ones((height, width), bool), intrinsics(width, height),
                                        albedo=np.full((height, width, 3), 0.3))
    cracked = render_preview(refinement_to_mesh(refinement, skirts=False), tmp_path / "cracked.png", size=(240, 180))
    closed = render_preview(refinement_to_mesh(refinement), tmp_path / "closed.png", size=(240, 180))
    assert background_inside(cv2.imread(str(cracked))) > 100  # the crack loop around the square
    assert background_inside(cv2.imread(str(closed))) == 0


def test_preview_shading_uses_the_mesh_normals(tmp_path):
    """Smooth shading of a steep bump from its own normals: no facet pattern on the pixel grid.

    Roughness = mean |second difference| of the grey picture along u plus along v. Measured:
    0.65 with the mesh normals, 1.63 with VTK's per-triangle normals (the staircase pattern of
    the demo preview); bound 1.0.
    """
    import cv2

    from o3d_mvps.viz import render_preview

    K = intrinsics(40, 30)
    v, u = np.mgrid[0:30, 0:40].astype(float)
    x, y = (u - K[0, 2]) / K[0, 0] * 0.6, (v - K[1, 2]) / K[1, 1] * 0.6
    depth = 0.6 - 0.1 * np.exp(-(x**2 + y**2) / (2 * 0.06**2))
    refinement = Refinement.from_arrays(depth, np.ones((30, 40), bool), K, albedo=np.full((30, 40, 3), 0.5))
    path = render_preview(refinement_to_mesh(refinement), tmp_path / "bump.png", size=(320, 240))
    grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).astype(float)[40:200, 60:260]
    roughness = (np.abs(grey[:, 2:] - 2 * grey[:, 1:-1] + grey[:, :-2]).mean()
                 + np.abs(grey[2:] - 2 * grey[1:-1] + grey[:-2]).mean())
    assert roughness < 1.0, roughness


def test_cli_export(tmp_path, monkeypatch, capsys):
    refinement = make_refinement(hole_mask(48, 36))
    folder = tmp_path / "refined"
    folder.mkdir()
    monkeypatch.setattr(refinement_module, "read_refinement", lambda path: refinement, raising=False)

    assert main(["export", str(folder), str(tmp_path / "scan.glb")]) == 0
    assert "wrote" in capsys.readouterr().out
    assert len(o3d.t.io.read_triangle_mesh(str(tmp_path / "scan.glb")).triangle.indices) > 0

    assert main(["export", str(folder), str(tmp_path / "print.stl"), "--print", "50", "--base-mm", "2"]) == 0
    tm = trimesh.load(str(tmp_path / "print.stl"))
    assert tm.is_volume and abs(tm.extents.max() - 50.0) < 1e-4

    assert main(["export", str(folder), str(tmp_path / "print.stl")]) == 1  # exists
    assert "--overwrite" in capsys.readouterr().err
    assert main(["export", str(folder), str(tmp_path / "print.stl"), "--overwrite", "--pieces", "all"]) == 0
    with pytest.raises(SystemExit) as usage:
        main(["export", str(folder), str(tmp_path / "scan.fbx")])
    assert usage.value.code == 2


def test_cli_export_reads_a_saved_refinement(tmp_path):
    refinement = make_refinement(hole_mask(48, 36))
    refinement.save(tmp_path / "refined")
    assert main(["--quiet", "export", str(tmp_path / "refined"), str(tmp_path / "scan.obj"), "--max-triangles", "500"]) == 0
    back = o3d.t.io.read_triangle_mesh(str(tmp_path / "scan.obj"))
    assert 0 < len(back.triangle.indices) <= 500
    assert back.material.texture_maps["albedo"].as_tensor().numpy().shape[:2] == (36, 48)
    assert main(["export", str(tmp_path / "missing"), str(tmp_path / "other.obj")]) == 1
