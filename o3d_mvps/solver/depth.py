"""Depth update: with dA and the warp frozen at the previous z, the IRLS energy is quadratic in z.

Per frame i and pixel p the light model gives the shading as ``s_i = c_i + <L_i, n>`` (SH: the
frame's constant light vector; LED: a per-pixel vector, frozen at the previous z like dA), so
``s_i = c_i + (A_i z)_p / dA_p`` with ``A_i = diag(alpha_i) Du + diag(beta_i) Dv + diag(gamma_i)``,
``alpha_i = fx L_i1 - (u - cx) L_i3``, ``beta_i = fy L_i2 - (v - cy) L_i3``, ``gamma_i = -L_i3``.
Minimising ``sum w/2 (I~ - rho s)^2 + tau ||D z - z0||^2`` gives the SPD system
``(sum_i A_i^T W_i A_i + 2 tau D^T D) z = sum_i A_i^T B_i + 2 tau D^T z0`` (7-point stencil),
solved by CG preconditioned with smoothed-aggregation AMG (pyamg), warm-started at z.
A backtracking line search on the true energy keeps every accepted step energy-decreasing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyamg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..model.robust import cauchy_weights
from .problem import Estimate, Evaluation, LevelProblem


@dataclass
class DepthSystem:
    """The SPD normal equations of the depth step: matrix (N, N) and right-hand side (N,)."""

    matrix: sp.csr_matrix
    rhs: np.ndarray


def depth_system(problem: LevelProblem, est: Estimate, ev: Evaluation) -> DepthSystem:
    """Assemble the depth step's normal equations at the current estimate."""
    g = problem.level.grid
    K = problem.level.K
    w = cauchy_weights(ev.residual, problem.lam) * ev.usable[..., None]  # (n, N, 3)
    q = est.albedo / ev.dA[:, None]  # (N, 3)
    du = g.u - K[0, 2]
    dv = g.v - K[1, 2]
    points_ref = problem.points(est.z)
    # accumulated over frames: the six products of (alpha, beta, gamma) weighted by W, and
    # (alpha, beta, gamma) times B
    Saa, Sbb, Sgg, Sab, Sag, Sbg, Ba, Bb, Bg = np.zeros((9, g.size))
    for i in range(problem.n_frames):
        T = est.poses[i]
        c, L = problem.light.field(est.lights[i], ev.normals, points_ref, T)
        L = np.broadcast_to(L, (g.size, 3))
        W = np.einsum("nc,nc->n", w[i], q * q)
        B = np.einsum("nc,nc,nc->n", w[i], q, ev.color[i] - est.albedo * np.reshape(c, (-1, 1)))
        alpha = K[0, 0] * L[:, 0] - du * L[:, 2]
        beta = K[1, 1] * L[:, 1] - dv * L[:, 2]
        gamma = -L[:, 2]
        Wa, Wb = W * alpha, W * beta
        Saa += Wa * alpha
        Sbb += Wb * beta
        Sgg += W * gamma * gamma
        Sab += Wa * beta
        Sag += Wa * gamma
        Sbg += Wb * gamma
        Ba += alpha * B
        Bb += beta * B
        Bg += gamma * B
    Du, Dv = g.difference_operators()
    diag = sp.diags
    cross = Du.T @ diag(Sab) @ Dv + Du.T @ diag(Sag) + Dv.T @ diag(Sbg)
    M = Du.T @ diag(Saa) @ Du + Dv.T @ diag(Sbb) @ Dv + diag(Sgg) + cross + cross.T
    prior = problem.level.prior
    M = M + (2.0 * problem.tau) * (prior.D.T @ prior.D)
    rhs = Du.T @ Ba + Dv.T @ Bb + Bg + (2.0 * problem.tau) * (prior.D.T @ prior.z0)
    return DepthSystem(sp.csr_matrix(M), rhs)


def amg_preconditioner(matrix: sp.csr_matrix) -> spla.LinearOperator:
    """One smoothed-aggregation AMG V-cycle (pyamg hierarchy) as an SPD preconditioner.

    The cycle is run here rather than through ``MultilevelSolver.aspreconditioner``, whose
    ``solve`` also computes two residuals and three norms per application (two extra
    fine-level products per CG iteration, about a quarter of the depth step's time).
    """
    ml = pyamg.smoothed_aggregation_solver(matrix, symmetry="symmetric", max_coarse=300, coarse_solver="splu")
    levels = ml.levels

    def cycle(k: int, b: np.ndarray) -> np.ndarray:
        level = levels[k]
        if k == len(levels) - 1:
            return np.asarray(ml.coarse_solver(level.A, b)).reshape(b.shape)
        x = np.zeros_like(b)
        level.presmoother(level.A, x, b)
        x += level.P @ cycle(k + 1, level.R @ (b - level.A @ x))
        level.postsmoother(level.A, x, b)
        return x

    return spla.LinearOperator(matrix.shape, lambda b: cycle(0, np.ravel(b)), dtype=matrix.dtype)


def solve_depth_system(system: DepthSystem, z0: np.ndarray, rtol: float, maxiter: int,
                       preconditioner: spla.LinearOperator | None = None) -> tuple[np.ndarray, int]:
    """PCG warm-started at z0; returns (z, iterations).

    ``preconditioner`` defaults to a fresh AMG hierarchy of the system; the driver passes the
    hierarchy of the level's first sweep instead, since the matrix changes little between
    sweeps (only the IRLS weights, albedo and lighting move) and the setup costs more than
    the few extra CG iterations.
    """
    precond = preconditioner if preconditioner is not None else amg_preconditioner(system.matrix)
    count = [0]

    def callback(_):
        count[0] += 1

    z, _ = spla.cg(system.matrix, system.rhs, x0=z0, rtol=rtol, maxiter=maxiter, M=precond, callback=callback)
    return z, count[0]


def update_depth(problem: LevelProblem, est: Estimate, ev: Evaluation, *, rtol: float, maxiter: int,
                 max_halvings: int = 5) -> tuple[np.ndarray, Evaluation, int]:
    """One depth step: returns (z, evaluation at z, CG iterations); z never raises the energy.

    The level's AMG preconditioner is built on its first depth step and kept in
    ``problem.depth_preconditioner`` until CG needs twice the iterations it first took.
    """
    system = depth_system(problem, est, ev)
    if problem.depth_preconditioner is None:
        problem.depth_preconditioner = amg_preconditioner(system.matrix)
    z_new, iterations = solve_depth_system(system, est.z, rtol, maxiter, problem.depth_preconditioner)
    if problem.depth_cg_baseline is None:
        problem.depth_cg_baseline = max(iterations, 5)
    elif iterations > 2 * problem.depth_cg_baseline:  # the system drifted from the hierarchy's: rebuild next time
        problem.depth_preconditioner = problem.depth_cg_baseline = None
    step = z_new - est.z
    t = 1.0
    for _ in range(max_halvings + 1):
        z_try = est.z + t * step
        if np.all(z_try > 0):
            trial = Estimate(z_try, est.albedo, est.lights, est.poses)
            ev_try = problem.evaluate(trial)
            if ev_try.energy <= ev.energy:
                return z_try, ev_try, iterations
        t *= 0.5
    return est.z, ev, iterations
