"""Whole-object reconstruction (o3d_mvps.reconstruct, o3d-mvps reconstruct) on tiny rendered rings."""

import json

import numpy as np
import open3d as o3d
import pytest
import scipy.ndimage as ndi
import trimesh
from scipy.spatial import cKDTree

import o3d_mvps
from o3d_mvps.synthetic import render_ring
from o3d_mvps.capture import write_capture
from o3d_mvps.cli import main
from o3d_mvps.export import check_solid, write_mesh
from o3d_mvps.reconstruct import ReconstructOptions, azimuth_span_deg, choose_references, reconstruct
from o3d_mvps.reconstruct.fusion import TSDFVolume, pixel_weights
from o3d_mvps.reconstruct.solid import contour
from o3d_mvps.reconstruct.surface import boundary_loops, fill_small_holes

K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
FAST = o3d_mvps.RefineOptions(levels=2, max_iterations=1, progress=False)


@pytest.fixture(scope="module")
def ring():
    return render_ring("bunny", frames=12, size=(160, 120))


def true_distance_mm(points: np.ndarray, capture, scene) -> np.ndarray:
    """Distance (mm) of frame-0 points (n, 3) to the true mesh."""
    to_scene = np.linalg.inv(np.asarray(capture.metadata["world_to_camera"][0]))
    p = points @ to_scene[:3, :3].T + to_scene[:3, 3]
    return 1000 * scene.raycaster.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy()


def test_references_spread_round_the_ring_and_the_span(ring):
    capture, _ = ring
    poses = capture.groundtruth.poses
    assert choose_references(poses, 4) == [0, 3, 6, 9]
    assert azimuth_span_deg(poses) == pytest.approx(330, abs=0.5)  # 12 frames, 30-degree steps
    arc, _ = render_ring("bunny", frames=4, size=(32, 24), arc_deg=30)
    assert azimuth_span_deg(arc.groundtruth.poses) == pytest.approx(30, abs=0.5)



@pytest.mark.parametrize("arc_deg, elevation_deg", [(60, 20), (180, 60), (360, 60)])
def test_span_of_arcs_across_the_azimuth_wrap(arc_deg, elevation_deg):
    # A ring's arc centred on azimuth 0 (frames on both sides of the +-180 degree seam of the
    # arctan2, for every choice of frame 0) and seen from above: the span is the arc, not 360.
    from o3d_mvps.model.se3 import relative_to_reference
    from o3d_mvps.synthetic.camera import ring_trajectory

    world = ring_trajectory(12, 0.6, elevation_deg, arc_deg)
    expected = arc_deg if arc_deg < 360 else 330
    for first in (0, 5, 11):  # frame 0 at one end, the middle, the other end
        poses = relative_to_reference(np.roll(world, -first, axis=0))
        assert azimuth_span_deg(poses) == pytest.approx(expected, abs=0.5)


@pytest.mark.parametrize("max_angle_deg", [5, 15, 30])
def test_an_orbit_in_front_of_the_object_does_not_go_around(max_angle_deg):
    # The +-15 degree spiral orbit of the refine captures once read as 323 degrees (its viewing
    # directions' cone axis, the mean viewing direction, was taken as 'up'). Its span is the
    # yaw range: at most 2 * max_angle_deg, with a 20 % margin for the spiral's sampling.
    from o3d_mvps.synthetic.camera import orbit_trajectory

    span = azimuth_span_deg(orbit_trajectory(20, 0.6, "orbit", max_angle_deg))
    assert 1.0 * max_angle_deg < span <= 2.0 * max_angle_deg * 1.2

def test_pixel_weights_ramp_from_the_silhouette():
    depth = np.full((48, 64), 0.5)
    mask = np.zeros((48, 64), bool)
    mask[10:40, 10:50] = True
    w = pixel_weights(depth, mask, K, 1.0, edge_px=3)
    v, u = np.mgrid[0:48, 0:64]
    cos = 1 / np.sqrt(((u - 31.5) / 100) ** 2 + ((v - 23.5) / 100) ** 2 + 1)  # frontal plane, oblique rays
    ramp = w / cos
    assert w[~mask].max() == 0 and ramp[10, 20] == pytest.approx(1 / 3) and ramp[11, 20] == pytest.approx(2 / 3)
    assert ramp[12, 20] == pytest.approx(1.0) and ramp[25, 30] == pytest.approx(1.0)


def test_fused_plane_lies_on_the_plane():
    volume = TSDFVolume(0.004)
    depth = np.full((48, 64), 0.5)
    for dx in (-0.02, 0.0, 0.02):  # three cameras shifted sideways
        T = np.eye(4)
        T[0, 3] = dx
        volume.integrate(depth, np.ones_like(depth), K, T)
    z = volume.extract_mesh(0.5).vertex.positions.numpy()[:, 2]
    assert len(z) > 100 and np.abs(z - 0.5).max() < 1e-3  # marching cubes on a planar TSDF is exact


def test_small_holes_close_large_stay_open():
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.05, resolution=10)
    positions, tri = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    check_solid(positions, tri)
    cut = tri[1:]  # one triangle removed: one small hole
    assert len(boundary_loops(cut)) == 1
    p, t = fill_small_holes(positions, cut, hole_size=0.05)
    check_solid(p, t)
    p, t = fill_small_holes(positions, cut, hole_size=0.001)
    assert len(t) == len(cut)


@pytest.fixture(scope="module")
def raw_result(ring):
    capture, _ = ring
    return reconstruct(capture, ReconstructOptions(references=4, depth="raw", voxel_mm=3, texture_px=512,
                                                   progress=False), poses=capture.groundtruth.poses)


def test_solid_contour_vertices_stay_apart():
    # vertices of a crossing next to a grid point once came within float32 rounding of one another
    # (an armadillo print solid then lost is_volume when its vertices were merged): the level is
    # kept LEVEL_CLEARANCE from every grid point, so vertices stay ~2.5e-3 voxel apart (0.2e-3 before)
    rng = np.random.default_rng(0)
    occupancy = (ndi.gaussian_filter(rng.random((40, 40, 40)), 2) > 0.5).astype(np.float32)
    positions, triangles = contour(occupancy, np.zeros(3), 1.0)
    assert cKDTree(positions).query(positions, k=2)[0][:, 1].min() > 1e-3
    check_solid(positions, triangles)


def test_raw_reconstruction_is_close_and_prints_a_volume(ring, raw_result):
    capture, scene = ring
    result = raw_result
    d = true_distance_mm(result.mesh.vertex.positions.numpy(), capture, scene)
    assert np.median(d) < 3.0  # 3 mm voxels, 1 mm depth steps with ~4 mm noise at 0.6 m
    assert result.goes_around and result.info["references"] == [0, 3, 6, 9]
    assert result.mesh.vertex.colors.numpy().shape == (len(d), 3)
    solid = result.printable_solid(60.0)
    mesh = trimesh.Trimesh(solid.vertex.positions.numpy(), solid.triangle.indices.numpy())
    assert mesh.is_volume and mesh.extents.max() == pytest.approx(60.0, rel=1e-5)


@pytest.mark.parametrize("suffix", [".obj", ".glb"])
def test_textured_mesh_loads_back_with_its_texture(raw_result, tmp_path, suffix):
    written = write_mesh(raw_result.mesh, tmp_path / f"mesh{suffix}")
    assert [p.name for p in written] == (["mesh.mtl", "mesh_albedo.png", "mesh.obj"] if suffix == ".obj" else ["mesh.glb"])
    loaded = trimesh.load(tmp_path / f"mesh{suffix}", force="mesh")
    material = loaded.visual.material
    texture = np.asarray(getattr(material, "baseColorTexture", None) or material.image)
    assert texture.shape == (512, 512, 3) and loaded.visual.uv.shape == (len(loaded.vertices), 2)
    # the texture read at each vertex's UV against the fused mesh's vertex colour there
    _, index = cKDTree(raw_result.mesh.vertex.positions.numpy()).query(loaded.vertices)
    from_texture = loaded.visual.to_color().vertex_colors[:, :3] / 255.0
    expected = raw_result.mesh.vertex.colors.numpy()[index]
    assert np.abs(from_texture - expected).mean() < 0.015  # measured 0.005: texel rounding, 8 bits, blends
    assert np.abs(from_texture.mean(axis=0) - expected.mean(axis=0)).max() < 0.005  # measured 0.002
    assert np.ptp(texture.reshape(-1, 3).mean(axis=1) / 255) > 0.3  # an albedo image, not a flat fill
    reread = o3d.t.io.read_triangle_mesh(str(tmp_path / f"mesh{suffix}"))
    assert "albedo" in reread.material.texture_maps and "texture_uvs" in reread.triangle


def test_an_arc_warns_that_the_back_is_missing_and_prints_flat(tmp_path, capsys):
    capture, _ = render_ring("bunny", frames=5, size=(160, 120), arc_deg=30)
    with pytest.warns(UserWarning, match="cover 30 degrees.*back is missing"):
        reconstruct(capture, ReconstructOptions(references=2, depth="raw", progress=False),
                    poses=capture.groundtruth.poses)
    write_capture(capture, tmp_path / "arc")
    np.save(tmp_path / "arc" / "poses.npy", capture.groundtruth.poses)
    code = main(["reconstruct", str(tmp_path / "arc"), str(tmp_path / "out"), "--depth", "raw",
                 "--references", "2", "--voxel-mm", "3", "--print", "50"])
    assert code == 0
    out = capsys.readouterr().out
    assert "warning: the frames cover 30 degrees" in out and "the unseen back is closed flat" in out
    solid = trimesh.load(tmp_path / "out" / "print.stl")
    assert solid.is_volume
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["goes_around"] is False and report["azimuth_span_deg"] == pytest.approx(30, abs=0.5)
    assert (tmp_path / "out" / "mesh.glb").is_file() and (tmp_path / "out" / "mesh.obj").is_file()
    assert (tmp_path / "out" / "report.html").is_file()
    # export takes the folder: the mesh simplified, and its print.stl rescaled
    assert main(["export", str(tmp_path / "out"), str(tmp_path / "small.ply"), "--max-triangles", "400"]) == 0
    small = trimesh.load(tmp_path / "small.ply")
    assert 300 <= len(small.faces) <= 400 and small.visual.vertex_colors.shape[0] == len(small.vertices)
    assert main(["export", str(tmp_path / "out"), str(tmp_path / "p.stl"), "--print", "80"]) == 0
    rescaled = trimesh.load(tmp_path / "p.stl")
    assert rescaled.is_volume and rescaled.extents.max() == pytest.approx(80.0, rel=1e-5)
    assert np.allclose(rescaled.extents / rescaled.extents.max(), solid.extents / solid.extents.max(), atol=1e-5)


def test_export_of_an_open_reconstruction_points_at_reconstruct_print(raw_result, tmp_path, capsys):
    folder = tmp_path / "object"
    folder.mkdir()
    write_mesh(raw_result.mesh, folder / "mesh.ply")
    (folder / "report.json").write_text(json.dumps(raw_result.info))
    assert main(["export", str(folder), str(tmp_path / "x.stl")]) == 1
    err = capsys.readouterr().err
    assert f"the mesh in {folder} is not closed" in err and f"reconstruct CAPTURE {folder} --overwrite --print" in err
    assert not (tmp_path / "x.stl").exists()


def test_two_dask_workers_give_the_same_mesh_as_one():
    capture, _ = render_ring("bunny", frames=8, size=(96, 72))
    options = ReconstructOptions(references=3, frames_per_reference=4, voxel_mm=4, texture_px=0, refine=FAST,
                                 progress=False)
    meshes = [o3d_mvps.reconstruct(capture, ReconstructOptions(**{**options.__dict__, "workers": n}),
                                   poses=capture.groundtruth.poses).mesh.vertex.positions.numpy() for n in (1, 2)]
    # the fused grid's block order (hence the vertex order) is not fixed: compare nearest vertices
    assert meshes[0].shape == meshes[1].shape
    assert max(cKDTree(a).query(b)[0].max() for a, b in (meshes, meshes[::-1])) < 1e-6


@pytest.mark.parametrize("light", ["led", "room", None])
def test_a_view_job_keeps_the_capture_and_what_lit_it(ring, light):
    """The arrays a Dask task carries give the capture back: images, intrinsics, its light
    (without it a room-lit ring was refined with the LED model, with a warning per view) and its
    frames' file names."""
    from o3d_mvps.reconstruct.views import capture_arrays, capture_from_arrays

    capture = ring[0].select(range(3))
    capture.light = light
    capture.frame_names = ["000000.png", "000001.png", "000002.png"]
    back = capture_from_arrays(capture_arrays(capture))
    assert back.light == light and back.n_frames == 3
    # a view's messages name the capture's files: "frame 1 (000001.png)"
    assert back.frame_names == capture.frame_names and back.frame_label(1) == "frame 1 (000001.png)"
    np.testing.assert_array_equal(back.color_array(2), capture.color_array(2))
    np.testing.assert_array_equal(back.depth_array(1), capture.depth_array(1))
    np.testing.assert_array_equal(back.color_K(), capture.color_K())


def test_a_views_frames_are_named_by_their_index_in_the_capture(ring):
    """A ring made in memory has no file names: a view's messages (its input checks among them)
    name its frames by their index in the ring ("frame 0" for the view's second frame of reference
    9's view), not by their place in the view ("frame 1"); with file names, by both."""
    import dataclasses

    from o3d_mvps.capture import image_from_array
    from o3d_mvps.capture.checks import check_inputs
    from o3d_mvps.capture.poses import GivenPoses
    from o3d_mvps.covisibility import MIN_COVISIBILITY
    from o3d_mvps.reconstruct.views import capture_from_arrays, plan_view

    capture = ring[0]
    job = plan_view(capture, capture.groundtruth.poses, 9, min_covisibility=MIN_COVISIBILITY, max_frames=8)
    view = capture_from_arrays(job.arrays)
    assert job.frames[:2] == [9, 0] and view.frame_ids == job.frames
    assert [view.frame_label(k) for k in range(2)] == ["frame 9", "frame 0"]
    assert check_inputs(view, GivenPoses.from_array(job.poses)).checks[-1]["name"] == "poses"
    with pytest.warns(UserWarning, match=r"frame quality: dropped 1 frame\(s\): frame 0: black"):
        check_inputs(dataclasses.replace(view, color=[view.color[0], image_from_array(
            np.zeros_like(view.color_array(1)))] + view.color[2:]))
    named = dataclasses.replace(capture, frame_names=[f"{i:06d}.png" for i in range(capture.n_frames)])
    job = plan_view(named, capture.groundtruth.poses, 9, min_covisibility=MIN_COVISIBILITY, max_frames=8)
    assert capture_from_arrays(job.arrays).frame_label(1) == "frame 0 (000000.png)"
    # registration dropped frame 5: the 11 left keep their numbers in the view, its reference and its selection
    kept = [i for i in range(12) if i != 5]
    left = dataclasses.replace(capture.select(kept), frame_ids=kept)
    job = plan_view(left, capture.groundtruth.poses[kept], kept.index(9), min_covisibility=MIN_COVISIBILITY,
                    max_frames=8)
    assert job.reference == 9 and job.frames[:2] == [9, 0] and 5 not in job.selection.covisibility
    assert capture_from_arrays(job.arrays).frame_ids == job.frames and set(job.frames) <= set(kept)
