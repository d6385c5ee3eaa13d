"""Tests of the joint pose-depth Gauss-Newton step (o3d_mvps.solver.joint) and of the rigid
re-anchoring step (o3d_mvps.solver.anchor).

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

# pytest puts tests/ (no __init__.py) on sys.path, so the model tests' helpers import directly
from test_model import SIZE, K, bump_depth, make_problem
from threadpoolctl import threadpool_limits

from o3d_mvps import RefineOptions
from o3d_mvps.metrics import reprojection_error_px
from o3d_mvps.model import se3
from o3d_mvps.model.camera import pixel_grid
from o3d_mvps.model.normals import unnormalised_normals
from o3d_mvps.model.robust import cauchy, cauchy_weights
from o3d_mvps.model.warping import image_gradients
from o3d_mvps.solver.anchor import moved_estimate, update_anchor
from o3d_mvps.solver.depth import depth_system
from o3d_mvps.solver.joint import joint_system, residual_jacobians, update_pose_depth
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
# a rigid move of the surface (reference coordinates): ~5 mm and ~0.8 deg
MOVE = np.array([0.003, -0.002, 0.004, 0.01, -0.008, 0.006])
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
    return dataclasses.replace(make_problem(3)[0].level, images=images,
                               gradients=[np.stack(image_gradients(image)) for image in images])


@pytest.fixture
def problem(level):
    """A fresh problem per test (update steps cache a preconditioner on it)."""
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
    system = joint_system(problem, est, ev)
    assert system.frames == [1, 2] and system.rhs_xi.shape == (2, 6)

    def energy(i, d):
        return problem.evaluate(dataclasses.replace(est, poses=kicked_poses(est.poses, i, d))).energy

    for i, rhs in zip(system.frames, system.rhs_xi):
        fd = twist_differences(partial(energy, i))
        assert relative_error(-rhs, fd) < 0.03, (i, fd, -rhs)


def test_depth_rhs_is_minus_the_gradient_of_the_frozen_energy(problem):
    """rhs_z equals minus the gradient of the frozen-dA, frozen-light energy with the warp live
    (parallax included), along smooth directions; the frozen energy at z is the true energy.
    The warp's share is not negligible: freezing it too (depth_system's energy) misses by far.
    The prior's share is exact."""
    est = kicked_estimate(problem)
    ev = problem.evaluate(est)
    system = joint_system(problem, est, ev)
    assert frozen_energy(problem, est, ev, est.z) == pytest.approx(ev.energy, rel=1e-12)

    directions = smooth_directions(problem.level.grid)
    fd, fd_no_warp = (np.array([central_difference(partial(frozen_energy, problem, est, ev, live_warp=live), est.z,
                                                   d, 1e-3) for d in directions]) for live in (True, False))
    assert relative_error(directions @ -system.rhs_z, fd) < 0.03
    assert relative_error(fd_no_warp, fd) > 0.2
    # the prior's share, exactly: against the same system without the prior
    prior = problem.level.prior
    no_prior = joint_system(LevelProblem(problem.level, 0.0, problem.lam), est, ev)
    prior_gradient = 2 * problem.tau * prior.D.T @ (prior.D @ est.z - prior.z0)
    np.testing.assert_allclose(no_prior.rhs_z - system.rhs_z, prior_gradient, rtol=1e-9,
                               atol=1e-9 * np.abs(prior_gradient).max())
    # and the warp-frozen derivative is what depth_system's gradient gives (sanity of the yardstick)
    depth = depth_system(problem, est, ev)
    assert relative_error(directions @ (depth.matrix @ est.z - depth.rhs), fd_no_warp) < 1e-5


def test_joint_matrix_is_the_gauss_newton_matrix_of_the_residuals(problem):
    """M, U and H are the Gauss-Newton products of the residuals' derivatives with the Cauchy
    weights w: d^T M d = sum w (J_z d)^2 + 2 tau |D d|^2, d^T U = sum w (J_z d) J_xi per frame,
    H = sum w J_xi J_xi^T. Exactly, from residual_jacobians' per-pixel J_xi and parallax g
    (checked through the gradients above) with the shading part of J_z d by differences of the
    frozen residuals (linear in z); and, independently, H and d^T M d against finite differences
    of the frozen residuals to a few percent."""
    est = kicked_estimate(problem)
    ev = problem.evaluate(est)
    system = joint_system(problem, est, ev)
    w = cauchy_weights(ev.residual, problem.lam) * ev.usable[..., None]
    D = problem.level.prior.D
    points = problem.points(est.z)
    J_xi, parallax = np.zeros((problem.n_frames, est.z.size, 3, 6)), np.zeros(ev.residual.shape)
    for i in range(problem.n_frames):
        use, J, g = residual_jacobians(problem, est, ev, i, points)
        parallax[i, use] = g
        if J is not None:
            J_xi[i, use] = J

    def curvature(Jd, d):
        return (w * Jd**2).sum() + 2 * problem.tau * np.sum((D @ d) ** 2)

    for d in smooth_directions(problem.level.grid)[[0, 4, 8]]:
        shading_part = central_difference(lambda z: frozen_residuals(problem, est, ev, z, live_warp=False),
                                          est.z, d, 1.0)
        Jd = shading_part + parallax * d[:, None]
        assert d @ (system.matrix @ d) == pytest.approx(curvature(Jd, d), rel=1e-9)
        coupling = np.concatenate([np.einsum("nc,nc,ncj->j", w[i], Jd[i], J_xi[i]) for i in system.frames])
        np.testing.assert_allclose(d @ system.coupling, coupling, rtol=1e-9, atol=1e-9 * np.abs(coupling).max())
        fd = central_difference(lambda z: frozen_residuals(problem, est, ev, z), est.z, d, 1e-3)
        assert d @ (system.matrix @ d) == pytest.approx(curvature(fd, d), rel=0.03)
    for j, i in enumerate(system.frames):
        np.testing.assert_allclose(system.hessians[j], np.einsum("nc,ncj,nck->jk", w[i], J_xi[i], J_xi[i]),
                                   rtol=1e-9, atol=1e-9 * np.abs(system.hessians[j]).max())
        fd = twist_differences(partial(kicked_frame_residuals, problem, est, ev, i))  # (6, N, 3)
        assert relative_error(system.hessians[j], np.einsum("nc,jnc,knc->jk", w[i], fd, fd)) < 0.05, i


def test_schur_route_solves_the_full_system(problem, rng):
    """M is symmetric positive definite, the full matrix [[M, U], [U^T, blockdiag(H)]] is SPD,
    and the Schur complement route (dense solve of S, then twists) gives the dense solution."""
    est = kicked_estimate(problem)
    system = joint_system(problem, est, problem.evaluate(est))
    M = system.matrix.toarray()
    N = M.shape[0]
    assert np.abs(M - M.T).max() < 1e-12 * np.abs(M).max()
    for x in rng.normal(size=(5, N)):
        assert x @ M @ x > 0
    H = np.zeros((12, 12))
    for j, block in enumerate(system.hessians):
        H[6 * j:6 * j + 6, 6 * j:6 * j + 6] = block
    U = system.coupling
    assert U.shape == (N, 12) and np.abs(U).max() > 0
    full = np.block([[M, U], [U.T, H]])
    factor = scipy.linalg.cho_factor(full)  # raises unless SPD
    solution = scipy.linalg.cho_solve(factor, np.concatenate([system.rhs_z, system.rhs_xi.ravel()]))

    S, rhs, V = system.schur_operator()
    np.testing.assert_allclose(V, U @ np.linalg.inv(H), rtol=1e-10, atol=1e-12 * np.abs(V).max())
    S_dense = S @ np.eye(N)  # a block of columns, as well as the 1-D vectors CG applies it to
    np.testing.assert_allclose(S.matvec(np.eye(N)[0]), S_dense[:, 0])
    dz = np.linalg.solve(S_dense, rhs)
    xi = system.twists(dz)
    assert xi.shape == (2, 6)
    assert relative_error(dz, solution[:N]) < 1e-6
    assert relative_error(xi, solution[N:]) < 1e-6


# ---------------------------------------------------------------------------------------------
# update_pose_depth


def test_update_pose_depth_descends_and_recovers_kicked_poses(problem):
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
        z, poses, ev, _ = update_pose_depth(problem, est, ev, rtol=OPTIONS.joint_cg_tolerance,
                                            maxiter=OPTIONS.cg_max_iterations)
        est = dataclasses.replace(est, z=z, poses=poses)
        assert ev.energy == pytest.approx(problem.evaluate(est).energy, rel=1e-12)
        energies.append(ev.energy)
        errors.append(reprojection_errors(poses))
    assert energies[1] < 0.1 * energies[0]
    assert np.all(np.diff(energies) <= 0), energies
    np.testing.assert_array_equal(est.poses[0], np.eye(4))
    # the problem is nearly quadratic in the kick: one step removes ~99 % of it
    assert np.all(errors[0] < 0.03 * before) and np.all(errors[-1] <= 1.05 * errors[0]), (before, errors)


# ---------------------------------------------------------------------------------------------
# moved_estimate and update_anchor


def test_moved_estimate_moves_the_surface_and_its_albedo_to_first_order(problem):
    """Moving by xi puts the depth and albedo of the rigidly moved surface on the pixels, and
    moving back by -xi restores them, both up to O(|xi|^2) (errors shrink ~4x as xi halves);
    poses 1.. become T_i exp(xi)^-1, the reference pose stays; xi = 0 changes nothing."""
    truth = true_estimate(problem)
    grid = problem.level.grid
    interior = (grid.wf_u == 0.5) & (grid.wf_v == 0.5)  # central differences (first order at the rim)

    def errors(xi):
        moved = moved_estimate(problem, truth, xi)
        back = moved_estimate(problem, moved, -xi)
        # the moved pixels' points, moved back, lie on the true surface and carry its albedo
        G_inv = se3.exp(-xi)
        X = (problem.points(moved.z) @ G_inv[:3, :3].T + G_inv[:3, 3])[interior]
        off_surface = np.abs(X[:, 2] - surface_depth(X[:, 0] / X[:, 2], X[:, 1] / X[:, 2])).max()
        albedo = np.abs(moved.albedo[interior] - albedo_at(X)).max()
        round_trip = np.abs(back.z - truth.z).max(), np.abs(back.albedo - truth.albedo).max()
        return np.array([off_surface, albedo, *round_trip])

    coarse, fine = errors(MOVE), errors(MOVE / 2)
    assert np.all((coarse / fine > 3.5) & (coarse / fine < 4.5)), coarse / fine
    moved = moved_estimate(problem, truth, MOVE)
    assert coarse[0] < 0.1 * np.abs(moved.z - truth.z).max()  # far below the move itself
    assert coarse[1] < 0.3 * np.abs(moved.albedo - truth.albedo).max()
    np.testing.assert_array_equal(moved.poses[0], np.eye(4))
    np.testing.assert_allclose(moved.poses[1:] @ se3.exp(MOVE), truth.poses[1:], atol=1e-12)

    same = moved_estimate(problem, truth, np.zeros(6))
    np.testing.assert_allclose(same.z, truth.z, rtol=0, atol=1e-12)
    np.testing.assert_allclose(same.albedo, truth.albedo, rtol=0, atol=1e-12)
    np.testing.assert_allclose(same.poses, truth.poses, rtol=0, atol=1e-15)


def test_update_anchor_undoes_a_rigid_move_without_raising_the_energy(problem):
    """From the truth moved rigidly (surface by G, poses by G^-1), the anchor step strictly
    lowers the energy, brings the depth most of the way back and never raises the energy after;
    when no step can reach the energy it is handed, it returns its inputs."""
    truth = true_estimate(problem)
    est = moved_estimate(problem, truth, MOVE / 3)
    ev = problem.evaluate(est)
    start_error = np.abs(est.z - truth.z).mean()
    energies = [ev.energy]
    for _ in range(3):
        est, ev = update_anchor(problem, est, ev)
        assert ev.energy == pytest.approx(problem.evaluate(est).energy, rel=1e-12)
        energies.append(ev.energy)
    assert energies[1] < 0.5 * energies[0]
    assert np.all(np.diff(energies) <= 0), energies
    assert np.abs(est.z - truth.z).mean() < 0.1 * start_error

    # an evaluation claiming a negative energy: no candidate can match it, so nothing moves
    unreachable = dataclasses.replace(ev, data=-1.0, prior=0.0)
    kept, kept_ev = update_anchor(problem, est, unreachable)
    assert kept is est and kept_ev is unreachable


def test_refine_options_validate_the_joint_step_settings():
    for bad, message in [(dict(joint_min_pixels=-1), "joint_min_pixels"),
                         (dict(joint_cg_tolerance=0.0), "joint_cg_tolerance"),
                         (dict(cg_tolerance=1.5), "cg_tolerance")]:
        with pytest.raises(ValueError, match=message):
            RefineOptions(**bad)
    assert RefineOptions(joint_min_pixels=0, anchor=False).joint_min_pixels == 0
