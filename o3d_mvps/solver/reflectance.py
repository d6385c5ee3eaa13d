"""Closed-form albedo and per-frame lighting updates (weighted linear least squares).

Both use IRLS weights from the current residuals, so each step minimises a majoriser of the
robust energy and never increases it.
"""

from __future__ import annotations

import numpy as np

from ..model.robust import cauchy_weights
from .linear import ridge_solve
from .problem import Estimate, Evaluation


def update_albedo(est: Estimate, ev: Evaluation, lam: float) -> np.ndarray:
    """rho_c(p) = sum_i w I~ s / sum_i w s^2, per pixel and channel: (N, 3)."""
    w = cauchy_weights(ev.residual, lam) * ev.usable[..., None]  # (n, N, 3)
    s = ev.shading[..., None]
    num = np.sum(w * ev.color * s, axis=0)
    den = np.sum(w * s * s, axis=0)
    ok = den > 1e-8
    return np.where(ok, num / np.where(ok, den, 1.0), est.albedo)


def update_lighting(est: Estimate, ev: Evaluation, lam: float) -> np.ndarray:
    """l_i = argmin sum_{p,c} w (I~ - rho_c <l, B_i>)^2 per frame: (n, k), B_i the light basis."""
    w = cauchy_weights(ev.residual, lam) * ev.usable[..., None]  # (n, N, 3)
    wr2 = np.einsum("inc,nc->in", w, est.albedo**2)  # (n, N)
    wri = np.einsum("inc,nc,inc->in", w, est.albedo, ev.color)
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
