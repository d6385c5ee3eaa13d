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
    w = cauchy_weights(ev.residual, problem.lam) * ev.usable[..., None]  # (n, N, 3)
    q = est.albedo / ev.dA[:, None]  # (N, 3)
    points_ref = problem.points(est.z)
    # accumulated over frames: the six products of (alpha, beta, gamma) weighted by W, and
    # (alpha, beta, gamma) times B
    Saa, Sbb, Sgg, Sab, Sag, Sbg, Ba, Bb, Bg = np.zeros((9, g.size))
    for i in range(problem.n_frames):
        c, alpha, beta, gamma = shading_rows(problem, est.lights[i], ev.normals, points_ref, est.poses[i])
        W = np.einsum("nc,nc->n", w[i], q * q)
        B = np.einsum("nc,nc,nc->n", w[i], q, ev.color[i] - est.albedo * np.reshape(c, (-1, 1)))
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
    prior = problem.level.prior
    M = stencil_normal_matrix(g, Saa, Sbb, Sgg, Sab, Sag, Sbg) + (2.0 * problem.tau) * (prior.D.T @ prior.D)
    rhs = stencil_transpose(g, Ba, Bb, Bg) + (2.0 * problem.tau) * (prior.D.T @ prior.z0)
    return DepthSystem(sp.csr_matrix(M), rhs)


def shading_rows(problem: LevelProblem, light: np.ndarray, normals: np.ndarray, points_ref: np.ndarray,
                 pose: np.ndarray):
    """(c, alpha, beta, gamma), (N,) each (c may be a scalar), with the light field frozen at
    the current surface: the shading is ``c + (alpha Du z + beta Dv z + gamma z) / dA``."""
    g, K = problem.level.grid, problem.level.K
    c, L = problem.light.field(light, normals, points_ref, pose)
    L = np.broadcast_to(L, (g.size, 3))
    alpha = K[0, 0] * L[:, 0] - (g.u - K[0, 2]) * L[:, 2]
    beta = K[1, 1] * L[:, 1] - (g.v - K[1, 2]) * L[:, 2]
    return c, alpha, beta, -L[:, 2]


def stencil_normal_matrix(grid, Saa, Sbb, Sgg, Sab, Sag, Sbg) -> sp.csr_matrix:
    """sum over rows of R^T W R for rows ``R = a Du + b Dv + c I``, from the per-pixel weighted
    products (N,) each (``Saa = sum w a a``, ...): an (N, N) sparse 7-point-stencil matrix."""
    Du, Dv = grid.difference_operators()
    diag = sp.diags
    cross = Du.T @ diag(Sab) @ Dv + Du.T @ diag(Sag) + Dv.T @ diag(Sbg)
    return sp.csr_matrix(Du.T @ diag(Saa) @ Du + Dv.T @ diag(Sbb) @ Dv + diag(Sgg) + cross + cross.T)


def stencil_transpose(grid, Ba, Bb, Bg):
    """``Du^T Ba + Dv^T Bb + Bg``: R^T applied to per-pixel values, (N,) or (N, k) each."""
    Du, Dv = grid.difference_operators()
    return Du.T @ Ba + Dv.T @ Bb + Bg


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


def solve_with_level_preconditioner(problem: LevelProblem, matrix, rhs: np.ndarray, x0: np.ndarray, rtol: float,
                                     maxiter: int, schur=None) -> tuple[np.ndarray, int]:
    """PCG with the level's AMG hierarchy: built on the level's first solve and kept in
    ``problem.depth_preconditioner`` until CG needs twice the iterations it first took.

    ``matrix`` (N, N) sparse SPD, or a LinearOperator with ``schur`` the sparse part the
    hierarchy is built from. Returns (x, iterations).
    """
    if problem.depth_preconditioner is None:
        problem.depth_preconditioner = amg_preconditioner(matrix if schur is None else schur)
    x, iterations = solve_depth_system(DepthSystem(matrix, rhs), x0, rtol, maxiter, problem.depth_preconditioner)
    if problem.depth_cg_baseline is None:
        problem.depth_cg_baseline = max(iterations, 5)
    elif iterations > 2 * problem.depth_cg_baseline:  # the system drifted from the hierarchy's: rebuild next time
        problem.depth_preconditioner = problem.depth_cg_baseline = None
    return x, iterations


def update_depth(problem: LevelProblem, est: Estimate, ev: Evaluation, *, rtol: float, maxiter: int,
                 max_halvings: int = 5) -> tuple[np.ndarray, Evaluation, int]:
    """One depth step: returns (z, evaluation at z, CG iterations); z never raises the energy."""
    system = depth_system(problem, est, ev)
    z_new, iterations = solve_with_level_preconditioner(problem, system.matrix, system.rhs, est.z, rtol, maxiter)
    step = z_new - est.z

    def trial(t: float):
        z = est.z + t * step
        return Estimate(z, est.albedo, est.lights, est.poses) if np.all(z > 0) else None

    found = backtracking_search(problem, ev, trial, max_halvings)
    return (est.z, ev, iterations) if found is None else (found[0].z, found[1], iterations)


def backtracking_search(problem: LevelProblem, ev: Evaluation, trial, max_halvings: int):
    """Try ``trial(t)`` (an Estimate, or None where invalid) for t = 1, 1/2, ...; return the
    first (estimate, evaluation) whose energy is not above ``ev``'s, else None."""
    t = 1.0
    for _ in range(max_halvings + 1):
        candidate = trial(t)
        if candidate is not None:
            candidate_ev = problem.evaluate(candidate)
            if candidate_ev.energy <= ev.energy:
                return candidate, candidate_ev
        t *= 0.5
    return None
