"""The synthetic renderer, checked against the geometry it claims to render (small images)."""

import json

import numpy as np
import open3d as o3d
import pytest
from scipy import ndimage

from o3d_mvps import read_capture, synthetic
from o3d_mvps.capture import default_depth_intrinsic
from o3d_mvps.cli import main
from o3d_mvps.colour import linear_to_srgb
from o3d_mvps.datasets import load_mesh
from o3d_mvps.model.camera import backproject, project, transform
from o3d_mvps.model.normals import perspective_normals

SIZE = (160, 120)  # (W, H)


@pytest.fixture(scope="module")
def bunny():
    return load_mesh("bunny")


@pytest.fixture(scope="module")
def directional(bunny):
    """Noise-free SH-exact capture: 3 frames, SF 4."""
    return synthetic.render_capture(bunny, frames=3, scale_factor=4, size=SIZE, light="directional", noise=False)


@pytest.fixture(scope="module")
def led_pair(bunny):
    """LED captures with and without noise (same seed), larger object for more depth pixels, SF 2."""
    kw = dict(frames=3, scale_factor=2, size=SIZE, trajectory="orbit-translate", object_size=0.3, distance=0.5)
    return synthetic.render_capture(bunny, noise=True, **kw), synthetic.render_capture(bunny, noise=False, **kw)


@pytest.fixture(scope="module")
def torus():
    """A smooth legacy mesh seen large (0.3 m at 0.45 m), 3 frames."""
    mesh = o3d.geometry.TriangleMesh.create_torus(
        torus_radius=1, tube_radius=0.45, radial_resolution=200, tubular_resolution=100
    )
    mesh.rotate(o3d.geometry.get_rotation_matrix_from_xyz((0.9, 0.3, 0.0)), center=(0, 0, 0))
    capture = synthetic.render_capture(
        mesh, frames=3, size=SIZE, light="directional", noise=False, object_size=0.3, distance=0.45
    )
    return capture, mesh


def block_mean(depth, sf):
    """Test's own SF x SF area average; blocks with any zero pixel are 0."""
    H, W = depth.shape
    b = depth.astype(np.float64).reshape(H // sf, sf, W // sf, sf)
    return np.where((b > 0).all(axis=(1, 3)), b.mean(axis=(1, 3)), 0.0)


def interior(mask, pixels=2):
    return ndimage.binary_erosion(mask, iterations=pixels)


def srgb_codes(linear):
    return np.rint(linear_to_srgb(np.clip(linear, 0, 1)).astype(np.float64) * 255).astype(int)


def assert_same_8bit(actual_linear, expected_linear):
    """Equal 8-bit sRGB codes; a rounding tie may flip a rare value by one code (float32 vs 64)."""
    difference = np.abs(srgb_codes(actual_linear) - srgb_codes(expected_linear))
    assert difference.max() <= 1 and np.mean(difference > 0) < 1e-3


def frame_buffers(capture, mesh, i, seed=0):
    """The renderer's own noise-free buffers of frame i (same scene as ``capture``)."""
    meta = capture.metadata["synthetic"]
    scene = synthetic.build_scene(
        mesh, size=SIZE, object_size=meta["object_size"], distance=meta["distance"], seed=seed
    )
    light = synthetic.make_light(meta["light"], meta["distance"])
    return synthetic.render_frame(scene, capture.groundtruth.poses[i], light)


# --- geometry --------------------------------------------------------------------------------


def test_conventions(directional):
    cap, gt = directional, directional.groundtruth
    K = cap.color_K()
    assert cap.n_frames == 3 and cap.color_size == (120, 160) and cap.depth_size == (30, 40)
    np.testing.assert_allclose(K[:2, 2], [(160 - 1) / 2, (120 - 1) / 2])
    np.testing.assert_allclose(cap.depth_K(), default_depth_intrinsic(K, 4))
    np.testing.assert_array_equal(gt.poses[0], np.eye(4))
    assert cap.sensor == "synthetic" and cap.color_encoding == "srgb" and cap.depth_scale == 1000
    json.dumps(gt.light)  # serialisable
    z = gt.depth[gt.depth > 0]
    assert 0.45 < z.min() and z.max() < 0.75  # ~0.2 m object ~0.6 m away
    for i in range(cap.n_frames):  # every frame sees the object, R orthonormal, offsets <= ~15 deg
        R = gt.poses[i, :3, :3]
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) <= 22
        assert cap.mask_array(i).sum() > 500


def test_gt_depth_lies_on_the_mesh(directional, bunny):
    gt = directional.groundtruth
    mask = gt.depth > 0
    points = backproject(gt.depth.astype(np.float64), directional.color_K())[mask]
    M = gt.mesh_to_reference
    scale = np.cbrt(np.linalg.det(M[:3, :3]))
    in_mesh = transform(np.linalg.inv(M), points)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        bunny.vertex.positions.numpy().astype(np.float32), bunny.triangle.indices.numpy().astype(np.uint32)
    )
    dist = scene.compute_distance(o3d.core.Tensor(in_mesh.astype(np.float32))).numpy() * scale
    assert mask.sum() > 1000
    assert dist.max() < 1e-4


def test_full_size_depth_has_the_shading_normals():
    # A scanned mesh's facets span ~3 px at 1280x720: the colour, shaded with interpolated normals,
    # and the depth, the facets', part by 2.43 deg (measured). Subdivided below ~a pixel, the depth's
    # own normals are the shading's: 0.308 deg mean measured (the central differences' own error).
    light = synthetic.make_light("led", 0.6)
    angles = {}
    for subdivisions in (None, 0):
        scene = synthetic.build_scene("bunny", size=(1280, 720), subdivisions=subdivisions)
        frame = synthetic.render_frame(scene, np.eye(4), light)
        normals, _ = perspective_normals(frame.depth, scene.K, frame.mask)
        inside = interior(frame.mask, 6)
        cosine = np.clip((normals[inside] * frame.normals[inside]).sum(axis=1), -1, 1)
        angles[scene.subdivisions] = float(np.degrees(np.arccos(cosine)).mean())
    assert set(angles) == {2, 0}  # 1280x720 at 0.6 m picks two Loop subdivisions
    assert angles[2] < 0.4 and angles[0] > 2.0


def test_subdivision_keeps_the_surface_and_follows_the_pixel_size():
    coarse = synthetic.build_scene("bunny", size=(1280, 720), subdivisions=0)
    fine = synthetic.build_scene("bunny", size=(1280, 720), subdivisions=1)
    assert len(fine.triangles) == 4 * len(coarse.triangles)
    np.testing.assert_array_equal(fine.mesh_to_reference, coarse.mesh_to_reference)  # placed as given
    surface = o3d.t.geometry.RaycastingScene()
    surface.add_triangles(o3d.core.Tensor(coarse.vertices.astype(np.float32)),
                          o3d.core.Tensor(coarse.triangles.astype(np.uint32)))
    moved_mm = 1000 * surface.compute_distance(o3d.core.Tensor(fine.vertices.astype(np.float32))).numpy()
    assert np.median(moved_mm) < 0.02 and moved_mm.max() < 0.4  # Loop smoothing, measured 0.014 / 0.32 mm
    # the shipped bunny's facets (mean edge 1.6 px at 640x480 and 0.6 m) against MAX_FACET_PX = 1.5
    chosen = {(size, distance): synthetic.build_scene("bunny", size=size, distance=distance).subdivisions
              for size, distance in [((160, 120), 0.6), ((640, 480), 0.6), ((640, 480), 0.25), ((1708, 1136), 0.25)]}
    assert list(chosen.values()) == [0, 1, 2, 3]


def test_subdivisions_stop_short_of_too_many_triangles_and_bad_counts_are_named():
    from o3d_mvps.synthetic.scene import MAX_TRIANGLES, facet_subdivisions

    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    one = np.array([[0, 1, 2]])
    assert facet_subdivisions(vertices, one, 100.0) == 3  # edges of ~100 px: as many as allowed
    many = np.repeat(one, MAX_TRIANGLES // 8, axis=0)  # one subdivision more would pass the cap
    assert facet_subdivisions(vertices, many, 100.0) == 1
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="subdivisions must be None .* or an integer >= 0"):
            synthetic.build_scene("bunny", size=(160, 120), subdivisions=bad)


def test_a_mesh_vtk_cannot_subdivide_is_rendered_as_given():
    # three triangles on one edge: not manifold, which Loop subdivision refuses
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], dtype=float)
    triangles = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    with pytest.warns(RuntimeWarning, match="could not be Loop-subdivided"):
        scene = synthetic.build_scene(mesh, size=(160, 120), subdivisions=2)
    assert len(scene.triangles) == 3 and scene.subdivisions == 0


def median_angle_deg(a, b, mask):
    return np.median(np.degrees(np.arccos(np.clip((a[mask] * b[mask]).sum(axis=1), -1, 1))))


def test_gt_normals_match_depth_normals(torus):
    # A smooth surface, large in the image: forward differences sit half a pixel off, so their
    # error grows with curvature x pixel size (the scanned bunny has sub-pixel detail).
    torus, mesh = torus
    gt, K = torus.groundtruth, torus.color_K()
    mask = gt.depth > 0
    normals, _ = perspective_normals(gt.depth, K)
    assert median_angle_deg(normals, gt.normals, interior(mask)) < 3.0
    np.testing.assert_allclose(np.linalg.norm(gt.normals[mask], axis=1), 1, atol=1e-5)
    assert np.all((gt.normals[mask] * backproject(gt.depth, K)[mask]).sum(axis=1) < 0)  # facing the camera
    assert np.all(gt.normals[~mask] == 0) and np.all(gt.albedo[~mask] == 0)
    # another frame's buffers (camera frame) agree with its own depth as well
    frame = frame_buffers(torus, mesh, 2)
    normals, _ = perspective_normals(frame.depth, K)
    assert median_angle_deg(normals, frame.normals, interior(frame.mask)) < 3.0


def test_directional_colour_is_exact_sh_shading(directional, bunny):
    gt, sh = directional.groundtruth, np.asarray(directional.groundtruth.light["sh"])
    assert gt.light["model"] == "directional" and sh.shape == (3, 4)
    # reference frame: the ground truth alone
    expected = gt.albedo * (sh[0, 0] + gt.normals @ sh[0, 1:])[..., None]
    assert_same_8bit(directional.color_array(0), expected)
    # another frame: its own buffers, normals turned into reference coordinates
    i = 2
    frame = frame_buffers(directional, bunny, i)
    np.testing.assert_array_equal(frame.mask, directional.mask_array(i))
    n_ref = frame.normals @ gt.poses[i, :3, :3]  # R^T n_cam, row vectors
    expected = frame.albedo * (sh[i, 0] + n_ref @ sh[i, 1:])[..., None] * frame.mask[..., None]
    assert_same_8bit(directional.color_array(i), expected)


def test_low_resolution_depth_is_the_area_average(directional):
    gt = directional.groundtruth
    average = block_mean(gt.depth, 4)
    unquantised = synthetic.simulate_depth_sensor(gt.depth, 4, depth_scale=None)
    np.testing.assert_allclose(unquantised, average, atol=1e-6, rtol=0)
    # the capture: the same average in 1 mm steps
    lr = directional.depth_array(0)
    np.testing.assert_array_equal(lr > 0, average > 0)
    np.testing.assert_allclose(lr, np.rint(average * 1000) / 1000, atol=1e-6, rtol=0)


def test_depth_noise_statistic(led_pair, bunny):
    noisy, clean = led_pair
    residuals = []
    for i in range(noisy.n_frames):
        depth_hr = noisy.groundtruth.depth if i == 0 else frame_buffers(noisy, bunny, i).depth
        z = block_mean(depth_hr, 2)
        ok = (z > 0) & (noisy.depth_array(i) > 0)
        sigma_mm = 1e-5 * (z[ok] * 1000) ** 2
        residual_mm = (noisy.depth_array(i)[ok].astype(np.float64) - z[ok]) * 1000
        residuals.append(residual_mm / np.sqrt(sigma_mm**2 + 1 / 12))  # 1 mm quantisation adds 1/12 mm^2
        np.testing.assert_array_equal(clean.depth_array(i) > 0, z > 0)
    r = np.concatenate(residuals)
    assert r.size > 2000
    assert abs(r.std() - 1) < 0.1
    assert abs(r.mean()) < 0.1


def test_led_light_levels_and_noise(led_pair):
    noisy, clean = led_pair
    light = clean.groundtruth.light
    assert light["model"] == "led" and len(light["positions"]) == 3
    np.testing.assert_allclose(light["positions"][0], light["offset"])
    mask = clean.mask_array(0)
    colour = clean.color_array(0)[mask]
    assert 0.15 < np.median(colour) < 0.8 and colour.max() <= 1.0
    assert np.all(clean.color_array(0)[~mask] == 0)  # black background
    difference = noisy.color_array(0)[mask] - colour
    assert 0.002 < difference.std() < 0.02


def test_gt_poses_are_consistent(directional, bunny):
    gt, K = directional.groundtruth, directional.color_K()
    inner = interior(gt.depth > 0)
    points = backproject(gt.depth.astype(np.float64), K)[inner]
    for i in (1, 2):
        frame = frame_buffers(directional, bunny, i)
        u, v, Z = project(transform(gt.poses[i], points), K)
        u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
        inside = (u0 >= 0) & (v0 >= 0) & (u0 < SIZE[0] - 1) & (v0 < SIZE[1] - 1)
        u, v, Z, u0, v0 = u[inside], v[inside], Z[inside], u0[inside], v0[inside]
        corners = [frame.depth[v0 + dv, u0 + du] for dv in (0, 1) for du in (0, 1)]
        valid = np.all([c > 0 for c in corners], axis=0)
        a, b = u - u0, v - v0
        seen = (1 - a) * (1 - b) * corners[0] + a * (1 - b) * corners[1] + (1 - a) * b * corners[2] + a * b * corners[3]
        error = np.abs(seen - Z)[valid]  # occluded points are seen nearer: a minority of large errors
        assert valid.mean() > 0.9
        assert np.median(error) < 2e-4
        assert np.mean(error < 1e-3) > 0.85
        # and the frame's object mask covers the projected points
        assert directional.mask_array(i)[np.rint(v).astype(int), np.rint(u).astype(int)].mean() > 0.95


# --- determinism, errors, CLI -------------------------------------------------------------------


def test_deterministic_for_a_seed(bunny):
    kw = dict(frames=2, scale_factor=2, size=(80, 60))
    a, b = synthetic.render_capture(bunny, seed=5, **kw), synthetic.render_capture(bunny, seed=5, **kw)
    c = synthetic.render_capture(bunny, seed=6, **kw)
    for i in range(2):
        np.testing.assert_array_equal(a.color_array(i), b.color_array(i))
        np.testing.assert_array_equal(a.depth_array(i), b.depth_array(i))
    np.testing.assert_array_equal(a.groundtruth.albedo, b.groundtruth.albedo)
    assert not np.array_equal(a.color_array(0), c.color_array(0))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(frames=0), "frames must be an integer >= 1"),
        (dict(scale_factor=0), "scale_factor must be an integer in 1..16"),
        (dict(scale_factor=2.0), "scale_factor must be an integer"),
        (dict(scale_factor=32), "scale_factor must be an integer in 1..16"),
        (dict(scale_factor=3), "does not divide the size 160x120"),
        (dict(size=(160,)), r"size must be \(width, height\)"),
        (dict(trajectory="spiral"), "unknown trajectory 'spiral'"),
        (dict(light="sun"), "unknown light 'sun'"),
        (dict(distance=0.1), "must exceed object_size"),
    ],
)
def test_bad_arguments(bunny, kwargs, message):
    with pytest.raises(ValueError, match=message):
        synthetic.render_capture(bunny, **{"size": SIZE, **kwargs})


def test_bad_meshes():
    with pytest.raises(ValueError, match="mesh is empty"):
        synthetic.render_capture(o3d.t.geometry.TriangleMesh(), size=SIZE)
    with pytest.raises(TypeError, match="mesh must be an open3d TriangleMesh"):
        synthetic.render_capture(42, size=SIZE)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        synthetic.render_capture("no_such_mesh.ply", size=SIZE)


def test_cli_writes_a_readable_capture(tmp_path, capsys):
    out = tmp_path / "cap"
    args = ["render", "bunny", str(out), "--frames", "2", "--size", "160x120", "--scale-factor", "4"]
    assert main(["--quiet", *args]) == 0
    cap = read_capture(out)
    assert cap.n_frames == 2 and cap.color_size == (120, 160) and cap.depth_size == (30, 40)
    assert cap.groundtruth is not None and cap.groundtruth.poses.shape == (2, 4, 4) and cap.sensor == "synthetic"
    # the round trip through the folder is exact
    again = synthetic.render_capture("bunny", frames=2, size=SIZE, scale_factor=4)
    for i in range(2):
        np.testing.assert_array_equal(cap.color_array(i), again.color_array(i))
        np.testing.assert_array_equal(cap.depth_array(i), again.depth_array(i))
        np.testing.assert_array_equal(cap.mask_array(i), again.mask_array(i))
    np.testing.assert_array_equal(cap.groundtruth.depth, again.groundtruth.depth)
    # refuses to overwrite; bad sizes are reported, not raised
    assert main(["--quiet", *args]) == 1
    assert "--overwrite" in capsys.readouterr().err
    assert main(["--quiet", *args, "--overwrite"]) == 0
    assert main(["--quiet", "render", "bunny", str(tmp_path / "x"), "--size", "162x120"]) == 1
    assert "does not divide" in capsys.readouterr().err


def test_ring_trajectory_circles_the_object():
    from o3d_mvps.synthetic import ring_trajectory

    distance = 0.6
    poses = ring_trajectory(8, distance, elevation_deg=20.0)
    centre = np.array([0.0, 0.0, distance, 1.0])
    camera_centres = np.array([-T[:3, :3].T @ T[:3, 3] for T in poses])
    np.testing.assert_allclose(np.linalg.norm(camera_centres - centre[:3], axis=1), distance, atol=1e-12)
    for T in poses:  # the object centre on each optical axis, in front of the camera
        np.testing.assert_allclose((T @ centre)[:3], [0.0, 0.0, distance], atol=1e-12)
    np.testing.assert_allclose(camera_centres[:, 1], -distance * np.sin(np.radians(20.0)), atol=1e-12)  # above
    np.testing.assert_allclose(camera_centres[4], [0.0, camera_centres[0, 1], 2 * distance - camera_centres[0, 2]],
                               atol=1e-12)  # frame 4 of 8 looks from the back
    np.testing.assert_allclose(ring_trajectory(4, distance, 0.0)[0], np.eye(4), atol=1e-12)
