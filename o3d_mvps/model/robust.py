"""Cauchy M-estimator and its IRLS weights.

``phi(r) = lam^2 / 2 * log(1 + r^2 / lam^2)``; ``w(r) = phi'(r) / r = 1 / (1 + r^2 / lam^2)``.
``phi(r) <= phi(r_k) + w(r_k) / 2 * (r^2 - r_k^2)``, so a weighted least-squares step with
weights w(r_k) / 2 never increases the robust energy (majorise-minimise).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .arrays import array_module, contiguous, fused


def cauchy(r: np.ndarray, lam: float) -> np.ndarray:
    """phi(r), elementwise (computed in one temporary: the solver applies it to (n, N, 3) arrays;
    NumPy or CuPy)."""
    out = array_module(r).asarray(np.square(np.multiply(r, 1.0 / lam)))  # 0-d for a scalar r, so out= works
    np.log1p(out, out=out)
    out *= 0.5 * lam * lam
    return out


def cauchy_weights(r: np.ndarray, lam: float) -> np.ndarray:
    """IRLS weights w(r) = 1 / (1 + r^2 / lam^2), elementwise, in (0, 1] (NumPy, or CuPy: one
    fused kernel)."""
    if array_module(r) is not np:
        return _cauchy_weights(r, 1.0 / lam)
    out = array_module(r).asarray(np.square(np.multiply(r, 1.0 / lam)))  # 0-d for a scalar r, so out= works
    out += 1.0
    return np.reciprocal(out, out=out)


@fused
def _cauchy_weights(r, inv_lam):
    """:func:`cauchy_weights` of r with inv_lam = 1 / lam (one kernel on a GPU)."""
    y = r * inv_lam
    return 1.0 / (y * y + 1.0)


def cauchy_energy(r: np.ndarray, lam: float, kernel=None) -> float:
    """sum phi(r) over all elements: the energy of a residual array (any shape; float32 or float64,
    others are converted).

    kernel: the ``log1p_square_sum(x (M,), scale) -> sum log(1 + (scale x)^2)`` of the array's
    device (default: :func:`log1p_square_sum`, the CPU's, for NumPy arrays; the solver's
    ``kernels_for(r)`` gives it).

    One compiled parallel pass (:func:`log1p_square_sum`): a logarithm per :data:`LOG_BLOCK`
    terms, summed in float64, equal to the float32 logarithm of each term (the GPU's) to ~1e-10
    of the sum; the line searches compare energies far more different than that. NumPy's
    version made two temporaries of the solver's (n, N, 3) residuals and took most of an
    evaluation's time.
    """
    r = contiguous(r)
    flat = (r if r.dtype in (np.float32, np.float64) else r.astype(np.float64)).reshape(-1)
    return 0.5 * lam * lam * (kernel or log1p_square_sum)(flat, 1.0 / lam)


@numba.njit(inline="always")
def log1p_square_term(x, scale):  # pragma: no cover - compiled
    """log(1 + (scale x)^2) of one float64 x, in float32 (:func:`log1p_square_sum`'s term; the
    CUDA twin in :mod:`o3d_mvps.solver.cuda_kernels` calls it too)."""
    y = np.float32(x * scale)
    return math.log(np.float32(1.0) + y * y)


#: terms whose factors ``1 + y^2`` :func:`log1p_square_sum` multiplies before one logarithm
LOG_BLOCK = 8


@numba.njit(inline="always")
def square_factor(x, scale):  # pragma: no cover - compiled
    """1 + y^2 in float64 of y = float32(scale x), the y of :func:`log1p_square_term`."""
    y = np.float64(np.float32(x * scale))
    return 1.0 + y * y


@numba.njit(parallel=True, cache=True, fastmath=True)
def log1p_square_sum(x, scale):  # pragma: no cover - compiled
    """sum log(1 + (scale x)^2) over a 1-D array x: a float.

    y = float32(scale x) as in :func:`log1p_square_term` (the GPU's term), but the logarithm of
    the float64 product of :data:`LOG_BLOCK` factors ``1 + y^2`` per block instead of a float32
    logarithm per term: no scalar logarithm per element (numba's are not vectorised without
    SVML), 1.2-3.5x faster on 5.4 M float32 residuals (3.5x where 30 % are zero: the float32
    logarithm branches on them), more accurate (the product's rounding is ~1e-16; the float32
    logarithms' ~1e-7 a term) and equal to the per-term sum to ~1e-10 of it. The product cannot overflow where the per-term sum is finite: each factor is
    then below the float32 maximum 3.4e38, and 8 of them below 1.7e307."""
    blocks = x.size // LOG_BLOCK
    total = 0.0
    for b in numba.prange(blocks):
        product = 1.0
        for k in range(b * LOG_BLOCK, (b + 1) * LOG_BLOCK):
            product *= square_factor(x[k], scale)
        total += math.log(product)
    for k in range(blocks * LOG_BLOCK, x.size):
        total += math.log(square_factor(x[k], scale))
    return total


#: smallest scale :func:`robust_scale` returns (linear intensity): residuals of noiseless,
#: exactly modelled data are all ~0, and lambda -> 0 would weight every pixel out
MIN_SCALE = 1e-3


def nan_median(values: np.ndarray) -> np.ndarray:
    """The median over the first axis of floating-point ``values`` (k, ...) of its non-NaN
    entries (NaN where there are none; values' dtype), as ``np.nanmedian(values, axis=0)`` gives,
    by one sort (NaN sorts last): the mean of the ((c - 1) // 2)-th and (c // 2)-th of the c
    measured values. NumPy's masked path for few rows is several times slower, and warns on
    empty slices."""
    values = np.asarray(values)
    counts = (~np.isnan(values)).sum(axis=0)
    ordered = np.sort(values, axis=0)
    lower = np.take_along_axis(ordered, ((np.maximum(counts, 1) - 1) // 2)[None], axis=0)[0]
    upper = np.take_along_axis(ordered, (counts // 2)[None], axis=0)[0]
    return (lower + upper) / 2


def robust_scale(residual: np.ndarray, usable: np.ndarray, max_samples: int = 1_000_000) -> float:
    """1.4826 x the median absolute deviation of the usable residuals: their standard deviation
    where they are Gaussian, unmoved by outliers. residual (n, N, 3), usable (n, N); at most
    ``max_samples`` evenly spaced pixels per frame are read (no copy of the whole array).
    Not below :data:`MIN_SCALE`."""
    stride = max(1, residual.shape[1] // max_samples)
    r = residual[:, ::stride][usable[:, ::stride]].ravel()
    if r.size == 0:
        return MIN_SCALE
    return max(MIN_SCALE, 1.4826 * float(np.median(_absolute_deviations(r, np.median(r)))))


@fused
def _absolute_deviations(r, centre):
    """``|r - centre|`` elementwise (one kernel on a GPU; CuPy's fusion has no builtin ``abs``)."""
    return array_module(r).abs(r - centre)
