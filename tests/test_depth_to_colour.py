"""register_depth against ground truth rendered in both cameras with RaycastingScene."""

import numpy as np
import open3d as o3d
import pytest
from scipy.ndimage import binary_erosion, maximum_filter

from o3d_mvps.capture import default_depth_intrinsic
from o3d_mvps.model.camera import backproject, project, transform
from o3d_mvps.depth_to_colour import register_depth

# Colour 320 x 240 registered at SF 2 -> target grid 160 x 120; the depth camera is a
# 160 x 120 camera with slightly different intrinsics, 15 mm to the side, slightly rotated.
COLOR_K = np.array([[290.0, 0.0, 161.3], [0.0, 288.0, 118.7], [0.0, 0.0, 1.0]])
DEPTH_K = np.array([[139.0, 0.0, 78.2], [0.0, 140.5, 60.9], [0.0, 0.0, 1.0]])
SF, OUT_SIZE, DEPTH_SIZE = 2, (160, 120), (160, 120)


def _rotation_y(degrees):
    a = np.deg2rad(degrees)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _depth_to_color(baseline):
    T = np.eye(4)
    T[:3, :3] = _rotation_y(0.7)
    T[:3, 3] = [-baseline, 0.001, 0.0005]
    return T


def _scene(wall_z):
    """A sphere (r = 8 cm, 0.5 m away) in front of a wall, in depth-camera coordinates."""
    scene = o3d.t.geometry.RaycastingScene()
    wall = o3d.t.geometry.TriangleMesh.create_box(3.0, 3.0, 0.01)
    wall.translate([-1.5, -1.5, wall_z])
    sphere = o3d.t.geometry.TriangleMesh.create_sphere(0.08, resolution=60)
    sphere.translate([0.01, -0.005, 0.5])
    scene.add_triangles(wall)
    ids = {scene.add_triangles(sphere)}
    return scene, ids


def _render(scene, K, world_to_cam, size):
    """z-depth (h, w) and a mask of the given geometry ids, rays through pixel centres."""
    w, h = size
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    cam_to_world = np.linalg.inv(world_to_cam)
    d_world = d_cam @ cam_to_world[:3, :3].T  # keeps |z_cam| = 1, so t_hit is z
    origin = np.broadcast_to(cam_to_world[:3, 3], d_world.shape)
    rays = np.concatenate([origin, d_world], -1).reshape(-1, 6).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().reshape(h, w)
    geometry = hit["geometry_ids"].numpy().reshape(h, w)
    z = np.where(np.isfinite(t), t, 0.0)
    return z, geometry


def _rendered(baseline, wall_z):
    scene, sphere_ids = _scene(wall_z)
    T = _depth_to_color(baseline)
    depth, _ = _render(scene, DEPTH_K, np.eye(4), DEPTH_SIZE)
    target_K = default_depth_intrinsic(COLOR_K, SF)
    truth, geometry = _render(scene, target_K, T, OUT_SIZE)
    sphere = np.isin(geometry, list(sphere_ids))
    return depth, truth, sphere, T


def test_register_depth_matches_colour_render():
    # The D415's depth-to-colour baseline is about 15 mm.
    depth, truth, sphere, T = _rendered(0.015, 0.75)
    out = register_depth(depth, DEPTH_K, COLOR_K, T, OUT_SIZE, scale_factor=SF)
    assert out.shape == (120, 160) and out.dtype == np.float32
    # Inside the object (away from its silhouette, where one-pixel edge effects are expected).
    inner = binary_erosion(sphere, iterations=2)
    err = np.abs(out - truth)[inner]
    assert np.all(out[inner] > 0), "pinholes inside the object"
    assert np.median(err) < 1e-3
    assert np.percentile(err, 95) < 3e-3
    # The wall where both cameras see it: also reproduced, no pinholes.
    wall = binary_erosion((truth > 0.7) & ~sphere, iterations=2) & (out > 0.7)
    assert np.median(np.abs(out - truth)[wall]) < 1e-3
    assert (out > 0).mean() > 0.98


def test_register_depth_leaves_occluded_background_empty():
    # A wider baseline and a farther wall make the band hidden from the depth camera ~7 px wide.
    depth, truth, sphere, T = _rendered(0.05, 1.0)
    out = register_depth(depth, DEPTH_K, COLOR_K, T, OUT_SIZE, scale_factor=SF)
    # Wall pixels the colour camera sees but the depth camera cannot (behind the sphere from the
    # depth camera's viewpoint): find them by re-rendering the wall point into the depth camera.
    v, u = np.nonzero((truth > 0.9) & ~sphere)
    target_K = default_depth_intrinsic(COLOR_K, SF)
    pts = transform(np.linalg.inv(T), backproject(truth[v, u], target_K, u.astype(float), v.astype(float)))
    ud, vd, zd = project(pts, DEPTH_K)
    ui, vi = np.round(ud).astype(int), np.round(vd).astype(int)
    inside = (ui >= 0) & (ui < DEPTH_SIZE[0]) & (vi >= 0) & (vi < DEPTH_SIZE[1])
    # Hidden: every depth pixel within one pixel of the projection is on the sphere, in front.
    nearest_wall = maximum_filter(depth, size=3)
    hidden = np.zeros_like(inside)
    hidden[inside] = nearest_wall[vi[inside], ui[inside]] < zd[inside] - 0.05
    assert hidden.sum() > 100, "test scene should have a disocclusion region"
    hidden_out = out[v[hidden], u[hidden]]
    # Holes where occluded: never filled with the wall's depth, sphere fattened by <= 1 pixel.
    assert np.all(hidden_out < 0.6)
    assert np.mean(hidden_out == 0) > 0.7


def test_register_depth_identity_is_exact():
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.4, 0.9, size=(30, 40)).astype(np.float32)
    depth[5:8, 10:12] = 0.0
    K = default_depth_intrinsic(np.array([[100.0, 0, 39.5], [0, 100.0, 29.5], [0, 0, 1]]), 1)
    color_K = np.array([[200.0, 0, 79.5], [0, 200.0, 59.5], [0, 0, 1]])  # the same camera at 2x
    out = register_depth(depth, default_depth_intrinsic(color_K, 2), color_K, np.eye(4), (40, 30), scale_factor=2)
    np.testing.assert_allclose(out, depth, rtol=0, atol=1e-6)
    assert np.allclose(out, register_depth(depth, K, K, np.eye(4), (40, 30)), atol=1e-6)


def test_register_depth_input_checks():
    with pytest.raises(ValueError, match="4x4"):
        register_depth(np.ones((4, 4)), np.eye(3), np.eye(3), np.eye(3), (4, 4))
    with pytest.raises(ValueError, match="out_size"):
        register_depth(np.ones((4, 4)), np.eye(3), np.eye(3), np.eye(4), (0, 4))
    assert not register_depth(np.zeros((4, 4)), np.eye(3), np.eye(3), np.eye(4), (5, 3)).any()
