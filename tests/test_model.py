"""Unit tests of the model pieces: SE(3), normals, shading, warping/occlusion, robust weights,
and the solver's analytic derivatives against finite differences of the energy."""

import numpy as np
import pytest

from o3d_mvps.model import se3
from o3d_mvps.model.camera import backproject, pixel_grid, scale_intrinsics
from o3d_mvps.model.normals import (
    masked_grid,
    perspective_normals,
    unnormalised_normals,
)
from o3d_mvps.model.robust import cauchy, cauchy_weights
from o3d_mvps.model.shading import sh_basis, shading
from o3d_mvps.model.warping import sample_bilinear, visible, warp
from o3d_mvps.solver.lighting import LEDLight
from o3d_mvps.solver.normal_equations import joint_system
from o3d_mvps.solver.pose import pose_jacobian, pose_system
from o3d_mvps.solver.problem import LevelProblem

from helpers import SIZE, K, assert_gradient_at_random_pixels, bump_depth, make_problem

def test_se3_round_trip_and_composition(rng):
    for _ in range(20):
        xi = rng.normal(size=6) * np.array([0.1, 0.1, 0.1, 0.5, 0.5, 0.5])
        T = se3.exp(xi)
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(se3.log(T), xi, atol=1e-10)
    small = np.array([1e-3, 0, 0, 1e-7, -2e-7, 3e-7])
    np.testing.assert_allclose(se3.log(se3.exp(small)), small, atol=1e-14)
    rot, trans = se3.pose_error(se3.exp([0, 0, 0.01, 0, np.radians(2), 0]), np.eye(4))
    assert rot == pytest.approx(2.0, abs=1e-9) and trans == pytest.approx(0.01, rel=1e-3)


def test_perspective_normals_of_a_plane_match_the_plane():
    u, v = pixel_grid(*SIZE)
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    z = -0.6 / (rays @ n)
    normals, dA = perspective_normals(z, K)
    angle = np.degrees(np.arccos(np.clip(normals @ n, -1, 1)))
    assert angle.max() < 0.1
    # dA is |n~| = z^2 / (fx fy) * |dP/du x dP/dv| -> positive everywhere
    assert (dA > 0).all()


@pytest.mark.parametrize("scheme", ["central", "forward"])
def test_masked_differences_and_their_operators(scheme):
    mask = np.zeros((5, 6), bool)
    mask[1:4, 1:5] = True
    mask[2, 4] = False
    full = np.arange(30, dtype=float).reshape(5, 6) ** 1.5
    grid = masked_grid(mask, scheme)
    z = grid.gather(full)
    zu, zv = grid.gradient(z)

    def expected(r, c, dr, dc):
        f, b = mask[r + dr, c + dc], mask[r - dr, c - dc]
        if f and b and scheme == "central":
            return 0.5 * (full[r + dr, c + dc] - full[r - dr, c - dc])
        if f:
            return full[r + dr, c + dc] - full[r, c]
        return full[r, c] - full[r - dr, c - dc] if b else 0.0

    for k in range(grid.size):
        r, c = grid.v[k], grid.u[k]
        assert zu[k] == pytest.approx(expected(r, c, 0, 1)) and zv[k] == pytest.approx(expected(r, c, 1, 0))
    Du, Dv = grid.difference_operators()
    np.testing.assert_allclose(Du @ z, zu)
    np.testing.assert_allclose(Dv @ z, zv)


def test_central_normals_of_a_sphere_are_more_accurate_than_forward():
    u, v = pixel_grid(*SIZE)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    centre, radius = np.array([0.0, 0.0, 0.5]), 0.12
    b = rays @ centre
    disc = b**2 - (rays**2).sum(-1) * (centre @ centre - radius**2)
    hit = disc > 0
    t = np.where(hit, (b - np.sqrt(np.where(hit, disc, 0))) / (rays**2).sum(-1), 0)
    z = t  # rays have unit z component
    points = rays * t[..., None]
    truth = (points - centre) / radius
    inner = hit & (np.sqrt(np.where(hit, disc, 0)) > 0.3 * np.sqrt(disc.max()))
    errors = {}
    for scheme in ("central", "forward"):
        normals, _ = perspective_normals(z, K, hit, scheme)
        errors[scheme] = np.degrees(np.arccos(np.clip((normals * truth).sum(-1), -1, 1)))[inner].mean()
    assert errors["central"] < 0.3 < errors["forward"]


def test_sh_shading_is_the_dot_product():
    n = np.array([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8]])
    light = np.array([0.2, 0.1, -0.3, -1.0])
    np.testing.assert_allclose(sh_basis(n) @ light, shading(n, light))
    assert shading(n, light)[0] == pytest.approx(1.2)


def test_cauchy_weights_are_the_irls_derivative():
    r = np.linspace(-0.3, 0.3, 41)
    lam = 0.04
    h = 1e-6
    dphi = (cauchy(r + h, lam) - cauchy(r - h, lam)) / (2 * h)
    np.testing.assert_allclose(dphi, cauchy_weights(r, lam) * r, atol=1e-8)
    # majoriser: phi(r) <= phi(rk) + w(rk)/2 (r^2 - rk^2)
    rk = 0.05
    assert np.all(cauchy(r, lam) <= cauchy(rk, lam) + cauchy_weights(rk, lam) / 2 * (r**2 - rk**2) + 1e-15)


def test_bilinear_sampling_is_exact_on_linear_images():
    u, v = pixel_grid(*SIZE)
    image = np.stack([2 * u + 3 * v, u - v], -1)
    su, sv = np.array([0.0, 10.25, 62.9]), np.array([0.0, 7.5, 46.1])
    np.testing.assert_allclose(sample_bilinear(image, su, sv), np.stack([2 * su + 3 * sv, su - sv], -1), atol=1e-12)


def test_image_gradients_are_the_samples_of_central_difference_images(rng):
    """Away from the border the sampled gradients (the solver's kernel) are the bilinear samples of
    the image's central-difference gradient images (interpolation commutes with whole-pixel
    shifts), to rounding for a float64 image and to float32's for a float32 one."""
    from o3d_mvps.solver.kernels import warp_gradients

    H, W = SIZE
    u, v = pixel_grid(*SIZE)
    image = np.stack([np.sin(u / 5.0) * np.cos(v / 7.0), np.cos((u + 2 * v) / 9.0), 0.01 * u * v], -1)
    grad_u, grad_v = np.zeros_like(image), np.zeros_like(image)
    grad_u[:, 1:-1] = 0.5 * (image[:, 2:] - image[:, :-2])
    grad_v[1:-1] = 0.5 * (image[2:] - image[:-2])
    su, sv = rng.uniform(1.0, W - 2.0, 500), rng.uniform(1.0, H - 2.0, 500)
    points = backproject(np.ones(500), K, su, sv)  # seen at (su, sv) by the reference camera

    def gradients(image):
        points_i, gu, gv = (np.empty((500, 3)) for _ in range(3))
        warp_gradients(points, np.eye(4), K, image, points_i, gu, gv)
        return gu, gv

    gu, gv = gradients(image)
    np.testing.assert_allclose(gu, sample_bilinear(grad_u, su, sv), rtol=0, atol=1e-12)
    np.testing.assert_allclose(gv, sample_bilinear(grad_v, su, sv), rtol=0, atol=1e-12)
    gu32, gv32 = gradients(image.astype(np.float32))
    rounding = np.finfo(np.float32).eps * np.abs(image).max()  # of the image's values
    np.testing.assert_allclose(gu32, gu, rtol=0, atol=rounding)
    np.testing.assert_allclose(gv32, gv, rtol=0, atol=rounding)


def test_warp_with_identity_and_occlusion_test():
    z = bump_depth()
    P = backproject(z, K).reshape(-1, 3)
    _, u, v, Z = warp(P, np.eye(4), K)
    uu, vv = pixel_grid(*SIZE)
    np.testing.assert_allclose(u, uu.ravel(), atol=1e-9)
    np.testing.assert_allclose(v, vv.ravel(), atol=1e-9)
    # a fronto-parallel occluder 5 cm closer covering the left half hides those pixels
    z2 = z.copy()
    z2[:, :32] = 0.5
    occluder = backproject(z2, K)[:, :32].reshape(-1, 3)
    both = np.concatenate([P, occluder])
    T = se3.exp([0.02, 0, 0, 0, 0, 0])
    _, u, v, Z = warp(both, T, K)
    vis = visible(u, v, Z, SIZE)[: P.shape[0]].reshape(SIZE)
    # points behind the occluder in the warped view are hidden, the right part of the bump is seen
    assert not vis[:, 2:30].any()  # column 0-1 land left of where the occluder lands
    assert vis[5:-5, 40:-8].all()
    # out of view: a camera moved right sees the left part leave the image
    _, u, v, Z = warp(P, se3.exp([-0.2, 0, 0, 0, 0, 0]), K)
    assert not visible(u, v, Z, SIZE).reshape(SIZE)[:, :5].any()
    # a sensor measuring something nearer than the point hides it
    sensor = np.full((12, 16), 0.3)
    Kd = scale_intrinsics(K, 0.25)
    _, u, v, Z = warp(P, np.eye(4), K)
    su, sv = Kd[0, 0] * P[:, 0] / P[:, 2] + Kd[0, 2], Kd[1, 1] * P[:, 1] / P[:, 2] + Kd[1, 2]
    assert not visible(u, v, Z, SIZE, sensor_depth=sensor, sensor_uv=(su, sv)).any()


def _visible_by_arrays(u, v, Z, size, rel_tol, sensor_depth, sensor_uv, frame_mask, zbuffer):
    """The occlusion test of ``visible`` written with NumPy arrays (its form before the compiled
    pass): the reference the compiled pass must equal bit for bit."""
    H, W = size
    with np.errstate(invalid="ignore"):
        ok = (Z > 1e-6) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
    iu = np.rint(np.where(ok, u, 0)).astype(np.int64)
    iv = np.rint(np.where(ok, v, 0)).astype(np.int64)
    tol = rel_tol * np.abs(Z)
    if zbuffer:
        zbuf = np.full(H * W, np.inf)
        np.minimum.at(zbuf, (iv * W + iu)[ok], Z[ok])
        ok &= Z <= zbuf[iv * W + iu] + tol
    if sensor_depth is not None:
        h, w = sensor_depth.shape
        with np.errstate(invalid="ignore"):
            su = np.clip(np.rint(np.where(ok, sensor_uv[0], 0)), 0, w - 1).astype(np.int64)
            sv = np.clip(np.rint(np.where(ok, sensor_uv[1], 0)), 0, h - 1).astype(np.int64)
        d = sensor_depth[sv, su]
        ok &= (d <= 0) | (Z <= d + tol)
    if frame_mask is not None:
        ok &= frame_mask[iv, iu]
    return ok


@pytest.mark.parametrize("zbuffer", [True, False])
def test_visible_is_the_array_formula_bit_for_bit(zbuffer):
    """The compiled occlusion test gives the mask of the NumPy formula on 200 000 random points:
    outside the image and behind the camera, NaN depths, pixel ties (x.5: rint rounds half to even),
    many points a pixel (the z-buffer), with and without a sensor depth and a frame mask."""
    rng = np.random.default_rng(0)
    H, W, N = 60, 80, 200_000
    u, v, Z = rng.uniform(-5, W + 5, N), rng.uniform(-5, H + 5, N), rng.uniform(-0.1, 1.0, N)
    u[::97], Z[::1001] = np.round(u[::97]) + 0.5, np.nan
    sensor = rng.uniform(-0.1, 1.0, (12, 16)).astype(np.float32)
    sensor_uv = (u / 5 + rng.normal(0, 2, N), v / 5 + rng.normal(0, 2, N))
    mask = rng.uniform(size=(H, W)) > 0.3
    for depth, uv, frame_mask in ((None, None, None), (sensor, sensor_uv, None), (sensor, sensor_uv, mask),
                                  (None, None, mask)):
        expected = _visible_by_arrays(u, v, Z, (H, W), 0.02, depth, uv, frame_mask, zbuffer)
        found = visible(u, v, Z, (H, W), rel_tol=0.02, sensor_depth=depth, sensor_uv=uv, frame_mask=frame_mask,
                        zbuffer=zbuffer)
        assert found.dtype == bool and 1000 < found.sum() < 0.9 * N
        np.testing.assert_array_equal(found, expected)


def test_pose_jacobian_matches_finite_differences():
    problem, est = make_problem()
    P = problem.points(est.z)
    keep = problem.sample(1, est.poses[1], P).usable
    J = pose_jacobian(problem.warped_gradients(1, est.poses[1], P), K)
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        plus = problem.sample(1, se3.exp(d) @ est.poses[1], P).color
        minus = problem.sample(1, se3.exp(-d) @ est.poses[1], P).color
        fd = (plus - minus) / (2 * h)
        # bilinear sampling is piecewise linear: compare against central-difference gradients
        err = np.abs(fd[keep] - J[keep, :, k])
        scale = np.abs(fd[keep]).mean()
        assert np.median(err) < 0.05 * scale


@pytest.mark.parametrize("light", ["sh", "led"])
def test_pose_system_on_the_host_equals_the_array_formula(light):
    """pose_system's compiled pass (kernels.pose_sums) against the array formula it replaced on
    the host (pose_jacobian, minus albedo x the LED's shading Jacobian, Cauchy weights, wJ^T J and
    wJ^T r): the same H and g to 1e-12 of their largest entries (another summation order)."""
    problem, est = make_problem(n_frames=2)
    if light == "led":
        problem = LevelProblem(problem.level, problem.tau, problem.lam, LEDLight(np.array([0.03, -0.02, 0.0])))
        est.lights = np.array([[0.2, 0.4], [0.1, 0.35]])
    P = problem.points(est.z)
    normals = problem.normals(est.z)[0]
    pose = est.poses[1]
    sample = problem.sample(1, pose, P)
    H, g = pose_system(problem, est, 1, pose, sample, P, normals)
    use, model = sample.usable, problem.light_model(est)
    points = P[use]
    shading = model.basis(normals[use], points, pose) @ est.lights[1]
    r = sample.color[use] - est.albedo[use] * shading[:, None]
    J = pose_jacobian(problem.warped_gradients(1, pose, points), K)
    dshading = model.shading_jacobian(est.lights[1], normals[use], points, pose)
    assert (dshading is None) == (light == "sh")
    if dshading is not None:
        J -= est.albedo[use][:, :, None] * dshading[:, None, :]
    J = J.reshape(-1, 6)
    wJ = J * cauchy_weights(r, problem.lam).reshape(-1, 1)
    expected_H, expected_g = wJ.T @ J, wJ.T @ r.reshape(-1)
    assert use.sum() > 100
    np.testing.assert_allclose(H, expected_H, rtol=0, atol=1e-12 * np.abs(expected_H).max())
    np.testing.assert_allclose(g, expected_g, rtol=0, atol=1e-12 * np.abs(expected_g).max())


def test_depth_system_gradient_matches_finite_differences_of_the_frozen_energy():
    """-rhs of the paper's depth step (no parallax, no twists, albedo held) equals the gradient of
    the energy with the warp and dA frozen at z."""
    problem, est = make_problem()
    ev = problem.evaluate(est)
    system = joint_system(problem, est, ev, parallax=False, twists=False, project_albedo=False)
    grad = -system.rhs_z
    g = problem.level.grid
    color, usable, dA = ev.color, ev.usable, ev.dA

    def frozen_energy(z):
        n_tilde = unnormalised_normals(g, z, K)
        e = problem.prior_energy(z)
        for i in range(problem.n_frames):
            s = est.lights[i, 0] + n_tilde @ est.lights[i, 1:] / dA
            r = np.where(usable[i][:, None], color[i] - est.albedo * s[:, None], 0)
            e += cauchy(r, problem.lam).sum()
        return e

    rng = np.random.default_rng(3)
    assert_gradient_at_random_pixels(frozen_energy, grad, est.z, rng)
    assert frozen_energy(est.z) == pytest.approx(ev.energy, rel=1e-7)  # solver: float32 logarithms
    # the system is symmetric positive definite
    M = system.matrix
    assert abs(M - M.T).max() < 1e-9 * abs(M).max()
    x = rng.normal(size=g.size)
    assert x @ (M @ x) > 0


def test_depth_envelope_bounds_each_pixel_by_the_sensor_depths_around_it():
    """A 4x4 depth map at SF 2 with a 0.1 m step between columns 1 and 2: colour pixels over depth
    column 0 see only the near side's neighbourhood (0.5 m), those over columns 1-2 both sides,
    all widened by the relative margin; a missing depth pixel takes its nearest neighbour's."""
    from o3d_mvps.solver.pyramid import depth_envelope

    z0 = np.array([[0.5, 0.5, 0.6, 0.6]] * 4)
    z0[3, 3] = 0.0
    lower, upper = depth_envelope(z0, (8, 8), margin=0.02)
    assert lower.shape == upper.shape == (8, 8)
    np.testing.assert_allclose(upper[:, :2], 0.5 * 1.02)  # over depth column 0: its neighbours are all 0.5 m
    np.testing.assert_allclose(lower[:, :2], 0.5 * 0.98)
    np.testing.assert_allclose(upper[:, 2:6], 0.6 * 1.02)  # columns 1 and 2 straddle the step
    np.testing.assert_allclose(lower[:, 2:6], 0.5 * 0.98)
    np.testing.assert_allclose(lower[:, 6:], 0.6 * 0.98)  # the hole at (3, 3) is filled with 0.6, not 0
    # a coarser level (one pixel per 2x2 depth pixels) widens the window to cover its footprint
    lower2, upper2 = depth_envelope(z0, (2, 2), margin=0.0)
    np.testing.assert_allclose(lower2, 0.5)
    np.testing.assert_allclose(upper2, 0.6)


def test_block_average_and_valid_resampling_agree_on_full_blocks():
    from o3d_mvps.model.resampling import block_average, resample_valid

    rng = np.random.default_rng(1)
    depth = rng.uniform(0.5, 0.7, size=(8, 12))
    depth[0, 0] = 0.0  # one missing pixel in the first 4 x 4 block
    blocks = depth.reshape(2, 4, 3, 4).mean(axis=(1, 3))
    np.testing.assert_allclose(block_average(depth, 4), blocks, rtol=1e-12)
    strict, ok_strict = resample_valid(depth, depth > 0, (2, 3), min_valid_fraction=1.0)
    lenient, ok_lenient = resample_valid(depth, depth > 0, (2, 3), min_valid_fraction=1e-6)
    assert not ok_strict[0, 0] and strict[0, 0] == 0.0 and ok_strict.sum() == 5  # a sensor drops mixed blocks
    np.testing.assert_allclose(strict[ok_strict], blocks[ok_strict], rtol=1e-12)
    assert ok_lenient.all()
    np.testing.assert_allclose(lenient[0, 0], depth[:4, :4].sum() / 15, rtol=1e-12)  # mean of the 15 valid pixels


def test_full_blocks_stay_valid_at_a_ratio_that_is_not_a_whole_number():
    # a 2 MP capture's depth (1709x1139 colour / 4) onto the pose checks' 80-px grid: cv2 weighs such
    # areas in float32, and the strict test once kept 2 % of a fully valid map (true poses refused)
    from o3d_mvps.model.resampling import resample_valid

    depth = np.full((284, 427), 0.25)
    for size in [(47, 71), (94, 142), (71, 106)]:
        values, ok = resample_valid(depth, depth > 0, size, min_valid_fraction=1.0)
        assert ok.all() and np.allclose(values, 0.25, rtol=1e-6)
    depth[100, 200] = 0.0  # one missing pixel still drops the blocks it falls in
    _, ok = resample_valid(depth, depth > 0, (47, 71), min_valid_fraction=1.0)
    assert 1 <= (~ok).sum() <= 4 and not ok[100 * 47 // 284, 200 * 71 // 427]


def test_repeat_pixels_is_undone_by_block_averaging():
    from o3d_mvps.model.resampling import block_average, repeat_pixels

    mask = np.random.default_rng(2).random((6, 9)) > 0.5
    big = repeat_pixels(mask, 4)
    assert big.shape == (24, 36) and big.dtype == bool and big[13, 22] == mask[3, 5]
    np.testing.assert_array_equal(block_average(big.astype(float), 4), mask.astype(float))


def test_fill_nearest_valid_copies_the_nearest_valid_pixel():
    from o3d_mvps.model.resampling import fill_nearest_valid

    image = np.zeros((5, 7, 2))
    image[1, 1], image[3, 6] = (1.0, 2.0), (3.0, 4.0)
    filled = fill_nearest_valid(image, image[..., 0] > 0)
    np.testing.assert_array_equal(filled[0, 0], (1.0, 2.0))
    np.testing.assert_array_equal(filled[4, 5], (3.0, 4.0))
    np.testing.assert_array_equal(fill_nearest_valid(image, np.zeros((5, 7), bool)), image)  # nothing to copy from


def test_scale_factor_rule_of_native_and_registered_depth():
    from o3d_mvps.errors import CaptureError
    from o3d_mvps.model.sensor import check_depth_unit, choose_scale_factor

    assert choose_scale_factor((720, 1280), (480, 848)) == 2   # RealSense: depth registered onto 640x360
    assert choose_scale_factor((720, 1280), (360, 640)) == 2
    assert choose_scale_factor((240, 320), (240, 320)) == 1
    assert choose_scale_factor((240, 320), (240, 320), 4, exact=True) == 4  # colour-resolution depth, averaged
    with pytest.raises(CaptureError, match="SF 4 is the nearest.*register_depth"):
        choose_scale_factor((240, 320), (60, 79), exact=True)
    with pytest.raises(CaptureError, match="not divisible by scale_factor 7"):
        choose_scale_factor((240, 320), (60, 80), 7)
    check_depth_unit(np.array([0.0, 0.6, 0.61]), "frame 0", "fix it")
    with pytest.raises(CaptureError, match="frame 0: median depth 605 m.*fix it"):
        check_depth_unit(np.array([0.0, 600.0, 610.0]), "frame 0", "fix it")


def test_smoothness_prior_is_zero_on_planes_and_its_gradient_matches_finite_differences():
    from o3d_mvps.model.normals import masked_grid
    from o3d_mvps.solver.pyramid import depth_prior, second_differences

    rng = np.random.default_rng(0)
    mask = np.zeros((24, 32), bool)
    mask[3:21, 4:30] = True
    mask[10:14, 10:13] = False  # a hole: no stencil reaches across it
    grid = masked_grid(mask)
    S = second_differences(grid)
    plane = 0.6 + 0.002 * grid.u - 0.001 * grid.v
    np.testing.assert_allclose(S @ plane, 0.0, atol=1e-12)
    assert S.shape[0] > 0 and np.all(np.abs(S).sum(axis=1) == 4)  # 1, -2, 1 on three masked pixels
    # the forward scheme's grid (normals from forward differences) has the same rows: it once had
    # none (rows were picked by the central scheme's 1/2 weights), so its smoothness did nothing
    assert (second_differences(masked_grid(mask, "forward")) != S).nnz == 0
    from o3d_mvps.solver.smoothness import grid_mode_rows
    modes = grid_mode_rows(grid, 4.0)
    assert modes.shape[0] > 0 and (grid_mode_rows(masked_grid(mask, "forward"), 4.0) != modes).nnz == 0
    prior = depth_prior(grid, rng.uniform(0.55, 0.65, (6, 8)), 4.0)
    prior.S = S
    z = plane + 0.001 * rng.normal(size=grid.size)
    hessian, rhs = prior.normal_equations(z, 3.0, 5.0)
    step = 1e-6 * rng.normal(size=grid.size)
    change = prior.energy(z + step, 3.0, 5.0) - prior.energy(z - step, 3.0, 5.0)
    assert change == pytest.approx(-2 * rhs @ step, rel=1e-6)  # rhs is minus the gradient
    np.testing.assert_allclose(hessian @ step, -(prior.normal_equations(z + step, 3.0, 5.0)[1] - rhs), rtol=1e-6, atol=1e-12)


def test_slope_weights_follow_the_metric_slope_of_the_sensor_surface():
    """On a plane the weights are (1 + tan^2 theta)^(-3/4) = cos^1.5 theta, theta the plane's tilt
    from fronto-parallel: 1 facing the camera, 0.35 at 60 degrees (the sensor's 1 mm steps,
    blurred away, do not count as slope)."""
    from o3d_mvps.model.normals import masked_grid
    from o3d_mvps.solver.smoothness import second_differences, slope_weights

    K_level = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    grid = masked_grid(np.ones((48, 64), bool))
    S = second_differences(grid)
    inner = (grid.u[np.asarray(abs(S).argmax(axis=1)).ravel()] - 32) ** 2 < 16**2  # away from the blur's edge
    for tilt_deg in (0.0, 60.0):
        # z(x) = 0.6 + tan(tilt) x on the ray through (u, v): z = 0.6 / (1 - tan(tilt) (u - cx) / f)
        u = np.arange(16) * 4 + 1.5  # a 16 x 12 depth image, SF 4
        z_row = 0.6 / (1 - np.tan(np.radians(tilt_deg)) * (u - 32) / 100)
        z0 = np.round(np.tile(z_row, (12, 1)) * 1000) / 1000  # 1 mm steps
        w = slope_weights(grid, S, z0, K_level, 4.0)
        expected = np.cos(np.radians(tilt_deg)) ** 1.5
        assert np.median(w[inner]) == pytest.approx(expected, rel=0.05), tilt_deg


def test_nan_median_equals_numpys_without_its_warning():
    """model.robust.nan_median: np.nanmedian over the first axis bit for bit (odd and even counts
    of measured values, one, none: NaN), a 3-d stack too, and no RuntimeWarning for empty slices."""
    import warnings

    from o3d_mvps.model.robust import nan_median

    rng = np.random.default_rng(3)
    for shape in ((20, 5000), (2, 300), (1, 40), (6, 30, 20)):
        values = rng.normal(size=shape) * rng.choice([1e-3, 1.0, 1e3], size=shape)
        values[rng.random(shape) < 0.4] = np.nan
        values[:, :2] = np.nan
        values[1:, 2] = np.nan  # one measured value
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            expected = np.nanmedian(values, axis=0)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            np.testing.assert_array_equal(nan_median(values), expected)
        assert np.isnan(nan_median(values)[:2]).all()


def test_robust_scale_is_the_standard_deviation_of_gaussian_residuals_despite_outliers():
    from o3d_mvps.model.robust import MIN_SCALE, robust_scale

    rng = np.random.default_rng(3)
    residual = rng.normal(0.0, 0.01, (4, 50000, 3))
    residual[:, :5000] = 0.5  # 10 % outliers (an albedo edge, a specularity)
    usable = np.ones((4, 50000), bool)
    usable[3] = False
    assert robust_scale(residual, usable) == pytest.approx(0.01 * 1.13, rel=0.03)  # MAD of a 10 %-contaminated normal
    assert robust_scale(residual, usable, max_samples=1000) == pytest.approx(0.0113, rel=0.1)
    assert robust_scale(np.zeros((2, 10, 3)), np.ones((2, 10), bool)) == MIN_SCALE
    assert robust_scale(residual, np.zeros((4, 50000), bool)) == MIN_SCALE


def test_auto_smoothness_grows_with_the_sensor_noise_and_with_finer_pixels():
    """sensor_roughness measures the noise of a tilted plane's depth (2 mm rms: 2.0 mm within 5 %)
    inside the mask only (the table outside is rougher and ignored); a constant depth gives the
    floor, a 1 mm unit's rounding of a tilted plane 0.6 mm. mu~ scales with the noise's variance
    and the footprint's fourth power, and is at least tau~ x 24."""
    from o3d_mvps.solver.smoothness import MIN_ROUGHNESS, auto_smoothness, sensor_roughness

    rng = np.random.default_rng(5)
    v, u = np.mgrid[0:120, 0:160]
    plane = 0.6 + 0.0004 * u - 0.0002 * v  # metres
    mask = np.zeros((480, 640), bool)
    mask[40:440, 40:600] = True
    noisy = plane + rng.normal(0.0, 0.002, plane.shape)
    noisy[:10] += rng.normal(0.0, 0.05, (10, 160))  # a rough table, outside the mask
    assert sensor_roughness(noisy, mask, 4) == pytest.approx(0.002, rel=0.05)
    assert sensor_roughness(np.full(plane.shape, 0.6), mask, 4) == MIN_ROUGHNESS
    # 1 mm rounding of a tilted plane: second differences of -1, 0, 1 mm read as 0.6 mm
    assert sensor_roughness(np.round(plane, 3), mask, 4) == pytest.approx(1.4826e-3 / np.sqrt(6), rel=1e-6)
    assert sensor_roughness(noisy, np.zeros_like(mask), 4) == MIN_ROUGHNESS  # nothing inside: the floor
    K_colour = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    mu = auto_smoothness(10.0, noisy, mask, 4, K_colour)
    footprint = np.median(noisy[10:110, 10:150]) / 600.0
    assert mu == pytest.approx(10.0 * 40.0 * (sensor_roughness(noisy, mask, 4) / 1e-3) ** 2 * (1e-3 / footprint) ** 4,
                               rel=0.01)
    doubled = plane + 2 * (noisy - plane)
    assert auto_smoothness(10.0, doubled, mask, 4, K_colour) == pytest.approx(4 * mu, rel=0.1)
    assert auto_smoothness(10.0, noisy, mask, 4, K_colour * [[2], [2], [1]]) == pytest.approx(16 * mu, rel=1e-9)
    assert auto_smoothness(10.0, np.full(plane.shape, 0.6), mask, 4, K_colour) == 240.0  # the stereo's floor


def test_a_float32_residual_problem_keeps_its_residuals_in_float32():
    """residual_dtype (float32 in the solver, CPU and CUDA) is what an evaluation stores its residuals and
    shading in, and the energy moves only by float32 rounding of the residuals (relative 1e-6;
    the energy's logarithms are float32 either way)."""
    from o3d_mvps.solver.problem import LevelProblem

    problem, est = make_problem()
    single = LevelProblem(problem.level, problem.tau, problem.lam, residual_dtype=np.float32)
    ev64, ev32 = problem.evaluate(est), single.evaluate(est)
    assert ev64.residual.dtype == np.float64 and ev32.residual.dtype == ev32.shading.dtype == np.float32
    np.testing.assert_allclose(ev32.residual, ev64.residual, rtol=0, atol=1e-6 * np.abs(ev64.residual).max())
    assert ev32.energy == pytest.approx(ev64.energy, rel=1e-6)
    assert single.reevaluate(est, ev32, overwrite=True).residual.dtype == np.float32
