"""Closed-form albedo and per-frame lighting updates (weighted linear least squares).

Both use IRLS weights from the current residuals, so each step minimises a majoriser of the
robust energy and never increases it.
"""

from __future__ import annotations

import numpy as np

from ..model.arrays import array_module, contiguous
from .device import kernels_for, to_host
from .problem import Estimate, Evaluation


def update_albedo(est: Estimate, ev: Evaluation, lam: float) -> np.ndarray:
    """rho_c(p) = sum_i w I~ s / sum_i w s^2, per pixel and channel: (N, 3), w the Cauchy
    IRLS weights of the current residuals."""
    xp = array_module(est.albedo)
    num, den, out = xp.empty_like(est.albedo), xp.empty_like(est.albedo), xp.empty_like(est.albedo)
    kernels_for(num).albedo_update(ev.residual, ev.usable, ev.color, ev.shading, 1.0 / lam, contiguous(est.albedo),
                                   num, den, out)  # num / den where den > 1e-8, else the albedo (one launch)
    return out


def refit_albedo(problem, est: Estimate, ev: Evaluation, *, scored: bool = True) -> Evaluation:
    """``est.albedo`` set to :func:`update_albedo`'s and the evaluation at it written into
    ``ev``'s arrays (``problem.reevaluate(est, ev, overwrite=True)``; ``ev`` is given up), in one
    pass (:meth:`.LevelProblem.albedo_reevaluation`: one launch on a GPU, one compiled pass on
    the host). ``scored`` False: without its data energy on the host, for a caller that refits the
    lights next (the energy reads then raise)."""
    return problem.albedo_reevaluation(est, ev, scored=scored)


def update_lighting(est: Estimate, ev: Evaluation, lam: float, light) -> np.ndarray:
    """The lights (n, k) minimising sum_{i,p,c} w (I~ - rho_c <l_i, B_i>)^2 under the light
    model ``light``'s constraint (:meth:`~.lighting.SHLight.fit`: per frame, or one light for
    all), B_i the light basis; frames with fewer than 8 usable pixels keep their light.

    Every frame's system in one compiled pass (:func:`.kernels.lighting_sums`; on a GPU one launch
    and one copy): on the host it replaced a loop of five passes a frame (the IRLS weights'
    sums, a cast and a scaling of the basis, two BLAS products): 2 MP, 20 frames 0.33 -> 0.19 CPU s
    a call (one thread), the same systems to round-off (their sums in another order)."""
    xp = array_module(ev.residual)
    n, k = est.lights.shape
    kernels = kernels_for(ev.residual)
    partials = xp.empty((n, kernels.lighting_blocks(ev.usable.shape[1]), k * k + k + 1))
    kernels.lighting_sums(ev.residual, ev.usable, ev.color, contiguous(est.albedo), 1.0 / lam, ev.basis, partials)
    sums = to_host(partials).sum(axis=1)  # (n, k k + k + 1)
    gram, rhs, counts = sums[:, :k * k].reshape(n, k, k), sums[:, k * k:k * k + k], sums[:, -1]
    gram[counts < 8], rhs[counts < 8] = 0.0, 0.0
    return light.fit(gram, rhs, est.lights)
