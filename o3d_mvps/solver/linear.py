"""Linear solves: preconditioned CG with a reusable AMG cycle for the depth and joint steps,
and the small ridge-regularised systems of the pose, LED-offset and lighting steps.

The depth block M (7-point stencil plus 2 tau D^T D, sparse SPD) changes little between a
level's sweeps (only the IRLS weights, albedo and lighting move), so one smoothed-aggregation
hierarchy (pyamg) serves several solves and is rebuilt once CG needs twice the iterations it
first took. The joint step solves the Schur complement ``M - U H^-1 U^T`` with the hierarchy
of M.
"""

from __future__ import annotations

import numpy as np
import pyamg
import scipy.sparse as sp
import scipy.sparse.linalg as spla


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


def pcg(matrix, rhs: np.ndarray, x0: np.ndarray, rtol: float, maxiter: int,
        preconditioner: spla.LinearOperator | None = None) -> tuple[np.ndarray, int]:
    """PCG on ``matrix x = rhs`` ((N, N) sparse SPD or operator) from x0; returns (x, iterations).

    ``preconditioner`` defaults to a fresh AMG hierarchy of ``matrix`` (which must then be sparse).
    """
    precond = preconditioner if preconditioner is not None else amg_preconditioner(matrix)
    count = [0]

    def callback(_):
        count[0] += 1

    x, _ = spla.cg(matrix, rhs, x0=x0, rtol=rtol, maxiter=maxiter, M=precond, callback=callback)
    return x, count[0]


class LevelPreconditioner:
    """The AMG hierarchy of one pyramid level, reused across its depth (or joint) solves."""

    def __init__(self):
        self.cycle: spla.LinearOperator | None = None
        self.baseline: int | None = None  # CG iterations of the hierarchy's first solve

    def solve(self, matrix, rhs: np.ndarray, rtol: float, maxiter: int, sparse_part=None) -> tuple[np.ndarray, int]:
        """PCG from zero on ``matrix`` ((N, N) sparse SPD, or an operator whose sparse part
        ``sparse_part`` the hierarchy is built from); returns (x, iterations)."""
        if self.cycle is None:
            self.cycle = amg_preconditioner(matrix if sparse_part is None else sparse_part)
        x, iterations = pcg(matrix, rhs, np.zeros_like(rhs), rtol, maxiter, self.cycle)
        if self.baseline is None:
            self.baseline = max(iterations, 5)
        elif iterations > 2 * self.baseline:  # the system drifted from the hierarchy's: rebuild next time
            self.cycle = self.baseline = None
        return x, iterations


def ridge_solve(A: np.ndarray, b: np.ndarray, ridge: float = 1e-9) -> np.ndarray | None:
    """Solution of the small SPD system ``(A + ridge trace(A) I) x = b`` (k,), or None where
    it is singular or not finite: the Gauss-Newton steps of the pose, LED offset and lighting."""
    if not np.isfinite(A).all():
        return None
    try:
        return np.linalg.solve(A + ridge * np.trace(A) * np.eye(len(A)), b)
    except np.linalg.LinAlgError:
        return None
