"""Closed-form albedo and per-frame lighting updates (weighted linear least squares).

Both use IRLS weights from the current residuals, so each step minimises a majoriser of the
robust energy and never increases it.
"""

from __future__ import annotations

import numpy as np

from ..model.arrays import array_module, contiguous
from .device import kernels_for, on_gpu, to_host
from .problem import Estimate, Evaluation


def update_albedo(est: Estimate, ev: Evaluation, lam: float) -> np.ndarray:
    """rho_c(p) = sum_i w I~ s / sum_i w s^2, per pixel and channel: (N, 3), w the Cauchy
    IRLS weights of the current residuals."""
    xp = array_module(est.albedo)
    num, den, out = xp.empty_like(est.albedo), xp.empty_like(est.albedo), xp.empty_like(est.albedo)
    kernels_for(num).albedo_update(ev.residual, ev.usable, ev.color, ev.shading, 1.0 / lam, contiguous(est.albedo),
                                   num, den, out)  # num / den where den > 1e-8, else the albedo (one launch)
    return out


def refit_albedo(problem, est: Estimate, ev: Evaluation) -> Evaluation:
    """``est.albedo`` set to :func:`update_albedo`'s and the evaluation at it written into
    ``ev``'s arrays (``problem.reevaluate(est, ev, overwrite=True)``; ``ev`` is given up): on a
    GPU in one launch (:meth:`.LevelProblem.albedo_reevaluation`), on the host the two steps."""
    if on_gpu(ev.residual):
        return problem.albedo_reevaluation(est, ev)
    est.albedo = update_albedo(est, ev, problem.lam)
    return problem.reevaluate(est, ev, overwrite=True)


def update_lighting(est: Estimate, ev: Evaluation, lam: float, light) -> np.ndarray:
    """The lights (n, k) minimising sum_{i,p,c} w (I~ - rho_c <l_i, B_i>)^2 under the light
    model ``light``'s constraint (:meth:`~.lighting.SHLight.fit`: per frame, or one light for
    all), B_i the light basis; frames with fewer than 8 usable pixels keep their light."""
    xp = array_module(ev.residual)
    albedo = contiguous(est.albedo)
    n, k = est.lights.shape
    gram, rhs = np.zeros((n, k, k)), np.zeros((n, k))
    if on_gpu(ev.residual):  # every frame's system in one launch and one copy (the host's loop: 5 a frame)
        kernels = kernels_for(ev.residual)
        partials = xp.empty((n, kernels.lighting_blocks(ev.usable.shape[1]), k * k + k + 1))
        kernels.lighting_sums(ev.residual, ev.usable, ev.color, albedo, 1.0 / lam, ev.basis, partials)
        sums = to_host(partials).sum(axis=1)  # (n, k k + k + 1)
        gram, rhs, counts = sums[:, :k * k].reshape(n, k, k), sums[:, k * k:k * k + k], sums[:, -1]
        gram[counts < 8], rhs[counts < 8] = 0.0, 0.0
        return light.fit(gram, rhs, est.lights)
    # on the host a frame at a time: the sums of one frame (1, N) each, not of all (2 x 160 MB
    # at 2 MP and 20 frames); the same values
    N = ev.usable.shape[1]
    wr2, wri = np.empty((1, N)), np.empty((1, N))
    # the basis in float64 (transposed, as NumPy's cast inside ``m.T @ wri`` laid it out) and
    # scaled by the weights, in buffers shared by the frames: fresh per frame, each (15 MB at
    # 2 MP) was mapped and faulted in anew (three a frame, with the casts inside the products);
    # the same products on the same layouts, so the same values bit for bit
    basis_t, scaled = None, np.empty((N, k))
    counts = ev.usable.sum(axis=1)
    for i in range(n):
        if counts[i] >= 8:
            frame = slice(i, i + 1)
            kernels_for(wr2).weighted_lighting_sums(ev.residual[frame], ev.usable[frame], ev.color[frame], albedo,
                                                    1.0 / lam, wr2, wri)
            m = ev.frame_basis(i)  # (N, k)
            if m.dtype != np.float64:
                basis_t = np.empty((k, N)) if basis_t is None else basis_t
                basis_t[...] = m.T
                m = basis_t.T
            np.multiply(m, wr2[0][:, None], out=scaled)
            gram[i], rhs[i] = scaled.T @ m, m.T @ wri[0]
    return light.fit(gram, rhs, est.lights)
