"""Depth update: the paper's depth step with the warp frozen at the previous z.

The Gauss-Newton normal equations of :func:`~.normal_equations.joint_system` without parallax
or twists (frozen dA and light field, albedo projected out), ``M dz = b`` with M sparse SPD
(7-point stencil plus 2 tau D^T D, Levenberg-damped: :func:`.linear.levenberg_damped`), solved
by AMG-preconditioned CG (:mod:`.linear`), then a backtracking line search on the true energy
(:mod:`.line_search`).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..model.arrays import array_module, contiguous
from .device import kernels_for, on_gpu, to_host
from .kernels import extrapolation_blocks
from .line_search import backtrack
from .linear import levenberg_damped, solve_spd
from .normal_equations import joint_system
from .problem import Estimate, Evaluation, LevelProblem
from .reflectance import refit_albedo as refit_albedo_at


def update_depth(problem: LevelProblem, est: Estimate, ev: Evaluation, *, rtol: float, maxiter: int,
                 project_albedo: bool = True, parallax: bool = False,
                 max_halvings: int = 5, plain: bool = False) -> tuple[Estimate, Evaluation, int]:
    """One depth step (warp frozen, or with ``parallax`` linearised in z like the joint step's
    depth rows; with ``project_albedo`` the albedo eliminated and refitted at every trial):
    returns (estimate, its evaluation, CG iterations); never raises the energy. ``ev``, the
    evaluation of ``est``, is released once read (:meth:`.Evaluation.release`). plain: solved
    with the plain-aggregation hierarchy (:func:`.linear.plain_aggregation`), for levels whose
    poses do not move (a static camera's, a held finest level's: no twists that its rounding
    could reach)."""
    energy = ev.energy
    # ev released once read: not held while the matrices are formed, nor through the solve and line search
    system = joint_system(problem, est, ev, parallax=parallax, twists=False, project_albedo=project_albedo,
                          release=True)
    step, iterations = solve_spd(levenberg_damped(system.matrix, overwrite=True), system.rhs_z, rtol, maxiter,
                                 pixel_prolongations=problem.pixel_prolongations, plain=plain)
    del system

    def moved(t: float):
        z = stepped_depth(problem.level.prior, est.z, t, step)
        return None if z is None else Estimate(z, est.albedo, est.lights, est.poses, est.led_offset)

    return (*search_estimates(problem, est, energy, moved, max_halvings, refit_albedo=project_albedo), iterations)


def search_estimates(problem: LevelProblem, est: Estimate, energy: float, moved: Callable[[float], Estimate | None],
                     max_halvings: int, *, refit_albedo: bool = False) -> tuple[Estimate, Evaluation]:
    """Backtrack from ``est`` (of energy ``energy``) along ``moved(t)``, the estimate at step
    length t (None where invalid), on the true energy; returns the accepted (estimate,
    evaluation), or ``est`` evaluated anew when no length lowers the energy (its evaluation
    was released for the solve: see :meth:`.Evaluation.release`).

    refit_albedo: give each trial its closed-form albedo (:func:`.reflectance.refit_albedo`) first.
    """

    def trial(t: float):
        candidate = moved(t)
        if candidate is None:
            return None
        candidate_ev = problem.evaluate_refit(candidate) if refit_albedo else None  # one launch on a GPU
        if candidate_ev is None:  # refitted at once: the energy at the old albedo is not read
            candidate_ev = problem.evaluate(candidate, scored=not refit_albedo)
            if refit_albedo:
                candidate_ev = refit_albedo_at(problem, candidate, candidate_ev)
        return (candidate, candidate_ev), candidate_ev.energy

    found = backtrack(trial, energy, max_halvings)
    return (est, problem.evaluate(est)) if found is None else found[1]


def stepped_depth(prior, z: np.ndarray, t: float, dz: np.ndarray) -> np.ndarray | None:
    """A line search's trial depth ``prior.clip(z + t dz)`` (N,) metres (``prior`` the level's
    :class:`.pyramid.DepthPrior`), or None where a depth is not > 0; on a GPU one launch and one
    read (:func:`.kernels.depth_step`; was up to five array operations and a read), no read
    where the envelope is positive (:attr:`.pyramid.DepthPrior.envelope_positive`: every
    clipped depth is > 0 or NaN, and a NaN depth's energy is NaN, which the search rejects)."""
    if not on_gpu(z):
        stepped = prior.clip(z + t * dz)
        return stepped if np.all(stepped > 0) else None
    xp = array_module(z)
    out, bad = xp.empty(z.shape[0]), xp.empty(extrapolation_blocks(z.shape[0]))
    kernels_for(z).depth_step(contiguous(z, np.float64), contiguous(dz, np.float64), float(t),
                              *envelope_arrays(prior, xp), out, bad)
    if getattr(prior, "envelope_positive", False):  # clipped into a positive envelope: no read (gpueval2)
        return out
    return out if to_host(bad).sum() == 0 else None


def envelope_arrays(prior, xp) -> tuple:
    """The depth envelope (lower, upper) of ``prior`` (:class:`.pyramid.DepthPrior`) as the
    kernels take it: C-contiguous float64 (N,) each, or empty (0,) arrays of ``xp`` (NumPy or
    CuPy) without one."""
    if prior.lower is None:
        return xp.empty(0), xp.empty(0)
    return contiguous(prior.lower, np.float64), contiguous(prior.upper, np.float64)
