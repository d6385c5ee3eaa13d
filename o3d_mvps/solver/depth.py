"""Depth update and the linear algebra of the depth and joint steps.

The depth step is the paper's with the warp frozen at the previous z: the Gauss-Newton normal
equations of :func:`~.normal_equations.joint_system` without parallax or twists (frozen dA and
light field, albedo projected out), ``M dz = b`` with M sparse SPD (7-point stencil plus
2 tau D^T D), solved by CG preconditioned with smoothed-aggregation AMG (pyamg). A backtracking
line search on the true energy keeps every accepted step energy-decreasing.
"""

from __future__ import annotations

import numpy as np
import pyamg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .normal_equations import joint_system
from .problem import Estimate, Evaluation, LevelProblem
from .reflectance import update_albedo


def amg_preconditioner(matrix: sp.csr_matrix) -> spla.LinearOperator:
    """One smoothed-aggregation AMG V-cycle (pyamg hierarchy) as an SPD preconditioner.

    The cycle is run here rather than through ``MultilevelSolver.aspreconditioner``, whose
    ``solve`` also computes two residuals and three norms per application (two extra
    fine-level products per CG iteration, about a quarter of the depth step's time).
    """
    state = np.random.get_state()  # pyamg starts its spectral-radius estimates from numpy's global RNG:
    np.random.seed(0)  # seeded here (and restored) so that the same inputs give the same result
    try:
        ml = pyamg.smoothed_aggregation_solver(matrix, symmetry="symmetric", max_coarse=300, coarse_solver="splu")
    finally:
        np.random.set_state(state)
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


def solve_depth_system(matrix, rhs: np.ndarray, x0: np.ndarray, rtol: float, maxiter: int,
                       preconditioner: spla.LinearOperator | None = None) -> tuple[np.ndarray, int]:
    """PCG on ``matrix x = rhs`` ((N, N) sparse SPD or operator) from x0; returns (x, iterations).

    ``preconditioner`` defaults to a fresh AMG hierarchy of the system; the driver passes the
    hierarchy of the level's first sweep instead, since the matrix changes little between
    sweeps (only the IRLS weights, albedo and lighting move) and the setup costs more than
    the few extra CG iterations.
    """
    precond = preconditioner if preconditioner is not None else amg_preconditioner(matrix)
    count = [0]

    def callback(_):
        count[0] += 1

    x, _ = spla.cg(matrix, rhs, x0=x0, rtol=rtol, maxiter=maxiter, M=precond, callback=callback)
    return x, count[0]


def solve_with_level_preconditioner(problem: LevelProblem, matrix, rhs: np.ndarray, x0: np.ndarray, rtol: float,
                                     maxiter: int, schur=None) -> tuple[np.ndarray, int]:
    """PCG with the level's AMG hierarchy: built on the level's first solve and kept in
    ``problem.depth_preconditioner`` until CG needs twice the iterations it first took.

    ``matrix`` (N, N) sparse SPD, or a LinearOperator with ``schur`` the sparse part the
    hierarchy is built from. Returns (x, iterations).
    """
    if problem.depth_preconditioner is None:
        problem.depth_preconditioner = amg_preconditioner(matrix if schur is None else schur)
    x, iterations = solve_depth_system(matrix, rhs, x0, rtol, maxiter, problem.depth_preconditioner)
    if problem.depth_cg_baseline is None:
        problem.depth_cg_baseline = max(iterations, 5)
    elif iterations > 2 * problem.depth_cg_baseline:  # the system drifted from the hierarchy's: rebuild next time
        problem.depth_preconditioner = problem.depth_cg_baseline = None
    return x, iterations


def update_depth(problem: LevelProblem, est: Estimate, ev: Evaluation, *, rtol: float, maxiter: int,
                 project_albedo: bool = True, max_halvings: int = 5) -> tuple[Estimate, Evaluation, int]:
    """One depth step (warp frozen; with ``project_albedo`` the albedo eliminated and refitted at
    every trial): returns (estimate, its evaluation, CG iterations); never raises the energy."""
    system = joint_system(problem, est, ev, parallax=False, twists=False, project_albedo=project_albedo)
    step, iterations = solve_with_level_preconditioner(problem, system.matrix, system.rhs_z, np.zeros_like(est.z),
                                                       rtol, maxiter)

    def trial(t: float):
        z = problem.level.prior.clip(est.z + t * step)
        return Estimate(z, est.albedo, est.lights, est.poses) if np.all(z > 0) else None

    found = backtracking_search(problem, ev, trial, max_halvings, refit_albedo=project_albedo)
    return (est, ev, iterations) if found is None else (*found, iterations)


def backtracking_search(problem: LevelProblem, ev: Evaluation, trial, max_halvings: int, *,
                        refit_albedo: bool = False):
    """Try ``trial(t)`` (an Estimate, or None where invalid) for t = 1, 1/2, ...; return the
    first (estimate, evaluation) whose energy is not above ``ev``'s, else None.

    refit_albedo: give each trial its closed-form albedo (:func:`update_albedo`) first.
    """
    t = 1.0
    for _ in range(max_halvings + 1):
        candidate = trial(t)
        if candidate is not None:
            candidate_ev = problem.evaluate(candidate)
            if refit_albedo:
                candidate.albedo = update_albedo(candidate, candidate_ev, problem.lam)
                candidate_ev = problem.reevaluate(candidate, candidate_ev)
            if candidate_ev.energy <= ev.energy:
                return candidate, candidate_ev
        t *= 0.5
    return None
