"""Joint pose-depth step: one Gauss-Newton step on z and every frame's twist together.

Alternating the pose and depth updates creeps along the valley where they trade off (a
frame's rotation about the object against a bend of the surface): each update sees the other
unknowns frozen, so the poses converged at ~7 % per sweep on the finest level. This step
linearises the robust energy in both at once (:func:`~.normal_equations.joint_system`, with the
warp's parallax in the depth rows and the albedo projected out), solves the Schur complement
``M - U H^-1 U^T`` (M Levenberg-damped: :func:`.linear.levenberg_damped`) by CG preconditioned
with AMG on M (on levels of up to :data:`REUSE_HIERARCHY_MAX_PIXELS` pixels the first step's
prolongations kept for the level's next steps), recovers the twists, and takes a backtracking line search on the true energy
(:mod:`.line_search`), so every accepted step lowers it.
"""

from __future__ import annotations

import dataclasses
import weakref

from ..model import se3
from .depth import search_estimates, stepped_depth
from .device import on_gpu
from .linear import galerkin_hierarchy, levenberg_damped, smoothed_aggregation, solve_spd
from .normal_equations import joint_system
from .pose_trust import PoseAnchors
from .problem import Estimate, Evaluation, LevelProblem


#: Levels of up to this many object pixels keep the AMG hierarchy of their first joint step for
#: the next ones, made over for each step's depth block (:func:`.linear.galerkin_hierarchy`: the
#: prolongations kept, the coarse matrices formed anew), instead of a fresh set-up per step (86-103
#: ms of serial work at the D415's 89 619 pixels; made over: 50 ms by scipy's products, 18 ms from
#: the second time on, into the held patterns). The depth block's pattern
#: stays the same through a level, and its values change little between steps: the D415 render's
#: joint steps took the same CG iterations (4-5) as with fresh hierarchies, and its result moved
#: by 1e-6 deg and 1e-6 mm. A hierarchy kept whole (no coarse matrices formed anew) let CG run
#: to 22-48 iterations. Larger levels keep a fresh set-up: on the 2 MP render's two finest
#: levels (240k and 958k pixels) kept prolongations took other, worse steps
#: (docs/performance.md, "2 MP joint step: AMG set-up per sweep"), and they would be held
#: through the next assembly (P and R, some 15 MB at D415 size).
REUSE_HIERARCHY_MAX_PIXELS = 150_000
#: ... and a step whose CG took more than this many iterations over its level's fresh set-up
#: drops the kept hierarchy (the next step sets up anew)
REUSE_EXTRA_ITERATIONS = 2

# per level problem: (its kept hierarchy, finest matrix let go; the CG iterations of its fresh set-up)
_kept_hierarchies: "weakref.WeakKeyDictionary[LevelProblem, tuple]" = weakref.WeakKeyDictionary()


def _hierarchy(problem: LevelProblem, matrix) -> tuple:
    """(the AMG hierarchy for the joint step's depth block ``matrix`` (N, N) on the host, the CG
    iterations of the fresh set-up it was made over from, or None where it is fresh), or
    (None, None) where the linear solve builds its own (a GPU, a level of more than
    :data:`REUSE_HIERARCHY_MAX_PIXELS` pixels). Takes the level's kept hierarchy over."""
    if on_gpu(matrix.data) or matrix.shape[0] > REUSE_HIERARCHY_MAX_PIXELS:
        return None, None
    kept = _kept_hierarchies.pop(problem, None)
    if kept is not None and len(kept[0].levels) > 1 and kept[0].levels[0].P.shape[0] == matrix.shape[0]:
        return galerkin_hierarchy(kept[0], matrix), kept[1]
    return smoothed_aggregation(matrix), None


def _keep_hierarchy(problem: LevelProblem, hierarchy, fresh: int | None, iterations: int) -> None:
    """Keep ``hierarchy`` for the level's next joint step, its finest matrix (this step's depth
    block) let go, unless its CG ``iterations`` exceeded those of the fresh set-up it was made
    over from (``fresh``; None: it is fresh) by more than :data:`REUSE_EXTRA_ITERATIONS`."""
    if fresh is not None and iterations > fresh + REUSE_EXTRA_ITERATIONS:
        return
    hierarchy.levels[0].A = None
    _kept_hierarchies[problem] = (hierarchy, iterations if fresh is None else fresh)


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
    hierarchy, fresh = _hierarchy(problem, system.matrix)
    dz, iterations = solve_spd(S, rhs, rtol, maxiter, sparse_part=system.matrix,
                               pixel_prolongations=problem.pixel_prolongations, hierarchy=hierarchy)
    if hierarchy is not None:
        _keep_hierarchy(problem, hierarchy, fresh, iterations)
    del hierarchy
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

