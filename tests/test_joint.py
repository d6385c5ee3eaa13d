"""Tests of the Gauss-Newton normal equations (o3d_mvps.solver.normal_equations), with and
without the albedo projected out, and of the joint pose-depth step (o3d_mvps.solver.joint).

The scene is exact: test_model's bump surface with a smooth albedo texture fixed to the surface
and per-frame SH lights, ray cast into three cameras, so the true depth, albedo, lights and poses
reproduce every image up to bilinear interpolation and finite-difference normals. Kicking the
non-reference poses off the truth makes the residuals systematic (not noise), so sums over many
pixels (gradients, directional derivatives, Gauss-Newton products) can be compared with finite
differences to a few percent. Exact agreement is not expected: bilinear sampling is piecewise
linear while the analytic Jacobians use central-difference image gradients.
"""

import dataclasses
from functools import partial

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp

# pytest puts tests/ (no __init__.py) on sys.path, so the model tests' helpers import directly
from helpers import SIZE, K, bump_depth, make_problem
from threadpoolctl import threadpool_limits

from o3d_mvps import RefineOptions
from o3d_mvps.metrics import reprojection_error_px
from o3d_mvps.model import se3
from o3d_mvps.model.camera import pixel_grid
from o3d_mvps.model.normals import unnormalised_normals
from o3d_mvps.model.robust import cauchy, cauchy_weights
from o3d_mvps.solver.joint import update_pose_depth
from o3d_mvps.solver.linear import DAMPING, levenberg_damped
from o3d_mvps.solver.normal_equations import joint_system, residual_jacobians
from o3d_mvps.solver.problem import Estimate, LevelProblem

LIGHTS = np.array([[0.2, 0.1, -0.1, -1.0], [0.1, -0.2, 0.05, -0.9], [0.15, 0.05, 0.2, -0.95]])


def orbit(degrees, shift):
    """A pose (reference -> camera) rotated by ``degrees`` (3,) about the bump's centre
    (0, 0, 0.6) m and shifted by ``shift`` (3,) m."""
    R = se3.exp(np.concatenate([np.zeros(3), np.radians(degrees)]))[:3, :3]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.array([0, 0, 0.6]) - R @ [0, 0, 0.6] + shift
    return T


POSES = np.stack([np.eye(4), orbit([2, 10, 1], [0.01, -0.005, 0.002]), orbit([-8, -6, 0], [-0.005, 0.004, -0.01])])
# left-multiplied kicks of frames 1, 2 off the truth: ~2 mm and ~0.3 deg, ~0.7 px in the images
KICKS = np.array([[0.0] * 6, [0.002, -0.001, 0.001, 0.004, -0.003, 0.002],
                  [-0.001, 0.002, -0.0015, -0.002, 0.004, -0.003]])
OPTIONS = RefineOptions()


# ---------------------------------------------------------------------------------------------
# the exact scene


def surface_depth(x, y):
    """Depth of the bump surface (test_model.bump_depth) along the normalised ray (x, y, 1)."""
    return 0.6 - 0.04 * np.exp(-(x**2 + y**2) / 0.02)


def albedo_at(X):
    """Smooth RGB albedo (..., 3) of surface points X (..., 3): 11-16 cm wavelengths, ~25 px."""
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    return np.stack([0.5 + 0.2 * np.sin(x / 0.02) * np.cos(y / 0.025),
                     0.45 + 0.2 * np.cos(x / 0.018 + y / 0.03 + 20 * z),
                     0.5 + 0.2 * np.sin((x - y) / 0.022)], -1)


def normal_at(X):
    """Unit normals (..., 3) of the bump surface at its points X, facing the reference camera."""
    x, y, Z = X[..., 0] / X[..., 2], X[..., 1] / X[..., 2], X[..., 2]
    bump = 0.04 * np.exp(-(x**2 + y**2) / 0.02)
    fx, fy = bump * x / 0.01, bump * y / 0.01  # d(depth)/dx, d(depth)/dy
    # -grad of Z - f(X / Z, Y / Z)
    n = np.stack([fx / Z, fy / Z, -1 - (fx * x + fy * y) / Z], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def render(pose, light):
    """(H, W, 3) image of the scene seen with ``pose`` (reference -> camera) under SH ``light``."""
    u, v = pixel_grid(*SIZE)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ pose[:3, :3]
    centre = -pose[:3, :3].T @ pose[:3, 3]
    s = (0.6 - centre[2]) / rays[..., 2]
    for _ in range(30):  # fixed point on the ray parameter: the bump is gentle
        X = centre + s[..., None] * rays
        s = (surface_depth(X[..., 0] / X[..., 2], X[..., 1] / X[..., 2]) - centre[2]) / rays[..., 2]
    X = centre + s[..., None] * rays
    return albedo_at(X) * (light[0] + normal_at(X) @ light[1:])[..., None]


@pytest.fixture(autouse=True)
def one_blas_thread():
    """Run like refine() does: on a loaded 2-core machine OpenBLAS's threads made the dense
    solves here several times slower."""
    with threadpool_limits(1, user_api="blas"):
        yield


@pytest.fixture(scope="module")
def level():
    """make_problem's 3-frame level (grid, K, depth prior at the true bump) with rendered images."""
    images = [render(T, light) for T, light in zip(POSES, LIGHTS)]
    return dataclasses.replace(make_problem(3)[0].level, images=images)


@pytest.fixture
def problem(level):
    """A fresh problem per test."""
    return LevelProblem(level, 1.0, 0.04)


def true_estimate(problem):
    """The scene's exact depth, albedo, lights and poses."""
    z = problem.level.grid.gather(bump_depth())
    return Estimate(z, albedo_at(problem.points(z)), LIGHTS.copy(), POSES.copy())


def kicked_estimate(problem):
    """The truth with frames 1 and 2 kicked by KICKS and the depth bent by up to 0.5 mm (so the
    prior sees it too): its evaluation's residuals are systematic."""
    est = true_estimate(problem)
    est.poses = np.stack([se3.exp(kick) @ T for kick, T in zip(KICKS, POSES)])
    est.z = est.z + 0.5 * smooth_directions(problem.level.grid)[4]
    return est


# ---------------------------------------------------------------------------------------------
# the model the joint step linearises, and finite differences


def frozen_residuals(problem, est, ev, z, poses=None, live_warp=True):
    """Residuals (n, N, 3) at depth z with dA, the (SH) light field and the usable masks frozen
    at ``ev``; the warped colours are recomputed at points(z) under ``poses`` (default est's)
    unless ``live_warp`` is False."""
    poses = est.poses if poses is None else poses
    n_tilde = unnormalised_normals(problem.level.grid, z, K)
    points = problem.points(z)
    r = np.empty(ev.residual.shape)
    for i in range(problem.n_frames):
        color = problem.sample(i, poses[i], points).color if live_warp else ev.color[i]
        shading = est.lights[i, 0] + n_tilde @ est.lights[i, 1:] / ev.dA
        r[i] = (color - est.albedo * shading[:, None]) * ev.usable[i][:, None]
    return r


def kicked_frame_residuals(problem, est, ev, i, d):
    """Frame i's residuals (N, 3) at est.z with its pose left-updated by exp(d)."""
    return frozen_residuals(problem, est, ev, est.z, kicked_poses(est.poses, i, d))[i]


def frozen_energy(problem, est, ev, z, live_warp=True):
    """The energy the depth part of the joint step linearises: frozen dA and light, warp live."""
    return cauchy(frozen_residuals(problem, est, ev, z, live_warp=live_warp), problem.lam).sum() + \
        problem.prior_energy(z)


def central_difference(f, x, d, h):
    """(f(x + h d) - f(x - h d)) / 2h, for scalars or arrays."""
    return (f(x + h * d) - f(x - h * d)) / (2 * h)


def twist_differences(f, h=1e-6):
    """Central differences (6, ...) of f(d) at d = 0 along the six unit twists."""
    return np.array([central_difference(f, np.zeros(6), e, h) for e in np.eye(6)])


def kicked_poses(poses, i, d):
    """``poses`` with frame i left-updated by exp(d)."""
    out = poses.copy()
    out[i] = se3.exp(d) @ poses[i]
    return out


def smooth_directions(grid):
    """(9, N) low-frequency depth directions: products of cosines of the pixel coordinates
    (half to one period across the grid), 1 mm amplitude."""
    x = (grid.u - grid.u.min()) / np.ptp(grid.u)
    y = (grid.v - grid.v.min()) / np.ptp(grid.v)
    return np.array([1e-3 * np.cos(np.pi * a * x + 0.3) * np.cos(np.pi * b * y + 0.7)
                     for a in range(3) for b in range(3)])


def relative_error(actual, expected):
    return np.linalg.norm(np.ravel(actual) - np.ravel(expected)) / np.linalg.norm(expected)


# ---------------------------------------------------------------------------------------------
# joint_system: its right-hand side is minus the gradient, its matrix the Gauss-Newton matrix


def test_twist_rhs_is_minus_the_gradient_of_the_energy(problem):
    """rhs_xi of each refined frame equals minus the central-difference gradient of the true
    energy (problem.evaluate) in that frame's twist (left update exp(d) T_i)."""
    est = kicked_estimate(problem)
    ev = problem.evaluate(est)
    system = joint_system(problem, est, ev, project_albedo=False)
    assert system.frames == [1, 2] and system.rhs_xi.shape == (12,)

    def energy(i, d):
        return problem.evaluate(dataclasses.replace(est, poses=kicked_poses(est.poses, i, d))).energy

    for i, rhs in zip(system.frames, system.rhs_xi.reshape(-1, 6)):
        fd = twist_differences(partial(energy, i))
        assert relative_error(-rhs, fd) < 0.03, (i, fd, -rhs)


def test_depth_rhs_is_minus_the_gradient_of_the_frozen_energy(problem):
    """rhs_z equals minus the gradient of the frozen-dA, frozen-light energy with the warp live
    (parallax included), along smooth directions; the frozen energy at z is the true energy.
    The warp's share is not negligible: freezing it too (the paper's depth step) misses by far.
    The prior's share is exact."""
    est = kicked_estimate(problem)
    ev = problem.evaluate(est)
    system = joint_system(problem, est, ev, project_albedo=False)
    # the solver squares float32 residuals (model.robust.cauchy_energy, ~1e-7 relative); the test's float64
    assert frozen_energy(problem, est, ev, est.z) == pytest.approx(ev.energy, rel=1e-7)

    directions = smooth_directions(problem.level.grid)
    fd, fd_no_warp = (np.array([central_difference(partial(frozen_energy, problem, est, ev, live_warp=live), est.z,
                                                   d, 1e-3) for d in directions]) for live in (True, False))
    assert relative_error(directions @ -system.rhs_z, fd) < 0.03
    assert relative_error(fd_no_warp, fd) > 0.2
    # the prior's share, exactly: against the same system without the prior
    prior = problem.level.prior
    no_prior = joint_system(LevelProblem(problem.level, 0.0, problem.lam), est, ev, project_albedo=False)
    prior_gradient = 2 * problem.tau * prior.D.T @ (prior.D @ est.z - prior.z0)
    np.testing.assert_allclose(no_prior.rhs_z - system.rhs_z, prior_gradient, rtol=1e-9,
                               atol=1e-9 * np.abs(prior_gradient).max())
    # and the warp-frozen derivative is what the paper's depth step's gradient gives (sanity of the yardstick)
    depth = joint_system(problem, est, ev, parallax=False, twists=False, project_albedo=False)
    assert relative_error(directions @ -depth.rhs_z, fd_no_warp) < 1e-5


def test_joint_matrix_is_the_gauss_newton_matrix_of_the_residuals(problem):
    """M, U and H are the Gauss-Newton products of the residuals' derivatives with the Cauchy
    weights w: d^T M d = sum w (J_z d)^2 + 2 tau |D d|^2, d^T U = sum w (J_z d) J_xi per frame,
    H = sum w J_xi J_xi^T. Exactly, from residual_jacobians' per-pixel J_xi and parallax g
    (checked through the gradients above) with the shading part of J_z d by differences of the
    frozen residuals (linear in z); and, independently, H and d^T M d against finite differences
    of the frozen residuals to a few percent.

    With the albedo projected out, each (pixel, channel)'s derivatives over the frames lose
    their W-weighted component along the albedo's column -s: the products lose
    (sum_i w s J a)(sum_i w s J b) / sum_i w s^2, and the gradient gains the matching term in
    s^T W r (zero where the albedo is already optimal)."""
    est = kicked_estimate(problem)
    est.albedo = est.albedo * (1 + 0.05 * np.cos(np.arange(est.z.size) / 7.0))[:, None]  # not optimal
    ev = problem.evaluate(est)
    system = joint_system(problem, est, ev, project_albedo=False)
    projected = joint_system(problem, est, ev)
    w = cauchy_weights(ev.residual, problem.lam) * ev.usable[..., None]
    s = ev.shading[..., None]  # (n, N, 1)
    d_s = (w * s * s).sum(0)  # (N, 3): s^T W s per pixel and channel
    sWr = (w * s * ev.residual).sum(0)
    D = problem.level.prior.D
    points = problem.points(est.z)
    J_xi, parallax = np.zeros((problem.n_frames, est.z.size, 3, 6)), np.zeros(ev.residual.shape)
    for i in range(problem.n_frames):
        use, J, g = residual_jacobians(problem, est, ev, i, points)
        assert not np.any(g[~use]) and (J is None or not np.any(J[~use]))
        parallax[i] = g
        if J is not None:
            J_xi[i] = J
    J_all = np.concatenate([J_xi[i] for i in system.frames], axis=-1)  # (N, 3, 12) frame i's columns
    sWJ = np.concatenate([(w[i] * s[i])[..., None] * J_xi[i] for i in system.frames], axis=-1)  # (N, 3, 12)
    H = scipy.linalg.block_diag(*[np.einsum("nc,ncj,nck->jk", w[i], J_xi[i], J_xi[i]) for i in system.frames])
    np.testing.assert_allclose(system.hessian, H, rtol=1e-9, atol=1e-9 * np.abs(H).max())
    H_projected = H - np.einsum("ncj,nck,nc->jk", sWJ, sWJ, 1 / d_s)
    np.testing.assert_allclose(projected.hessian, H_projected, rtol=1e-9, atol=1e-9 * np.abs(H).max())
    rhs_xi = -np.concatenate([np.einsum("nc,nc,ncj->j", w[i], ev.residual[i], J_xi[i]) for i in system.frames])
    np.testing.assert_allclose(system.rhs_xi, rhs_xi, rtol=1e-9, atol=1e-9 * np.abs(rhs_xi).max())
    np.testing.assert_allclose(projected.rhs_xi, rhs_xi + np.einsum("ncj,nc->j", sWJ, sWr / d_s), rtol=1e-9,
                               atol=1e-9 * np.abs(rhs_xi).max())
    assert J_all.shape[-1] == 12

    def curvature(Jd, d):
        return (w * Jd**2).sum() + 2 * problem.tau * np.sum((D @ d) ** 2)

    for d in smooth_directions(problem.level.grid)[[0, 4, 8]]:
        shading_part = central_difference(lambda z: frozen_residuals(problem, est, ev, z, live_warp=False),
                                          est.z, d, 1.0)
        Jd = shading_part + parallax * d[:, None]
        assert d @ (system.matrix @ d) == pytest.approx(curvature(Jd, d), rel=1e-9)
        coupling = np.concatenate([np.einsum("nc,nc,ncj->j", w[i], Jd[i], J_xi[i]) for i in system.frames])
        # U is stored in float32 (normal_equations.COUPLING_DTYPE): its entries are exact to 6e-8
        np.testing.assert_allclose(d @ system.coupling, coupling, rtol=1e-9, atol=1e-7 * np.abs(coupling).max())
        sWJd = (w * s * Jd).sum(0)  # (N, 3)
        assert d @ (projected.matrix @ d) == pytest.approx(curvature(Jd, d) - (sWJd**2 / d_s).sum(), rel=1e-9)
        np.testing.assert_allclose(d @ projected.coupling, coupling - np.einsum("nc,ncj->j", sWJd / d_s, sWJ),
                                   rtol=1e-9, atol=1e-7 * np.abs(coupling).max())
        assert d @ projected.rhs_z == pytest.approx(d @ system.rhs_z + (sWJd * sWr / d_s).sum(), rel=1e-9)
        fd = central_difference(lambda z: frozen_residuals(problem, est, ev, z), est.z, d, 1e-3)
        assert d @ (system.matrix @ d) == pytest.approx(curvature(fd, d), rel=0.03)
    for j, i in enumerate(system.frames):
        fd = twist_differences(partial(kicked_frame_residuals, problem, est, ev, i))  # (6, N, 3)
        block = system.hessian[6 * j:6 * j + 6, 6 * j:6 * j + 6]
        assert relative_error(block, np.einsum("nc,jnc,knc->jk", w[i], fd, fd)) < 0.05, i


@pytest.mark.parametrize("project_albedo", [False, True])
def test_schur_route_solves_the_full_system(problem, rng, project_albedo):
    """M is symmetric positive definite, the full matrix [[M, U], [U^T, H]] is SPD, and the
    Schur complement route (dense solve of S, then twists) gives the dense solution."""
    est = kicked_estimate(problem)
    system = joint_system(problem, est, problem.evaluate(est), project_albedo=project_albedo)
    M = system.matrix.toarray()
    N = M.shape[0]
    assert np.abs(M - M.T).max() < 1e-12 * np.abs(M).max()
    for x in rng.normal(size=(5, N)):
        assert x @ M @ x > 0
    H = system.hessian
    U = system.coupling
    assert U.shape == (N, 12) and H.shape == (12, 12) and np.abs(U).max() > 0
    full = np.block([[M, U], [U.T, H]])
    factor = scipy.linalg.cho_factor(full)  # raises unless SPD
    solution = scipy.linalg.cho_solve(factor, np.concatenate([system.rhs_z, system.rhs_xi]))

    S, rhs = system.schur_operator()
    S_dense = S @ np.eye(N)  # a block of columns, as well as the 1-D vectors CG applies it to
    np.testing.assert_allclose(S.matvec(np.eye(N)[0]), S_dense[:, 0])
    dz = np.linalg.solve(S_dense, rhs)
    xi = system.twists(dz)
    assert xi.shape == (2, 6)
    assert relative_error(dz, solution[:N]) < 1e-6
    assert relative_error(xi.ravel(), solution[N:]) < 1e-6


@pytest.mark.parametrize("project_albedo", [False, True])
def test_blocks_of_pixels_give_the_same_system(problem, project_albedo):
    """Assembled in blocks of reference pixels (97 and 1000 here, 32768 on real images), every
    part of the system is the one-block system to rounding: the sums over frames are per pixel,
    the sums over pixels (twist Grams, projection, coupling's stencil) add up across blocks."""
    est = kicked_estimate(problem)
    ev = problem.evaluate(est)
    whole = joint_system(problem, est, ev, project_albedo=project_albedo)
    assert problem.level.grid.size > 1000 and len(whole.frames) == 2
    for block_pixels in (97, 1000):
        blocked = joint_system(problem, est, ev, project_albedo=project_albedo, block_pixels=block_pixels)
        assert blocked.frames == whole.frames
        assert abs(blocked.matrix - whole.matrix).max() <= 1e-12 * abs(whole.matrix).max()
        for part in ("rhs_z", "coupling", "hessian", "rhs_xi"):
            expected = getattr(whole, part)
            # the coupling's float32 entries (COUPLING_DTYPE) may round differently in another order
            tolerance = 1e-6 if part == "coupling" else 1e-11
            np.testing.assert_allclose(getattr(blocked, part), expected, rtol=tolerance,
                                       atol=tolerance * np.abs(expected).max(), err_msg=part)


@pytest.mark.parametrize("parallax, project_albedo", [(True, True), (True, False), (False, True)])
def test_one_launch_per_block_gives_the_per_frame_system(problem, monkeypatch, parallax, project_albedo):
    """The host's assembly with every frame of a block in one kernel launch
    (kernels.accumulate_block, in parallel over pixel chunks) and with one launch per frame
    (kernels.accumulate_frame, taken when the images differ in type) give the same system, in one
    block and in blocks of 700 pixels: bit for bit with chunks of kernels.CHUNK pixels; with the
    default 1024-pixel chunks (2 on this level) the depth block, its right-hand side and the
    coupling still bit for bit (per-pixel sums, frames in order), the twist Grams and right-hand
    sides (summed per chunk) to 1e-13 (measured: 1e-16). One launch per block is what runs on
    more than one kernel thread."""
    from o3d_mvps.solver import kernels, normal_equations

    est = kicked_estimate(problem)
    ev = problem.evaluate(est)
    launches = {"block": 0, "frame": 0}
    for name, key in (("accumulate_block", "block"), ("accumulate_frame", "frame")):
        def counted(*args, _kernel=getattr(kernels, name), _key=key):
            launches[_key] += 1
            return _kernel(*args)
        monkeypatch.setattr(kernels, name, counted)
    N = problem.level.grid.size
    assert normal_equations.HOST_CHUNK_PIXELS < N <= kernels.CHUNK
    monkeypatch.setattr(normal_equations, "current_kernel_threads", lambda: 2)  # one launch per frame on one
    for chunk_pixels in (kernels.CHUNK, normal_equations.HOST_CHUNK_PIXELS):
        for block_pixels in (None, 700):
            launches.update(block=0, frame=0)
            with monkeypatch.context() as patch:
                patch.setattr(normal_equations, "HOST_CHUNK_PIXELS", chunk_pixels)
                one = joint_system(problem, est, ev, parallax=parallax, project_albedo=project_albedo,
                                   block_pixels=block_pixels)
            blocks = -(-N // (block_pixels or normal_equations.BLOCK_PIXELS))
            assert launches == {"block": blocks, "frame": 0}
            with monkeypatch.context() as patch:
                patch.setattr(normal_equations, "_same_types", lambda images: False)
                per_frame = joint_system(problem, est, ev, parallax=parallax, project_albedo=project_albedo,
                                         block_pixels=block_pixels)
            assert launches == {"block": blocks, "frame": blocks * problem.n_frames}
            assert one.frames == per_frame.frames == [1, 2]
            assert (one.matrix != per_frame.matrix).nnz == 0
            for part in ("rhs_z", "coupling", "hessian", "rhs_xi"):
                got, expected = getattr(one, part), getattr(per_frame, part)
                if chunk_pixels == kernels.CHUNK or part in ("rhs_z", "coupling"):
                    np.testing.assert_array_equal(got, expected, err_msg=part)
                else:
                    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-13 * np.abs(expected).max(),
                                               err_msg=part)
    monkeypatch.setattr(normal_equations, "current_kernel_threads", lambda: 1)
    launches.update(block=0, frame=0)
    joint_system(problem, est, ev, parallax=parallax, project_albedo=project_albedo)
    assert launches == {"block": 0, "frame": problem.n_frames}  # on one thread: a launch per frame


def test_the_projection_gram_on_a_helper_thread_gives_the_same_system(problem, monkeypatch):
    """On more than one kernel thread, half of each block's albedo-projection Gram runs on a
    helper thread beside the main thread's half; the halves and their sum are the same on one
    thread, so the system is the same bit for bit (a launch per frame both times, so that only
    the helper differs), in one block and in blocks of 700 pixels."""
    from concurrent.futures import ThreadPoolExecutor

    from o3d_mvps.solver import normal_equations

    est = kicked_estimate(problem)
    ev = problem.evaluate(est)
    submitted = []

    class Counted(ThreadPoolExecutor):
        def submit(self, fn, *args, **kwargs):
            submitted.append(fn)
            return super().submit(fn, *args, **kwargs)

    monkeypatch.setattr(normal_equations, "ThreadPoolExecutor", Counted)
    monkeypatch.setattr(normal_equations, "_same_types", lambda images: False)  # a launch per frame
    for block_pixels in (None, 700):
        systems = []
        for threads in (1, 2):
            monkeypatch.setattr(normal_equations, "current_kernel_threads", lambda threads=threads: threads)
            submitted.clear()
            systems.append(joint_system(problem, est, ev, block_pixels=block_pixels))
            blocks = -(-problem.level.grid.size // (block_pixels or normal_equations.BLOCK_PIXELS))
            assert len(submitted) == (blocks if threads > 1 else 0)
        one, two = systems
        assert (one.matrix != two.matrix).nnz == 0
        for part in ("rhs_z", "coupling", "hessian", "rhs_xi"):
            np.testing.assert_array_equal(getattr(one, part), getattr(two, part), err_msg=part)


@pytest.mark.parametrize("led", [False, True])
def test_the_blocks_share_one_scratch_buffer_and_read_nothing_left_in_it(level, monkeypatch, led):
    """The host's assembly hands every block the same scratch buffer (fresh arrays of more than
    glibc's mmap threshold were mapped and faulted in anew per block: 7000 page faults a 2 MP
    block); filled with NaN before each block, the system is the same bit for bit as with a
    fresh buffer per block (no block reads what the last left), in blocks of 700 pixels (the
    last one shorter), for the SH light and the LED (its fields and shading Jacobians written
    into the buffer)."""
    from o3d_mvps.solver import normal_equations
    from o3d_mvps.solver.lighting import LEDLight

    problem = LevelProblem(level, 1.0, 0.04, light=LEDLight(np.array([0.03, -0.02, 0.0])) if led else None)
    est = kicked_estimate(problem)
    if led:
        est.lights = np.tile([0.1, 0.05], (problem.n_frames, 1))
    ev = problem.evaluate(est)
    assemble, buffers = normal_equations._assemble_block, []

    def poisoned(*args, scratch=None, **kwargs):
        buffers.append(scratch)
        scratch.fill(np.nan)
        return assemble(*args, scratch=scratch, **kwargs)

    def fresh(*args, scratch=None, **kwargs):
        return assemble(*args, scratch=None, **kwargs)

    systems = []
    for wrapper in (poisoned, fresh):
        with monkeypatch.context() as patch:
            patch.setattr(normal_equations, "_assemble_block", wrapper)
            systems.append(joint_system(problem, est, ev, block_pixels=700))
    blocks = -(-problem.level.grid.size // 700)
    assert blocks >= 3 and len(buffers) == blocks and all(b is buffers[0] for b in buffers)
    one, other = systems
    assert one.frames == other.frames == [1, 2]
    assert (one.matrix != other.matrix).nnz == 0 and np.isfinite(one.matrix.data).all()
    for part in ("rhs_z", "coupling", "hessian", "rhs_xi"):
        assert np.isfinite(getattr(one, part)).all(), part
        np.testing.assert_array_equal(getattr(one, part), getattr(other, part), err_msg=part)


@pytest.mark.parametrize("led, project", [(True, True), (False, False)])
def test_accumulate_block_equals_accumulate_frame_in_turn_over_several_chunks(led, project):
    """kernels.accumulate_block (every frame in one launch, in parallel over pixel chunks) equals
    kernels.accumulate_frame called a frame at a time, bit for bit, on 2 pixel chunks and a bit
    of kernels.CHUNK pixels, and to rounding in the twist sums on 1000-pixel chunks: frame 0
    with its extra column and no Jacobian, frames in twist slots 1 and 0, one with the parallax
    only; with and without the LED's shading Jacobians and the albedo projection's e."""
    from o3d_mvps.solver import kernels

    rng = np.random.default_rng(4)
    N, m, n = 2 * kernels.CHUNK + 77, 2, 4
    f = lambda *shape: rng.random(shape)  # noqa: E731
    frame_slots = np.array([[0, -1], [1, 1], [1, 0], [1, -1]], dtype=np.int64)
    poses = np.stack([np.eye(4)] + [orbit(d, s) for d, s in (([2, 5, 1], [0.01, 0, 0]), ([-3, 2, 0], [0, 0.01, 0]),
                                                                ([1, -4, 2], [0, 0, 0.01]))])
    points = np.column_stack([(f(N, 2) - 0.5) * 0.2, 0.6 + 0.05 * f(N)])
    images = [f(SIZE[0], SIZE[1], 3).astype(np.float32) for _ in range(n)]
    r, shading, usable, q = f(n, N, 3) - 0.5, f(n, N), rng.random((n, N)) > 0.2, f(N, 3)
    alpha, beta, gamma, extra_c, albedo = f(n, N) - 0.5, f(n, N) - 0.5, f(n, N), f(N, 3) - 0.5, f(N, 3)
    dshading = f(n, N, 6) - 0.5 if led else np.zeros((n, 0, 6))
    chunks = kernels.chunk_count(N)
    assert chunks == 3
    start = [f(9, N), f(3, N, 3) if project else np.zeros((0, 1, 3)), f(3, m, 6, N),
             f(m, 6, N, 3) if project else np.zeros((0, 6, 1, 3)), np.zeros((m + 1, chunks, 6, 6)),
             np.zeros((m + 1, chunks, 6))]
    block, loop = [a.copy() for a in start], [a.copy() for a in start]
    kernels.accumulate_block(r, shading, usable, 1.0 / 0.04, q, alpha, beta, gamma, extra_c, points, poses, K,
                             tuple(images), dshading, albedo, frame_slots, True, *block, kernels.CHUNK)
    sums, e, rows, F, gram, rhs = loop
    for i, (with_jacobian, slot) in enumerate(frame_slots):
        kernels.accumulate_frame(r[i], shading[i], usable[i], 1.0 / 0.04, q, alpha[i], beta[i], gamma[i],
                                 extra_c if i == 0 else np.zeros((0, 3)), points, poses[i], K, images[i],
                                 dshading[i] if with_jacobian else np.zeros((0, 6)), albedo, bool(with_jacobian),
                                 True, sums, e, rows, F, int(slot), gram[slot], rhs[slot])
    for name, got, expected in zip(("sums", "e", "rows", "F"), block, loop):
        assert got.size == 0 or not np.array_equal(got, start[("sums", "e", "rows", "F").index(name)]), name
        np.testing.assert_array_equal(got, expected, err_msg=name)
    for name, k in (("gram", 4), ("rhs", 5)):  # the refined frames' slots (the last row: nobody's)
        assert np.abs(block[k][:m]).sum(axis=-1).min() > 0.0, name  # every slot and chunk filled
        np.testing.assert_array_equal(block[k][:m], loop[k][:m], err_msg=name)
    # in chunks of 1000 pixels (34): the per-pixel outputs bit for bit, the twist sums to rounding
    small = [a.copy() for a in start[:4]] + [np.zeros((m + 1, 34, 6, 6)), np.zeros((m + 1, 34, 6))]
    kernels.accumulate_block(r, shading, usable, 1.0 / 0.04, q, alpha, beta, gamma, extra_c, points, poses, K,
                             tuple(images), dshading, albedo, frame_slots, True, *small, 1000)
    for got, expected in zip(small[:4], loop[:4]):
        np.testing.assert_array_equal(got, expected)
    for k in (4, 5):
        expected = loop[k][:m].sum(axis=1)
        np.testing.assert_allclose(small[k][:m].sum(axis=1), expected, rtol=0, atol=1e-12 * np.abs(expected).max())


# ---------------------------------------------------------------------------------------------
# update_pose_depth


@pytest.mark.parametrize("project_albedo", [False, True])
def test_update_pose_depth_descends_and_recovers_kicked_poses(problem, project_albedo):
    """From the exact scene with frames 1 and 2 kicked (~0.7 px), the joint step strictly lowers
    the energy on its first call, never raises it after, keeps the reference pose, and its first
    step pulls the kicked poses back to under 3 % of their reprojection error."""
    est = kicked_estimate(problem)
    ev = problem.evaluate(est)
    points = problem.points(est.z)

    def reprojection_errors(poses):
        return np.array([reprojection_error_px(poses[i], POSES[i], points, K) for i in (1, 2)])

    before = reprojection_errors(est.poses)
    assert np.all(before > 0.5)
    energies, errors = [ev.energy], []
    for _ in range(3):
        est, ev, _ = update_pose_depth(problem, est, ev, rtol=OPTIONS.joint_cg_tolerance,
                                       maxiter=OPTIONS.cg_max_iterations, project_albedo=project_albedo)
        assert ev.energy == pytest.approx(problem.evaluate(est).energy, rel=1e-12)
        energies.append(ev.energy)
        errors.append(reprojection_errors(est.poses))
    assert energies[1] < 0.1 * energies[0]
    assert np.all(np.diff(energies) <= 0), energies
    np.testing.assert_array_equal(est.poses[0], np.eye(4))
    # the problem is nearly quadratic in the kick: one step removes ~99 % of it
    assert np.all(errors[0] < 0.03 * before) and np.all(errors[-1] <= 1.05 * errors[0]), (before, errors)


def test_a_levels_joint_steps_keep_the_first_steps_prolongations(problem, monkeypatch):
    """On a level of at most REUSE_HIERARCHY_MAX_PIXELS pixels the first joint step sets up its
    AMG hierarchy and the next steps make it over (linear.galerkin_hierarchy), its finest matrix
    let go between steps; their CG takes as many iterations (within REUSE_EXTRA_ITERATIONS) and
    the steps the same energies (to 1e-4; CG stops at rtol 1e-2, so not to rounding) as with a
    fresh set-up each step. Above that size no hierarchy is kept."""
    from o3d_mvps.solver import joint, linear

    made = []
    over = linear.galerkin_hierarchy
    monkeypatch.setattr(joint, "galerkin_hierarchy", lambda ml, m: made.append(m.shape) or over(ml, m))

    def steps(level_problem):
        est = kicked_estimate(level_problem)
        ev = level_problem.evaluate(est)
        rows = []
        for _ in range(3):
            est, ev, iterations = update_pose_depth(level_problem, est, ev, rtol=OPTIONS.joint_cg_tolerance,
                                                    maxiter=OPTIONS.cg_max_iterations)
            rows.append((ev.energy, iterations))
        return rows

    kept = steps(problem)
    assert len(made) == 2  # steps 2 and 3
    hierarchy, fresh = joint._kept_hierarchies[problem]
    assert hierarchy.levels[0].A is None and fresh == kept[0][1]
    monkeypatch.setattr(joint, "REUSE_HIERARCHY_MAX_PIXELS", 0)
    other = LevelProblem(problem.level, problem.tau, problem.lam)
    anew = steps(other)
    assert len(made) == 2 and other not in joint._kept_hierarchies
    assert kept[0] == anew[0]  # the first step: the same set-up
    for (e_kept, n_kept), (e_anew, n_anew) in zip(kept[1:], anew[1:]):  # measured: 2e-6 relative, the same counts
        assert e_kept == pytest.approx(e_anew, rel=1e-4) and n_kept <= n_anew + joint.REUSE_EXTRA_ITERATIONS


def test_projecting_the_albedo_out_moves_it_with_the_step(problem):
    """With the albedo also off the truth (5 % ripple), one projected joint step removes over 99 %
    of the energy; the plain step, which holds the albedo, finds no step length that lowers it
    much (the ripple looks to it like shading to be explained by the depth)."""
    est = kicked_estimate(problem)
    est.albedo = est.albedo * (1 + 0.05 * np.cos(np.arange(est.z.size) / 7.0))[:, None]
    energy = problem.evaluate(est).energy
    after = {}
    for project in (False, True):  # each step releases the evaluation it is given: one each
        stepped, stepped_ev, _ = update_pose_depth(LevelProblem(problem.level, problem.tau, problem.lam), est,
                                                   problem.evaluate(est),
                                                   rtol=OPTIONS.joint_cg_tolerance,
                                                   maxiter=OPTIONS.cg_max_iterations, project_albedo=project)
        after[project] = stepped_ev.energy
        assert (stepped.albedo is est.albedo) != project
    assert after[True] < 0.01 * energy and after[False] > 0.9 * energy, (energy, after)


def test_a_step_releases_its_evaluation_and_a_second_use_is_refused(problem):
    """The step drops the per-pixel arrays of the evaluation it read (keeping its energy), so they
    are not held through the solve; reading it again is a clear error, not a crash."""
    est = kicked_estimate(problem)
    ev = problem.evaluate(est)
    energy = ev.energy
    _, stepped_ev, _ = update_pose_depth(problem, est, ev, rtol=OPTIONS.joint_cg_tolerance,
                                         maxiter=OPTIONS.cg_max_iterations)
    assert ev.residual is None and ev.color is None and ev.energy == energy
    assert stepped_ev.residual is not None and stepped_ev.energy < energy
    with pytest.raises(ValueError, match="released"):
        joint_system(problem, est, ev)


def test_refine_options_validate_the_joint_step_settings():
    for bad, message in [(dict(joint_min_pixels=-1), "joint_min_pixels"),
                         (dict(joint_cg_tolerance=0.0), "joint_cg_tolerance"),
                         (dict(cg_tolerance=1.5), "cg_tolerance")]:
        with pytest.raises(ValueError, match=message):
            RefineOptions(**bad)
    with pytest.raises(ValueError, match="depth_envelope"):
        RefineOptions(depth_envelope=-0.1)
    assert RefineOptions(joint_min_pixels=0, depth_envelope=None).joint_min_pixels == 0


def test_damping_keeps_the_step_finite_where_only_the_reference_sees(problem):
    """Pixels that no frame but the reference sees carry no data once the albedo is projected
    out (one image cannot tell albedo from shading); with the LED's little smoothness switched off
    and the prior averaging 2 x 2 blocks, M is singular there (3 free directions per block). An
    LED scene on a 360-degree ring gave CG NaN from the AMG cycle's coarse solve. Damped, M is
    positive definite, and the joint step is finite and lowers the energy."""
    est = kicked_estimate(problem)
    grid = problem.level.grid

    def free_directions():
        eigenvalues = np.linalg.eigvalsh(joint_system(problem, est, problem.evaluate(est)).matrix.toarray())
        return int(np.sum(eigenvalues < 1e-9 * eigenvalues[-1]))

    assert free_directions() == 0
    hidden = (grid.u >= 24) & (grid.u < 40) & (grid.v >= 16) & (grid.v < 32)  # 16 x 16 px, 64 whole blocks
    problem.visibility[1:, hidden] = False
    assert free_directions() > 64  # 132: up to 3 per block, fewer at the edge, which its neighbours' stencils pin
    ev = problem.evaluate(est)
    M = joint_system(problem, est, ev).matrix.toarray()
    damped = np.linalg.eigvalsh(levenberg_damped(sp.csr_matrix(M)).toarray())
    assert damped[0] >= DAMPING * 0.01 * np.mean(np.diag(M)) * (1 - 1e-6)
    stepped, stepped_ev, _ = update_pose_depth(problem, est, ev, rtol=1e-6, maxiter=300)
    assert np.isfinite(stepped.z).all() and stepped_ev.energy < problem.evaluate(est).energy


# ---------------------------------------------------------------------------------------------
# the coupling's storage and the step's memory


@pytest.mark.parametrize("project_albedo", [False, True])
def test_float32_coupling_gives_the_float64_system(problem, rng, monkeypatch, project_albedo):
    """The coupling U stored in float32 (normal_equations.COUPLING_DTYPE) and multiplied in
    float64 is the float64 U of before to its entries' rounding, and the Schur route on it gives
    the float64 system's step: U's products to 1e-6; the Schur complement, its right-hand side,
    dz and twists of an exact solve to 1e-5 (measured: 1e-6, the rounding times the system's condition; the joint step's CG stops at
    1e-2)."""
    from o3d_mvps.solver import normal_equations

    est = kicked_estimate(problem)
    ev = problem.evaluate(est)
    new = joint_system(problem, est, ev, project_albedo=project_albedo)
    monkeypatch.setattr(normal_equations, "COUPLING_DTYPE", np.float64)
    old = joint_system(problem, est, ev, project_albedo=project_albedo)
    assert new.coupling.dtype == np.float32 and old.coupling.dtype == np.float64
    assert new.coupling.nbytes * 2 == old.coupling.nbytes
    U = old.coupling
    assert np.abs(new.coupling - U).max() <= 1e-7 * np.abs(U).max()
    N = U.shape[0]
    for x, y in zip(rng.normal(size=(3, N)), rng.normal(size=(3, U.shape[1]))):
        np.testing.assert_allclose(new.couple_t(x), U.T @ x, rtol=1e-6, atol=1e-6 * np.abs(U.T @ x).max())
        np.testing.assert_allclose(new.couple(y), U @ y, rtol=1e-6, atol=1e-6 * np.abs(U @ y).max())
    S_old, rhs_old = old.schur_operator()
    S_new, rhs_new = new.schur_operator()
    assert relative_error(rhs_new, rhs_old) < 1e-5
    S_dense = S_old @ np.eye(N)
    assert relative_error(S_new @ np.eye(N), S_dense) < 1e-5
    dz_old = np.linalg.solve(S_dense, rhs_old)
    dz_new = np.linalg.solve(S_new @ np.eye(N), rhs_new)
    assert relative_error(dz_new, dz_old) < 1e-5
    assert relative_error(new.twists(dz_new).ravel(), old.twists(dz_old).ravel()) < 1e-5


def frames_problem(level, n):
    """The test level with n frames (frames 1 and 2 repeated), and the kicked estimate on it."""
    pick = [0] + [1 + k % 2 for k in range(n - 1)]
    many = LevelProblem(dataclasses.replace(level, images=[level.images[i] for i in pick],
                                            frame_masks=[level.frame_masks[i] for i in pick]), 1.0, 0.04)
    est = kicked_estimate(LevelProblem(level, 1.0, 0.04))
    return many, Estimate(est.z, est.albedo, est.lights[pick], est.poses[pick])


def test_the_assembly_memory_grows_linearly_with_the_frames(level):
    """tracemalloc's peak of the joint assembly for 3, 5 and 7 frames grows by the same amount
    per frame (within 15 %), and by at most 50 float64 numbers per pixel and frame (measured: 42,
    where one block holds all the pixels: the float32 coupling's 3, the block's twist rows 18 and
    w s J 18 (normal_equations.BLOCK_PIXELS bounds these at 2 megapixels), light rows and LED
    Jacobians)."""
    import tracemalloc

    peaks = []
    for n in (3, 5, 7):
        problem, est = frames_problem(level, n)
        ev = problem.evaluate(est)
        joint_system(problem, est, ev)  # once untraced: first-call caches
        tracemalloc.start()
        try:
            system = joint_system(problem, est, ev)
            peaks.append(tracemalloc.get_traced_memory()[1])
        finally:
            tracemalloc.stop()
        assert len(system.frames) == n - 1
    N = level.grid.size
    first, second = (peaks[1] - peaks[0]) / 2, (peaks[2] - peaks[1]) / 2
    assert first > 0 and abs(second - first) <= 0.15 * first, peaks
    assert second / (8 * N) <= 50, second / (8 * N)


# ---------------------------------------------------------------------------------------------
# the depth block filled into a per-level pattern


def test_depth_block_equals_the_sparse_products(level, rng):
    """depth_block (compiled fill of a cached pattern) gives the matrix of the sparse products
    and sums (stencil_normal_matrix + 2 tau D^T D + 2 mu S^T S) to rounding (1e-13 of its largest
    entry; measured ~1e-16), on a mask with a hole (one-sided differences), with smoothness
    weights changed after the pattern was built, and pixels that no frame sees."""
    from o3d_mvps.model.normals import masked_grid
    from o3d_mvps.solver.normal_equations import depth_block, stencil_normal_matrix
    from o3d_mvps.solver.pyramid import depth_prior
    from o3d_mvps.solver.smoothness import second_differences

    mask = level.grid.mask.copy()
    mask[20:26, 30:37] = False  # a hole: one-sided differences around it
    grid = masked_grid(mask)
    z0 = bump_depth().reshape(SIZE[0] // 2, 2, SIZE[1] // 2, 2).mean(axis=(1, 3))
    prior = depth_prior(grid, z0, 2.0)
    prior.S = second_differences(grid)
    problem = LevelProblem(dataclasses.replace(level, grid=grid, prior=prior), 0.7, 0.04, smoothness=0.3)
    for sweep in range(2):
        sums = rng.normal(size=(6, grid.size))
        sums[:3] = np.abs(sums[:3])
        sums[:, :40] = 0.0  # pixels no frame sees
        prior.weigh_smoothness(rng.uniform(0.1, 1.0, grid.size))
        expected = stencil_normal_matrix(grid, *sums) + 0.7 * 2 * prior.DtD + 0.3 * 2 * prior.StS
        actual = depth_block(problem, sums)
        assert problem.depth_pattern is not None and actual.has_sorted_indices
        scale = np.abs(expected).max()
        assert np.abs((actual - expected).toarray()).max() <= 1e-13 * scale
        assert np.shares_memory(actual.indices, problem.depth_pattern[1])  # the pattern's arrays, not a copy
        # 2 tau D^T D added from D's rows (a block average: one entry per column) equals adding D^T D bit for bit
        from o3d_mvps.solver import kernels
        indptr, indices = problem.depth_pattern
        data = np.zeros(indices.size)
        kernels.add_stencil_gram(indptr, indices, grid.fwd_u, grid.bwd_u, grid.wf_u, grid.wb_u, grid.fwd_v,
                                 grid.bwd_v, grid.wf_v, grid.wb_v, *sums, data)
        for scale, term in prior.hessian_terms(0.7, 0.3):
            kernels.add_csr_into_pattern(indptr, indices, data, scale, term.indptr, term.indices, term.data)
        assert np.bincount(prior.D.indices).max() == 1 and np.array_equal(actual.data, data)
        damped = levenberg_damped(actual.copy(), overwrite=True)
        assert np.abs((damped - levenberg_damped(expected)).toarray()).max() <= 1e-13 * scale


def test_released_early_the_system_is_the_same_and_colours_go_before_the_coupling(problem, monkeypatch):
    """joint_system(release=True) drops the warped colours and light bases, which it does not
    read, before it allocates the coupling U (their memory is not held beside U), the rest once
    read, and forms the same system bit for bit as without release; prepare_depth_block builds the
    level's pattern and D^T D up front (depth_block then reuses them: the same matrix bit for bit)."""
    from o3d_mvps.solver import normal_equations
    from o3d_mvps.solver.normal_equations import depth_block_pattern, prepare_depth_block

    est = kicked_estimate(problem)
    kept = joint_system(problem, est, problem.evaluate(est))
    seen = []
    assemble = normal_equations._assemble_block

    def recorded(problem, est, ev, *args, **kwargs):
        seen.append((ev.color is None, ev.basis is None, ev.residual is not None))
        return assemble(problem, est, ev, *args, **kwargs)

    monkeypatch.setattr(normal_equations, "_assemble_block", recorded)
    fresh = LevelProblem(problem.level, problem.tau, problem.lam)
    prepare_depth_block(fresh)
    indptr, indices = depth_block_pattern(fresh.level.grid, fresh.level.prior)
    assert np.array_equal(fresh.depth_pattern[0], indptr) and np.array_equal(fresh.depth_pattern[1], indices)
    pattern = fresh.depth_pattern
    ev = fresh.evaluate(est)
    released = joint_system(fresh, est, ev, release=True)
    assert seen and all(s == (True, True, True) for s in seen)
    assert all(getattr(ev, name) is None for name in ev.ARRAYS)
    assert fresh.depth_pattern is pattern  # reused, not rebuilt
    for a, b in ((kept.matrix, released.matrix),):
        assert np.array_equal(a.indptr, b.indptr) and np.array_equal(a.indices, b.indices)
        assert np.array_equal(a.data, b.data)
    for name in ("rhs_z", "coupling", "hessian", "rhs_xi"):
        assert np.array_equal(getattr(kept, name), getattr(released, name)), name
    assert kept.frames == released.frames


def test_the_smoothness_hessian_is_not_held_through_the_solve_and_comes_back_the_same(level, monkeypatch):
    """joint_system on the host forms M and its right-hand side from the prior's S^T S, then,
    on a grid of more than HOLD_PRODUCTS_PIXELS pixels, drops it (DepthPrior.release_products:
    107 MB at 2 megapixels, not held beside the AMG set-up): no reference to that matrix is left
    once the system is formed, and the next system, which forms S^T S again, is the same bit for
    bit as one formed with S^T S kept. On a smaller grid it is kept for the next step (the same
    matrix object), which then forms the same system bit for bit."""
    import gc
    import weakref

    from o3d_mvps.solver import normal_equations
    from o3d_mvps.solver.smoothness import second_differences

    prior = dataclasses.replace(level.prior, S=second_differences(level.grid))
    problem = LevelProblem(dataclasses.replace(level, prior=prior), 1.0, 0.04, smoothness=0.3)
    est = kicked_estimate(problem)
    assert level.grid.size <= normal_equations.HOLD_PRODUCTS_PIXELS
    held = joint_system(problem, est, problem.evaluate(est), release=True)
    product = prior.__dict__["StS"]  # kept on this small grid
    again = joint_system(problem, est, problem.evaluate(est), release=True)
    assert prior.__dict__["StS"] is product  # not formed again
    for name in ("rhs_z", "coupling", "hessian", "rhs_xi"):
        assert np.array_equal(getattr(held, name), getattr(again, name)), name
    assert np.array_equal(held.matrix.data, again.matrix.data)
    prior.release_products()
    monkeypatch.setattr(normal_equations, "HOLD_PRODUCTS_PIXELS", level.grid.size - 1)  # as on a larger grid
    first = joint_system(problem, est, problem.evaluate(est), release=True)
    assert "StS" not in prior.__dict__
    gone = weakref.ref(prior.StS)  # formed again on demand (the next step's product)
    kept = prior.StS
    expected = joint_system(problem, est, problem.evaluate(est))  # with S^T S held by `kept` throughout
    assert "StS" not in prior.__dict__
    del kept
    gc.collect()
    assert gone() is None  # nothing in the system or the problem holds it
    for a, b in ((first, expected), (first, held)):
        assert np.array_equal(a.matrix.data, b.matrix.data) and np.array_equal(a.matrix.indices, b.matrix.indices)
        for name in ("rhs_z", "coupling", "hessian", "rhs_xi"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(prior.StS.toarray(), (prior.S.T @ prior.S).toarray())


def test_weighing_lets_the_last_weighted_smoothness_go_before_making_the_next(level, rng, monkeypatch):
    """At each weighing after the first the prior drops its last weighted S (and S^T S) once its
    unweighted S is back (made anew or put back from the weighted one) and before it weighs it, so
    that two weighted S are not held at once (77 MB at 2 MP, where the 2 MP solve peaked): when
    the rows' weights are read (row_centres), the last weighted S is already freed (a weak
    reference)."""
    import weakref

    from o3d_mvps.solver import pyramid
    from o3d_mvps.solver.pyramid import build_level

    monkeypatch.setattr(pyramid, "REBUILD_SMOOTHNESS_PIXELS", 0)
    z0 = bump_depth().reshape(SIZE[0] // 2, 2, SIZE[1] // 2, 2).mean(axis=(1, 3))
    prior = build_level(0, level.images, [None] * len(level.images), level.grid.mask, level.K, z0, 2).prior
    last, alive_at_weighing = [], []
    centres = pyramid.row_centres

    def recording_centres(S):
        alive_at_weighing.append([ref() is not None for ref in last])
        return centres(S)

    monkeypatch.setattr(pyramid, "row_centres", recording_centres)
    for sweep in range(3):
        prior.weigh_smoothness(rng.uniform(0.1, 1.0, prior.S.shape[1]))
        assert prior.StS is not None  # formed from the weighted S, as a step does
        last.append(weakref.ref(prior.S))
    assert alive_at_weighing == [[], [False], [False, False]]


def test_a_dropped_level_s_prior_is_freed_without_the_garbage_collector(level, rng, monkeypatch):
    """The prior's way to make its unweighted S again holds no reference to the prior (no cycle):
    once a level is dropped its prior and weighted S go at once, not at the collector's next run
    (a 2 MP level's S is 77 MB)."""
    import gc
    import weakref

    from o3d_mvps.solver import pyramid
    from o3d_mvps.solver.pyramid import build_level

    monkeypatch.setattr(pyramid, "REBUILD_SMOOTHNESS_PIXELS", 0)
    z0 = bump_depth().reshape(SIZE[0] // 2, 2, SIZE[1] // 2, 2).mean(axis=(1, 3))
    built = build_level(0, level.images, [None] * len(level.images), level.grid.mask, level.K, z0, 2)
    for sweep in range(2):
        built.prior.weigh_smoothness(rng.uniform(0.1, 1.0, built.grid.size))
    prior, S = weakref.ref(built.prior), weakref.ref(built.prior.S)
    gc.disable()
    try:
        del built
        assert prior() is None and S() is None
    finally:
        gc.enable()


def test_weighing_a_rebuildable_smoothness_keeps_no_copy_and_gives_the_same_rows(level, rng, monkeypatch):
    """build_level's prior makes its unweighted S anew for each weighing (rebuild_smoothness_with)
    instead of keeping a copy beside the weighted one, on grids of more than
    REBUILD_SMOOTHNESS_PIXELS (here 0): the weighted S, its S^T S and the smoothness pattern are
    the same bit for bit as with the copy kept, and no unweighted copy is held."""
    from o3d_mvps.solver import pyramid
    from o3d_mvps.solver.pyramid import build_level
    from o3d_mvps.solver.smoothness import second_differences

    monkeypatch.setattr(pyramid, "REBUILD_SMOOTHNESS_PIXELS", 0)

    z0 = bump_depth().reshape(SIZE[0] // 2, 2, SIZE[1] // 2, 2).mean(axis=(1, 3))
    built = build_level(0, level.images, [None] * len(level.images), level.grid.mask, level.K, z0, 2)
    kept = dataclasses.replace(built.prior, S=second_differences(built.grid))  # no way to rebuild: a copy kept
    kept.__dict__.pop("_S_build", None)
    assert np.array_equal(kept.S.toarray(), built.prior.S.toarray())
    for sweep in range(3):
        weights = rng.uniform(0.1, 1.0, built.grid.size)
        built.prior.weigh_smoothness(weights)
        kept.weigh_smoothness(weights)
        for a, b in ((built.prior.S, kept.S), (built.prior.StS, kept.StS)):
            assert np.array_equal(a.indptr, b.indptr) and np.array_equal(a.indices, b.indices)
            assert np.array_equal(a.data, b.data)
        assert "_S_unweighted" not in built.prior.__dict__ and "_S_unweighted" in kept.__dict__
        pattern = built.prior.smoothness_pattern
        assert np.array_equal(pattern.toarray(), kept.smoothness_pattern.toarray())
    # up to REBUILD_SMOOTHNESS_PIXELS (the default: this grid) the unweighted S is held instead of
    # made again at each weighing: the same weighted S bit for bit
    monkeypatch.undo()
    held = build_level(0, level.images, [None] * len(level.images), level.grid.mask, level.K, z0, 2)
    assert held.grid.size <= pyramid.REBUILD_SMOOTHNESS_PIXELS
    for sweep in range(3):
        weights = rng.uniform(0.1, 1.0, held.grid.size)
        held.prior.weigh_smoothness(weights)
        kept.weigh_smoothness(weights)
        assert "_S_unweighted" in held.prior.__dict__
        assert np.array_equal(held.prior.S.indices, kept.S.indices) and np.array_equal(held.prior.S.data, kept.S.data)
