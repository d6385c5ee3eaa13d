"""The per-frame point light of static captures (issue 32 item 4-6: a lamp moved by hand around a
tripod camera; o3d_mvps.solver.lighting.PointLight, o3d_mvps.solver.point_light)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import QUILT_DISTANCE, quilt_scene

from o3d_mvps import RefineOptions
from o3d_mvps.capture import read_capture, write_capture
from o3d_mvps.errors import CaptureError
from o3d_mvps.metrics import albedo_error, normal_mae_deg
from o3d_mvps.model.normals import perspective_normals
from o3d_mvps.solver.driver import solve
from o3d_mvps.solver.lighting import PointLight, make_light_model
from o3d_mvps.solver.problem_input import SolverInput
from o3d_mvps.synthetic import render_static_capture

FRAMES = 6


@pytest.fixture(scope="module")
def quilt():
    """The quilt under a lamp 0.35 m off axis, 0.65 m before the sheet (6 frames, 160x120, SF 2),
    refined with the point light model: (scene, solver output)."""
    scene = quilt_scene(frames=FRAMES, size=(160, 120))
    opts = RefineOptions(progress=False, light_model="point", refine_poses=False, levels=3, max_iterations=4)
    out = solve(SolverInput(scene["colors"], scene["depths"], [None] * FRAMES, scene["K"], scene["depth_K"], 2,
                            np.tile(np.eye(4), (FRAMES, 1, 1)), np.zeros(3), list(range(FRAMES)), opts))
    return scene, out


def test_point_lights_are_found(quilt):
    """Each frame's lamp is found in the right direction from the sheet's centre: measured 3.2-15.7
    deg off (bound 25) at 0.78-0.81 times its distance (1.24-1.43 when the lamps started on a
    300-pixel level; bounds 0.65-1.5: on a nearly flat sheet with a free albedo per pixel,
    distance and intensity nearly trade off); the model is reported
    with its positions, and the light selection scores it better than per-frame SH (measured
    held-out residual 0.0070 against 0.041, bound half)."""
    scene, out = quilt
    t = np.linspace(0, 2 * np.pi, FRAMES, endpoint=False)
    truth = np.stack([0.35 * np.cos(t), 0.35 * np.sin(t), np.full(FRAMES, QUILT_DISTANCE - 0.65)], axis=1)
    assert out.info["light_model"]["model"] == "point"
    found = np.asarray(out.info["light_model"]["positions_m"]) - [0.0, 0.0, QUILT_DISTANCE]
    expected = truth - [0.0, 0.0, QUILT_DISTANCE]
    cosine = np.sum(found * expected, axis=1) / np.linalg.norm(found, axis=1) / np.linalg.norm(expected, axis=1)
    assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).max() < 25.0
    ratio = np.linalg.norm(found, axis=1) / np.linalg.norm(expected, axis=1)
    assert 0.65 < ratio.min() and ratio.max() < 1.5, ratio
    assert out.lighting.shape == (FRAMES, 2) and (out.lighting[:, 1] > 0).all()
    scores = out.info["light_selection"]["scores"]
    assert set(scores) == {"sh", "point"} and scores["point"] < 0.5 * scores["sh"], scores


def test_point_lights_give_normals_and_albedo_without_shading(quilt):
    """Under the near lamp the normals come out 1.76 deg off (per-frame SH: 10.4 deg), bound 2.5;
    the albedo's median relative error after a global scale 3.9 % (SH 7.6 %), bound 5.5 %."""
    scene, out = quilt
    normals, _ = perspective_normals(out.depth, scene["K"])
    assert normal_mae_deg(normals, scene["normals"], out.mask) < 2.5
    assert albedo_error(out.albedo, scene["albedo"], out.mask) < 0.055


def test_borders_are_as_good_as_the_interior(quilt):
    """The quilt fills the frame and touches the image border on every side (where a real capture
    showed blocks of wrong normals and albedo): the normals within 2 px of the border are 2.39
    deg off against the interior's (16 px or more from the border) 1.49 (2.17 against 1.66 when
    the lamps started on a 300-pixel level); bound: the interior's + 1.1 deg. The albedo error
    there: 4.8 % against 2.9 %; bound: the interior's x 2."""
    scene, out = quilt
    normals, _ = perspective_normals(out.depth, scene["K"])
    error = np.degrees(np.arccos(np.clip(np.sum(normals * scene["normals"], axis=-1), -1, 1)))
    H, W = error.shape
    v, u = np.mgrid[:H, :W]
    distance = np.minimum(np.minimum(u, W - 1 - u), np.minimum(v, H - 1 - v))
    border, interior = out.mask & (distance < 2), out.mask & (distance >= 16)
    assert error[border].mean() < error[interior].mean() + 1.1
    assert albedo_error(out.albedo, scene["albedo"], border) < 2 * albedo_error(out.albedo, scene["albedo"], interior)


def test_point_model_needs_every_frame_at_once():
    """One frame's pose cannot name its light: the model says so instead of shading wrongly."""
    light = PointLight(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="3 light positions, one per frame, but was asked for 1 frames"):
        light.basis(np.array([[0.0, 0.0, -1.0]]), np.array([[0.0, 0.0, 0.5]]), np.eye(4))
    assert make_light_model("point").name == "point"


def test_capture_json_declares_a_point_light(tmp_path):
    """capture.json's "light": "point" reads back; an unknown light names the file and the choices."""
    capture = render_static_capture("bunny", frames=2, size=(160, 120), scale_factor=2, noise=False)
    capture.light = "point"
    write_capture(capture, tmp_path / "c")
    assert read_capture(tmp_path / "c").light == "point"
    settings_file = tmp_path / "c" / "capture.json"
    settings_file.write_text(settings_file.read_text().replace('"point"', '"torch"'))
    with pytest.raises(CaptureError, match="capture.json: light must be one of 'led', 'room', 'point'.*got 'torch'"):
        read_capture(tmp_path / "c")


def test_point_model_keeps_the_poses_and_says_so():
    """Asked to refine poses, the point model keeps them (a free lamp per frame would absorb a
    pose's shading) and warns, naming the LED model for a camera that moved."""
    scene = quilt_scene(frames=3, size=(64, 48))
    kicked = np.tile(np.eye(4), (3, 1, 1))
    kicked[1, 0, 3] = 0.002
    opts = RefineOptions(progress=False, light_model="point", levels=1, max_iterations=1)
    with pytest.warns(UserWarning, match="point light model .* keeps the initial poses.*--light-model led"):
        out = solve(SolverInput(scene["colors"], scene["depths"], [None] * 3, scene["K"], scene["depth_K"], 2, kicked,
                                np.zeros(3), [0, 1, 2], opts))
    np.testing.assert_array_equal(out.poses, kicked)


def test_point_model_energy_in_frame_batches(monkeypatch):
    """On large levels :meth:`LevelProblem.energy` (the extrapolation's trials) takes the frames in
    batches (``ENERGY_BATCH_PIXELS``); each batch must shade with its own frames' lamps (a 640x480
    bunny filling half the image raised "asked for 13 frames" there). Batches of 2 frames give
    the one-batch solve's energies (to 1e-9, the order of the float64 sums)."""
    from o3d_mvps.solver import problem

    scene = quilt_scene(frames=FRAMES, size=(80, 60))
    opts = RefineOptions(progress=False, light_model="point", refine_poses=False, levels=2, max_iterations=3)

    def energies():
        out = solve(SolverInput(scene["colors"], scene["depths"], [None] * FRAMES, scene["K"], scene["depth_K"], 2,
                                np.tile(np.eye(4), (FRAMES, 1, 1)), np.zeros(3), list(range(FRAMES)), opts))
        return np.array([row["energy"] for row in out.energy])

    whole = energies()
    monkeypatch.setattr(problem, "ENERGY_BATCH_PIXELS", 2 * 80 * 60)
    np.testing.assert_allclose(energies(), whole, rtol=1e-9)


def _lamp_scene(positions, M=600, seed=0):
    """Points on a bumpy patch 0.6 m before the camera, its unit normals, an albedo (M, 3) and the
    colours (n, M, 3) that lamps at ``positions`` (n, 3), ambient 0.05 and intensity 0.2 give."""
    from o3d_mvps.model.shading import led_vectors

    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.08, 0.08, (M, 2))
    z = 0.6 + 0.03 * np.cos(20 * xy[:, 0]) * np.sin(15 * xy[:, 1])
    points = np.column_stack([xy, z])
    gx, gy = -0.6 * np.sin(20 * xy[:, 0]) * np.sin(15 * xy[:, 1]), 0.45 * np.cos(20 * xy[:, 0]) * np.cos(15 * xy[:, 1])
    normals = np.column_stack([gx, gy, -np.ones(M)])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo = rng.uniform(0.3, 0.9, (M, 3))
    g = np.einsum("mj,nmj->nm", normals, led_vectors(points, np.asarray(positions)))
    colour = albedo[None] * (0.05 + 0.2 * np.maximum(g, 0.0))[..., None]
    return points, normals, albedo, colour


def test_frames_fit_finds_the_lamps_and_keeps_them_in_reach():
    """:func:`_fit_frames` (all frames' Levenberg-Marquardt together) finds noise-free lamps from
    starts 10 cm off to 1e-6 m, and a lamp whose data come from 10 object distances away is held
    within 5 (:data:`POINT_MAX_DISTANCE`)."""
    from o3d_mvps.solver.point_light import POINT_MAX_DISTANCE, _fit_frames

    truth = np.array([[0.3, 0.0, 0.0], [-0.2, 0.25, 0.05], [0.0, -0.4, 0.1]])
    points, normals, albedo, colour = _lamp_scene(truth)
    usable = np.ones(colour.shape[:2], bool)
    start = np.column_stack([np.full(3, 0.04), np.full(3, 0.25), truth + [0.1, -0.05, 0.05]])
    X, energy = _fit_frames(start, colour, albedo, usable, normals, points, 0.04, 40)
    np.testing.assert_allclose(X[:, 2:], truth, atol=1e-6)
    np.testing.assert_allclose(X[:, :2], [[0.05, 0.2]] * 3, atol=1e-6)
    centre = points.mean(axis=0)
    far = centre + 10 * np.linalg.norm(centre) * np.array([[0.6, 0.0, -0.8]])
    points, normals, albedo, colour = _lamp_scene(far)
    start = np.r_[0.05, 0.2 * 100.0, centre + 2 * np.linalg.norm(centre) * np.array([0.6, 0.0, -0.8])][None]
    X, _ = _fit_frames(start, colour, albedo, np.ones((1, len(points)), bool), normals, points, 0.04, 40)
    assert np.linalg.norm(X[0, 2:] - centre) <= POINT_MAX_DISTANCE * np.linalg.norm(centre) + 1e-9
    assert np.linalg.norm(X[0, 2:] - centre) > 3 * np.linalg.norm(centre)  # it did move out towards the lamp


def test_a_noisy_quilt_has_no_bad_border_band():
    """A real quilted-fabric capture showed jagged blocks of wrong normals and albedo along the top
    border and in a corner. The rendered quilt (320x240, SF 2, 12 frames) with the D415-like sensor
    (terraces, z^2 and low-frequency depth noise, speckle holes, shot noise, gain and white-balance
    drift), filling the frame, refined with the defaults (automatic masks, point light declared):
    the normals within 2 px of the border are 1.98 deg off against the interior's (16 px or more
    from the border) 1.57, every side's 8 px band at most 2.23 deg (the left); bounds: the
    interior's + 0.8 deg (2 px band) and + 1.0 deg (each side). The albedo error there 2.9 %
    against 2.1 %; bound: the interior's x 2. No band of blocks."""
    import open3d as o3d

    from o3d_mvps import refine
    from o3d_mvps.capture import Capture, image_from_array

    frames, (W, H) = 12, (320, 240)
    scene = quilt_scene(frames=frames, size=(W, H), sensor="d415")
    capture = Capture(color=[image_from_array(c) for c in scene["colors"]],
                      depth=[image_from_array(d[..., None]) for d in scene["depths"]],
                      color_intrinsic=o3d.core.Tensor(scene["K"]), depth_intrinsic=o3d.core.Tensor(scene["depth_K"]),
                      camera="static", light="point", depth_scale=1000.0)
    out = refine(capture, RefineOptions(progress=False))
    normals, _ = perspective_normals(out.depth_array().astype(np.float64), scene["K"])
    error = np.degrees(np.arccos(np.clip(np.sum(normals * scene["normals"], axis=-1), -1, 1)))
    mask, albedo = out.mask_array(), out.albedo_array()
    assert mask.mean() > 0.9  # the quilt fills the frame (less the speckle holes)
    v, u = np.mgrid[:H, :W]
    distance = np.minimum(np.minimum(u, W - 1 - u), np.minimum(v, H - 1 - v))
    border, interior = mask & (distance < 2), mask & (distance >= 16)
    inside = error[interior].mean()
    assert error[border].mean() < inside + 0.8, (error[border].mean(), inside)
    for side in (v < 8, v >= H - 8, u < 8, u >= W - 8):
        assert error[mask & side].mean() < inside + 1.0, (error[mask & side].mean(), inside)
    assert albedo_error(albedo, scene["albedo"], border) < 2 * albedo_error(albedo, scene["albedo"], interior)


def test_the_point_light_bases_are_the_clamped_irradiances_bit_for_bit():
    """:meth:`.LEDLight.bases` on the host (one compiled pass, :func:`.shading.led_bases_into`)
    equals ``[1, max(0, <n, v_i>)]`` of :func:`.shading.led_irradiances`
    cast to the dtype, for the point light's own positions and the LED's, float32 and float64;
    a pixel facing away from its lamp gets 0."""
    from o3d_mvps.model.shading import led_irradiances
    from o3d_mvps.solver.lighting import LEDLight

    rng = np.random.default_rng(3)
    N, n = 5000, 4
    normals = rng.normal(size=(N, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    points = rng.normal(size=(N, 3)) * 0.05 + [0.0, 0.0, 0.6]
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[1:, :3, 3] = rng.normal(size=(n - 1, 3)) * 0.02
    for light in (PointLight(rng.normal(size=(n, 3)) * 0.3), LEDLight([0.02, -0.01, 0.0])):
        g = led_irradiances(normals, points, light.positions(poses))
        assert (g < 0).any() and (g > 0).any()
        for dtype in (np.float32, np.float64):
            expected = np.ones(g.shape + (2,), dtype=dtype)
            expected[..., 1] = np.maximum(g, 0.0)
            found = light.bases(normals, points, poses, dtype=dtype)
            assert found.dtype == dtype and found.shape == (n, N, 2)
            np.testing.assert_array_equal(found, expected)
