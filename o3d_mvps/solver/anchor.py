"""Rigid re-anchoring: move the whole reconstruction against the reference camera.

Moving the surface by a rigid G (in reference coordinates) and every other frame's pose by
``T_i G^-1`` leaves frames 1..n-1 seeing the same surface points with the same albedo: their
data terms do not change. Only the reference frame (whose pose is fixed at the identity and
whose pixels index depth and albedo) and the depth prior see G. The other updates cannot move
along this direction (the joint step would need to shift the albedo with the surface), so the
reconstruction drifted by ~0.4 deg about the object as a whole; this step solves for G with
Gauss-Newton on the reference frame's data and the prior, and keeps it only if the full
energy drops.

Depth and albedo are carried to the moved surface to first order: a pixel p now sees what
p - dp saw, dp (N, 2) the pixel motion of the surface point at p.
"""

from __future__ import annotations

import numpy as np

from ..model import se3
from ..model.robust import cauchy_weights
from .depth import backtracking_search
from .problem import Estimate, Evaluation, LevelProblem


def moved_estimate(problem: LevelProblem, est: Estimate, xi: np.ndarray) -> Estimate:
    """``est`` with its surface moved by exp(xi) (xi (6,) twist in reference coordinates) and
    poses 1..n-1 moved by its inverse; depth and albedo resampled to first order."""
    grid, K = problem.level.grid, problem.level.K
    G = se3.exp(xi)
    moved = problem.points(est.z) @ G[:3, :3].T + G[:3, 3]
    du = K[0, 0] * moved[:, 0] / moved[:, 2] + K[0, 2] - grid.u
    dv = K[1, 1] * moved[:, 1] / moved[:, 2] + K[1, 2] - grid.v

    def shifted(values: np.ndarray) -> np.ndarray:
        value_u, value_v = grid.gradient(values)
        return values - (value_u * du + value_v * dv)

    albedo = np.stack([shifted(est.albedo[:, c]) for c in range(est.albedo.shape[1])], axis=1)
    poses = est.poses.copy()
    poses[1:] = est.poses[1:] @ np.linalg.inv(G)
    return Estimate(shifted(moved[:, 2]), albedo, est.lights, poses)


def _reference_residuals(problem: LevelProblem, est: Estimate, ev: Evaluation, xi: np.ndarray):
    """The reference frame's residuals (M*3,) and the prior's (rows,) after moving by xi."""
    moved = moved_estimate(problem, est, xi)
    normals, _ = problem.normals(moved.z)
    shading = problem.frame_shading(moved.lights[0], normals, problem.points(moved.z), moved.poses[0])
    data = (ev.color[0] - moved.albedo * shading[:, None])[ev.usable[0]].ravel()
    prior = problem.level.prior
    return data, prior.D @ moved.z - prior.z0


def update_anchor(problem: LevelProblem, est: Estimate, ev: Evaluation, *, step: float = 1e-6,
                  max_halvings: int = 1) -> tuple[Estimate, Evaluation]:
    """One Gauss-Newton step on G (finite-difference Jacobian, ``step`` in metres and radians);
    returns the moved (estimate, evaluation), or the inputs when no step length lowers the energy."""
    data, prior = _reference_residuals(problem, est, ev, np.zeros(6))
    J_data, J_prior = np.empty((data.size, 6)), np.empty((prior.size, 6))
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = step
        moved_data, moved_prior = _reference_residuals(problem, est, ev, xi)
        J_data[:, k] = (moved_data - data) / step
        J_prior[:, k] = (moved_prior - prior) / step
    w = cauchy_weights(data, problem.lam)[:, None]
    two_tau = 2.0 * problem.tau
    H = (w * J_data).T @ J_data + two_tau * J_prior.T @ J_prior
    g = (w * J_data).T @ data + two_tau * J_prior.T @ prior
    if not np.isfinite(H).all() or np.trace(H) <= 0:
        return est, ev
    xi = -np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(6), g)

    def trial(t: float):
        moved = moved_estimate(problem, est, t * xi)
        return moved if np.all(moved.z > 0) else None

    found = backtracking_search(problem, ev, trial, max_halvings)
    return (est, ev) if found is None else found
