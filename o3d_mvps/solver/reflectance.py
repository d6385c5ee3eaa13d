"""Closed-form albedo and per-frame lighting updates (weighted linear least squares).

Both use IRLS weights from the current residuals, so each step minimises a majoriser of the
robust energy and never increases it.
"""

from __future__ import annotations

import numpy as np

from .kernels import weighted_albedo_sums, weighted_lighting_sums
from .linear import ridge_solve
from .problem import Estimate, Evaluation


def update_albedo(est: Estimate, ev: Evaluation, lam: float) -> np.ndarray:
    """rho_c(p) = sum_i w I~ s / sum_i w s^2, per pixel and channel: (N, 3), w the Cauchy
    IRLS weights of the current residuals."""
    num, den = np.empty_like(est.albedo), np.empty_like(est.albedo)
    weighted_albedo_sums(ev.residual, ev.usable, ev.color, ev.shading, 1.0 / lam, num, den)
    ok = den > 1e-8
    return np.where(ok, num / np.where(ok, den, 1.0), est.albedo)


def update_lighting(est: Estimate, ev: Evaluation, lam: float) -> np.ndarray:
    """l_i = argmin sum_{p,c} w (I~ - rho_c <l, B_i>)^2 per frame: (n, k), B_i the light basis."""
    wr2, wri = np.empty(ev.usable.shape), np.empty(ev.usable.shape)  # sum_c w rho^2, sum_c w rho I~: (n, N)
    weighted_lighting_sums(ev.residual, ev.usable, ev.color, np.ascontiguousarray(est.albedo), 1.0 / lam, wr2, wri)
    lights = est.lights.copy()
    for i in range(lights.shape[0]):
        if ev.usable[i].sum() < 8:
            continue
        m = ev.frame_basis(i)  # (N, k)
        A = (m * wr2[i][:, None]).T @ m
        solution = ridge_solve(A, m.T @ wri[i], ridge=1e-12)
        if solution is not None:
            lights[i] = solution
    return lights
