"""NumPy references of the lighting step's sums, for the CPU and CUDA kernels' tests.

No Open3D here: ``tests/test_cuda_kernels.py`` imports it, and a GPU machine need not have Open3D
(its check is ``tests/test_imports.py``).
"""

from __future__ import annotations

import numpy as np


def weighted_lighting_sums(residual, usable, color, albedo, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """NumPy reference of the lighting's per-pixel weights (what ``kernels.lighting_sums`` sums
    against each frame's basis): wr2 (n, N) = sum_c w rho^2 and wri (n, N) = sum_c w rho I over
    the channels, in float64, with the Cauchy IRLS weight w = usable / (1 + (r / lam)^2) of
    residual (n, N, 3); usable (n, N) bool, colour I (n, N, 3), albedo rho (N, 3)."""
    r, rho, I = (np.asarray(a, dtype=np.float64) for a in (residual, albedo, color))
    w = usable[..., None] / (1.0 + (r / lam) ** 2)
    return np.einsum("inc,nc->in", w, rho**2), np.einsum("inc,nc,inc->in", w, rho, I)
