"""Cauchy M-estimator and its IRLS weights.

``phi(r) = lam^2 / 2 * log(1 + r^2 / lam^2)``; ``w(r) = phi'(r) / r = 1 / (1 + r^2 / lam^2)``.
``phi(r) <= phi(r_k) + w(r_k) / 2 * (r^2 - r_k^2)``, so a weighted least-squares step with
weights w(r_k) / 2 never increases the robust energy (majorise-minimise).
"""

from __future__ import annotations

import numpy as np


def cauchy(r: np.ndarray, lam: float) -> np.ndarray:
    """phi(r), elementwise (computed in one temporary: the solver applies it to (n, N, 3) arrays)."""
    out = np.asarray(np.square(np.multiply(r, 1.0 / lam)))  # 0-d for a scalar r, so out= works
    np.log1p(out, out=out)
    out *= 0.5 * lam * lam
    return out


def cauchy_weights(r: np.ndarray, lam: float) -> np.ndarray:
    """IRLS weights w(r) = 1 / (1 + r^2 / lam^2), elementwise, in (0, 1]."""
    out = np.asarray(np.square(np.multiply(r, 1.0 / lam)))  # 0-d for a scalar r, so out= works
    out += 1.0
    return np.reciprocal(out, out=out)


def cauchy_energy(r: np.ndarray, lam: float) -> float:
    """sum phi(r) over all elements: the energy of a residual array.

    The logarithms are taken in float32 (``log(1 + x)``, relative error ~1e-7 a term, where a
    term below 6e-8 lam^2 rounds to zero) and summed in float64: on the solver's (n, N, 3)
    arrays that is six times faster than float64 ``log1p``, and the line searches compare
    energies far more different than that.
    """
    x = np.square(np.multiply(r, 1.0 / lam, dtype=np.float32))
    x += 1.0
    np.log(x, out=x)
    return 0.5 * lam * lam * float(np.sum(x, dtype=np.float64))
