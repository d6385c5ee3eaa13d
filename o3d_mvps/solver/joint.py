"""Joint pose-depth step: one Gauss-Newton step on z and every frame's twist together.

Alternating the pose and depth updates creeps along the valley where they trade off (a
frame's rotation about the object against a bend of the surface): each update sees the other
unknowns frozen, so the poses converged at ~7 % per sweep on the finest level. This step
linearises the robust energy in both at once (:func:`~.normal_equations.joint_system`, with the
warp's parallax in the depth rows and the albedo projected out), solves the Schur complement
``M - U H^-1 U^T`` (M Levenberg-damped: :func:`.linear.levenberg_damped`) by CG preconditioned
with AMG on M, recovers the twists, and takes a backtracking line search on the true energy
(:mod:`.line_search`), so every accepted step lowers it.
"""

from __future__ import annotations

import dataclasses

from ..model import se3
from .depth import search_estimates, stepped_depth
from .linear import levenberg_damped, solve_spd
from .normal_equations import joint_system
from .pose_trust import PoseAnchors
from .problem import Estimate, Evaluation, LevelProblem


def update_pose_depth(problem: LevelProblem, est: Estimate, ev: Evaluation, *, rtol: float, maxiter: int,
                      project_albedo: bool = True, max_halvings: int = 5,
                      anchors: PoseAnchors | None = None) -> tuple[Estimate, Evaluation, int]:
    """One joint step on z and the twists (and, with ``project_albedo``, the albedo refitted at
    every trial): returns (estimate, its evaluation, CG iterations); never raises the energy
    (returns ``est`` unchanged when no step length lowers it). ``ev``, the evaluation of
    ``est``, is released once read (:meth:`.Evaluation.release`). anchors: with given poses,
    their prior enters the twists' block (:meth:`.pose_trust.PoseAnchors.prior_system`), so the
    step does not slide a frame along the images' weak directions."""
    energy = ev.energy
    # ev released once read: not held while the matrices are formed, nor through the solve and line search
    system = joint_system(problem, est, ev, project_albedo=project_albedo, release=True)
    system = dataclasses.replace(system, matrix=levenberg_damped(system.matrix, overwrite=True))
    if anchors is not None:
        priors = ((k, anchors.prior_system(i, est.poses[i])) for k, i in enumerate(system.frames))
        system.add_priors([(k, *prior) for k, prior in priors if prior is not None])
    S, rhs = system.schur_operator()
    dz, iterations = solve_spd(S, rhs, rtol, maxiter, sparse_part=system.matrix, pixel_prolongations=problem.pixel_prolongations)
    xi, frames = system.twists(dz), system.frames
    del system, S, rhs  # the coupling (N, 6m) and M: not needed by the line search

    def moved(t: float):
        z = stepped_depth(problem.level.prior, est.z, t, dz)  # (one launch and one read on a GPU)
        if z is None:
            return None
        poses = est.poses.copy()
        for i, x in zip(frames, xi):
            poses[i] = se3.exp(t * x) @ est.poses[i]
        return Estimate(z, est.albedo, est.lights, poses, est.led_offset)

    return (*search_estimates(problem, est, energy, moved, max_halvings, refit_albedo=project_albedo), iterations)

