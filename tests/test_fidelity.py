"""The solver's weighting against the sensor (issue 32 items 3 and 6): the depth's low frequencies
tied to the sensor depth, and per-pixel smoothness from the shading system's conditioning."""

import cv2
import numpy as np
import pytest

from helpers import quilt_scene
from o3d_mvps.metrics import normal_mae_deg
from o3d_mvps.model.normals import masked_grid, perspective_normals
from o3d_mvps.solver.driver import solve
from o3d_mvps.solver.lighting import SHLight
from o3d_mvps.solver.options import RefineOptions
from o3d_mvps.solver.problem import Estimate, Evaluation
from o3d_mvps.solver.problem_input import SolverInput
from o3d_mvps.solver.pyramid import DepthPrior
from o3d_mvps.solver.smoothness import second_differences
from o3d_mvps.solver.weighting import (EVIDENCE_MAX_WEIGHT, LOWPASS_MIN_SIGMA, evidence_weights, lowpass_sigma,
                                       normal_evidence, tie_low_frequencies)


def _lowpass(x, mask, sigma):
    w = cv2.GaussianBlur(mask.astype(np.float64), (0, 0), sigma)
    return cv2.GaussianBlur(np.where(mask, x, 0.0), (0, 0), sigma) / np.maximum(w, 1e-9)


def test_tie_replaces_the_low_frequencies_and_keeps_the_detail():
    """A bowl of 8 mm plus a 0.5 mm relief of period 6 px on a 0.5 m plane (120x160, sensor at SF
    2): the tie leaves under 0.15 mm of the bowl (measured 0.107 mm, at the inner region's
    corners) and the relief within 3 %."""
    H, W = 120, 160
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    bowl = 0.008 * (((u - W / 2) / (W / 2)) ** 2 + ((v - H / 2) / (H / 2)) ** 2)
    detail = 0.0005 * np.sin(2 * np.pi * u / 6)
    z0 = np.full((H // 2, W // 2), 0.5)
    mask = np.ones((H, W), bool)
    tied = tie_low_frequencies(0.5 + bowl + detail, mask, z0, sigma=4.0)
    inner = (slice(10, -10), slice(10, -10))
    assert np.abs(_lowpass(tied, mask, 8.0) - 0.5)[inner].max() < 1.5e-4
    wave = np.sin(2 * np.pi * u / 6)[inner]
    kept = np.sum((tied[inner] - tied[inner].mean()) * wave) / np.sum(wave * wave)  # the relief's amplitude
    assert kept == pytest.approx(0.0005, rel=0.03)


def test_tie_ignores_pixels_outside_the_mask_and_missing_sensor_depth():
    z = np.full((40, 40), 0.6)
    mask = np.zeros((40, 40), bool)
    mask[5:35, 5:35] = True
    z0 = np.full((20, 20), 0.5)
    z0[:, :5] = 0.0  # missing depth: not compared
    tied = tie_low_frequencies(z, mask, z0, sigma=4.0)
    assert np.array_equal(tied[~mask], z[~mask])
    assert np.allclose(tied[mask], 0.5)


def test_lowpass_sigma_grows_with_the_sensor_noise():
    rng = np.random.default_rng(0)
    mask = np.ones((80, 80), bool)
    quiet = np.full((40, 40), 0.5)
    noisy = 0.5 + rng.normal(0, 0.003, (40, 40))
    assert lowpass_sigma(quiet, mask, 2) == LOWPASS_MIN_SIGMA
    # 3 mm noise at 0.5 m averaged down to 0.1 per mille: sigma = 3 / (2 sqrt(pi) 0.05) = 16.9 px
    assert lowpass_sigma(noisy, mask, 2) == pytest.approx(16.9, rel=0.15)


def _evaluation(normals, lights, albedo, usable):
    shading = lights[:, :1] + lights[:, 1:] @ normals.T  # (n, N)
    n, N = shading.shape
    return Evaluation(np.zeros((n, N, 3)), usable, np.zeros((n, N, 3), np.float32), shading, normals,
                      np.ones(N), None, 0.0, 0.0)


def test_normal_evidence_scales_with_albedo_squared_and_vanishes_without_light_diversity():
    """Four frames lit from four sides: the evidence of a pixel 10x darker is 100x smaller; with
    one light for every frame the shading says nothing about the normal (evidence ~0)."""
    N = 3
    normals = np.tile([0.0, 0.0, -1.0], (N, 1))
    lights = np.array([[0.2, 0.5, 0, -1], [0.2, -0.5, 0, -1], [0.2, 0, 0.5, -1], [0.2, 0, -0.5, -1]])
    albedo = np.array([[0.6] * 3, [0.06] * 3, [0.6] * 3])
    usable = np.ones((4, N), bool)
    usable[1:, 2] = False  # pixel 2: one frame only
    est = Estimate(np.full(N, 0.5), albedo, lights, np.tile(np.eye(4), (4, 1, 1)))
    evidence = normal_evidence(SHLight(), est, _evaluation(normals, lights, albedo, usable), np.zeros((N, 3)))
    assert evidence[0] > 0
    assert evidence[1] / evidence[0] == pytest.approx(0.01, rel=1e-6)
    assert evidence[2] < 1e-9 * evidence[0]
    same = np.tile(lights[:1], (4, 1))
    est.lights = same
    flat = normal_evidence(SHLight(), est, _evaluation(normals, same, albedo, np.ones((4, N), bool)), np.zeros((N, 3)))
    assert flat.max() < 1e-9 * evidence[0]



def test_the_tangent_eigenvalue_is_that_of_the_projected_matrix():
    """normal_evidence's closed form (one fused kernel on a GPU): the smaller eigenvalue of
    G - v v^T / d restricted to the plane normal to n, against NumPy's eigvalsh of that 2 x 2
    restriction in an orthonormal tangent basis; normals along the axes included."""
    from o3d_mvps.solver.weighting import _tangent_min_eigenvalue

    rng = np.random.default_rng(1)
    n = rng.normal(size=(400, 3))
    n[:3] = np.eye(3)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    A = rng.normal(size=(400, 3, 5))
    G, v = A @ A.transpose(0, 2, 1), rng.normal(size=(400, 3))
    d = rng.random(400) + 3 * (v**2).sum(axis=1)
    H = G - v[:, :, None] * v[:, None, :] / d[:, None, None]
    # any orthonormal tangent basis: from the QR of [n, e1, e2]
    T = np.stack([np.linalg.qr(np.column_stack([m, np.eye(3)[:, :2]]))[0][:, 1:] for m in n])  # (N, 3, 2)
    expected = np.maximum(np.linalg.eigvalsh(T.transpose(0, 2, 1) @ H @ T)[:, 0], 0.0)
    got = _tangent_min_eigenvalue(*n.T, G[:, 0, 0], G[:, 0, 1], G[:, 0, 2], G[:, 1, 1], G[:, 1, 2], G[:, 2, 2], *v.T, d)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())

def test_evidence_weights_lean_on_smoothness_where_evidence_is_weak():
    weights = evidence_weights(np.array([1.0, 2.0, 1.0, 0.1, 0.0, 3.0, 1.0]))
    assert np.allclose(weights, [1, 1, 1, 10, EVIDENCE_MAX_WEIGHT, 1, 1])
    assert np.array_equal(evidence_weights(np.zeros(4)), np.ones(4))


def test_weighted_smoothness_energy_is_the_weighted_sum_of_squared_second_differences():
    rng = np.random.default_rng(1)
    grid = masked_grid(np.ones((12, 15), bool))
    S = second_differences(grid)
    prior = DepthPrior(S[:0], np.zeros(0), S=S)
    z = rng.random(grid.size)
    w = 1 + 9 * rng.random(grid.size)
    prior.weigh_smoothness(w)
    centre = S.indices[S.data < 0]
    assert prior.energy(z, 0.0, 2.0) == pytest.approx(2.0 * np.sum(w[centre] * (S @ z) ** 2), rel=1e-12)
    hessian, rhs = prior.normal_equations(z, 0.0, 2.0)
    assert np.allclose(hessian @ z, -rhs)  # the gradient of the weighted energy
    prior.weigh_smoothness(np.ones(grid.size))  # replaces, does not compound
    assert prior.energy(z, 0.0, 1.0) == pytest.approx(np.sum((S @ z) ** 2), rel=1e-12)


def test_options_reject_a_wrong_sensor_lowpass():
    with pytest.raises(ValueError, match="sensor_lowpass.*-1"):
        RefineOptions(sensor_lowpass=-1)
    with pytest.raises(ValueError, match="evidence_weights"):
        RefineOptions(evidence_weights="yes")
    sh, led = RefineOptions(light_model="sh").model, RefineOptions(light_model="led").model
    assert (sh.lowpass_width(), sh.evidence_weighted()) == ("auto", True)
    assert (led.lowpass_width(), led.evidence_weighted()) == (None, True)
    assert RefineOptions(light_model="sh", sensor_lowpass=0).model.lowpass_width() is None


def _solve_quilt(scene, **options):
    n = len(scene["colors"])
    opts = RefineOptions(progress=False, light_model="sh", refine_poses=False, refine_led_offset=False, levels=3,
                         max_iterations=4, **options)
    return solve(SolverInput(scene["colors"], scene["depths"], [None] * n, scene["K"], scene["depth_K"], 2,
                             np.tile(np.eye(4), (n, 1, 1)), np.zeros(3), list(range(n)), opts))


def _quilt_figures(scene, out) -> dict:
    """Low-pass difference from the sensor (Gaussian 5 px, p95, per mille of depth), depth RMSE
    (mm), normal MAE (deg) in the dark patches for ours and for the sensor's bicubic surface
    smoothed by a Gaussian of 4 px, and the correlation of the depth error's high-pass (Gaussian
    3 px) with the albedo; inside an 8 px border."""
    H, W = scene["depth"].shape
    sensor = cv2.resize(scene["depths"][0].astype(np.float64), (W, H), interpolation=cv2.INTER_CUBIC)
    inner = np.zeros((H, W), bool)
    inner[8:-8, 8:-8] = True
    low = np.abs(_lowpass(out.depth, out.mask, 5.0) - _lowpass(sensor, out.mask, 5.0))[inner] / out.depth[inner]
    dark = inner & (scene["albedo"].mean(axis=2) < 0.1)
    ours, _ = perspective_normals(out.depth, scene["K"])
    smoothed, _ = perspective_normals(cv2.GaussianBlur(sensor, (0, 0), 4.0), scene["K"])
    error = out.depth - scene["depth"]
    high = (error - cv2.GaussianBlur(error, (0, 0), 3.0))[inner]
    return {"lowpass_per_mille": 1000 * float(np.percentile(low, 95)),
            "rmse_mm": 1000 * float(np.sqrt(np.mean(error[inner] ** 2))),
            "dark_mae": normal_mae_deg(ours, scene["normals"], dark),
            "sensor_dark_mae": normal_mae_deg(smoothed, scene["normals"], dark),
            "albedo_correlation": float(np.corrcoef(high, scene["albedo"].mean(axis=2)[inner])[0, 1])}


def test_static_camera_quilt_keeps_the_sensors_coarse_shape():
    """A static camera, a hand-held light 0.35 m off axis (which the SH model cannot describe),
    6 frames of a plaid quilt, 160x120, SF 2, 3 levels. Without the tie the surface bends
    (low-pass difference from the sensor p95 measured 10.6 per mille of depth, depth RMSE
    3.15 mm); with it 2.25 per mille (bound 3; at 320x240, 8 frames and the default 5 levels it
    is 1.75, within the issue's target of 2) and 1.58 mm (bound 2.0)."""
    scene = quilt_scene(frames=6, size=(160, 120))
    got = _quilt_figures(scene, _solve_quilt(scene))
    assert got["lowpass_per_mille"] < 3.0, got
    assert got["rmse_mm"] < 2.0, got


def test_dark_texture_does_not_become_relief():
    """The quilt under a distant light (SH-exact), 6 frames, 160x120, SF 2, colour noise 0.005
    and 8-bit linear quantisation (dark patches: albedo 0.04-0.08, signal about 10 grey levels),
    sensor noise 1.5 mm: the normals in the dark patches are 1.68 deg off (without the evidence
    weights 2.02), the sensor's smoothed surface's 4.29 deg: bound 0.6 x the sensor's (measured
    0.39 x). The depth error's high-pass does not follow the albedo: |correlation| 0.007, bound
    0.1."""
    scene = quilt_scene(frames=6, size=(160, 120), light_distance=35.0, light_height=65.0)
    got = _quilt_figures(scene, _solve_quilt(scene))
    assert got["dark_mae"] < 0.6 * got["sensor_dark_mae"], got
    assert abs(got["albedo_correlation"]) < 0.1, got


def test_static_capture_with_sensor_noise_follows_the_sensors_coarse_shape():
    """o3d_mvps.synthetic's static-camera bunny under a hand-held light with the D415-like sensor
    (quantised terraces, flying pixels, holes, gain drift), 320x240, SF 2, 12 frames, refined with
    per-frame SH (identity poses): the low-pass difference from the
    sensor (Gaussian 10 px over the pixels within 4 robust sigmas, p95) is 0.48 per mille of
    depth (without the tie and the evidence weights 3.27), bound 2; normals 6.5 deg (bicubic
    14.0), bound 0.6 x bicubic's."""
    from o3d_mvps import refine, synthetic
    from o3d_mvps.baselines import bicubic
    from o3d_mvps.metrics import evaluate

    capture = synthetic.render_static_capture("bunny", frames=12, size=(320, 240), scale_factor=2, sensor="d415")
    result = refine(capture, RefineOptions(progress=False, light_model="sh"))
    assert result.info["light_model"]["model"] == "sh"
    depth = result.depth_array()
    sensor = cv2.resize(capture.depth_array(0).astype(np.float64), (320, 240), interpolation=cv2.INTER_CUBIC)
    difference = depth - sensor
    ok = (depth > 0) & (sensor > 0)
    centre = np.median(difference[ok])
    ok &= np.abs(difference - centre) < 4 * 1.4826 * np.median(np.abs(difference[ok] - centre))
    inner = cv2.erode((depth > 0).astype(np.uint8), np.ones((17, 17), np.uint8)).astype(bool) & ok
    low = np.abs(_lowpass(difference, ok, 10.0))[inner] / depth[inner]
    assert 1000 * np.percentile(low, 95) < 2.0
    truth = capture.groundtruth
    assert evaluate(result, truth)["mae_deg"] < 0.6 * evaluate(bicubic(capture), truth)["mae_deg"]


def test_normal_evidence_under_the_led_equals_the_einsums_over_its_fields():
    """Under the LED (a field per frame and pixel) normal_evidence sums G, v, d in one compiled
    pass that forms the fields per pixel (kernels.led_evidence_sums, the GPU path's kernel): equal
    to the einsums over the light model's own fields (LEDLight.fields, (n, N, 3)) to 1e-12 of the
    largest evidence (summation order only), unusable frames, unlit pixels and a float32
    shading included; a pixel no frame sees has none."""
    from o3d_mvps.solver.lighting import LEDLight
    from o3d_mvps.solver.weighting import _tangent_min_eigenvalue

    rng = np.random.default_rng(3)
    n, N = 7, 5003
    usable = rng.random((n, N)) > 0.3
    usable[:, 0] = False  # a pixel no frame sees: zero evidence
    normals = rng.normal(size=(N, 3))
    normals[:, 2] = -np.abs(normals[:, 2])  # most face the camera: lit and unlit pixels
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = rng.normal(size=(N, 3)) * 0.05 + [0.0, 0.0, 0.6]
    albedo = rng.random((N, 3))
    shading = rng.random((n, N)).astype(np.float32)
    light = LEDLight(np.array([0.03, -0.02, 0.01]))
    lights = np.column_stack([rng.random(n) * 0.2, rng.random(n) * 0.4 + 0.1])
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = rng.normal(size=(n, 3)) * 0.05
    ev = Evaluation(np.zeros((n, N, 3), np.float32), usable, np.zeros((n, N, 3), np.float32), shading, normals,
                    np.ones(N), None, 0.0, 0.0)
    got = normal_evidence(light, Estimate(np.full(N, 0.6), albedo, lights, poses), ev, points)
    _, L = light.fields(lights, normals, points, poses)
    u = usable * (albedo**2).sum(axis=1)
    us = u * shading
    G, v = np.einsum("in,inj,ink->njk", u, L, L), np.einsum("in,inj->nj", us, L)
    expected = _tangent_min_eigenvalue(*normals.T, G[:, 0, 0], G[:, 0, 1], G[:, 0, 2], G[:, 1, 1], G[:, 1, 2],
                                       G[:, 2, 2], *v.T, (us * shading).sum(axis=0))
    assert (L == 0).any() and (L != 0).any()
    assert got[0] == 0.0 and expected.max() > 0
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * expected.max())
