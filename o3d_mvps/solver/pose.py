"""Pose update: robust Gauss-Newton on the twist of each frame (like dense visual odometry)."""

from __future__ import annotations

import numpy as np

from ..model import se3
from ..model.robust import cauchy_weights
from .problem import Estimate, FrameSample, LevelProblem


def pose_jacobian(sample: FrameSample, K: np.ndarray) -> np.ndarray:
    """d(warped colour)/d(xi) for a left update exp(xi) T: (N, 3, 6), xi = (v, w)."""
    X, Y, Z = sample.points[:, 0], sample.points[:, 1], sample.points[:, 2]
    iz = 1.0 / Z
    a = sample.grad_u * (K[0, 0] * iz)[:, None]  # (N, 3): dI/dX'
    b = sample.grad_v * (K[1, 1] * iz)[:, None]  # dI/dY'
    c = -(a * (X * iz)[:, None] + b * (Y * iz)[:, None])  # dI/dZ'
    g = np.stack([a, b, c], axis=-1)  # (N, 3, 3): per channel, gradient wrt the frame point
    rot = np.cross(sample.points[:, None, :], g)  # P' x g
    return np.concatenate([g, rot], axis=-1)


def update_pose(problem: LevelProblem, est: Estimate, i: int, points_ref: np.ndarray, shading: np.ndarray,
                iterations: int, max_halvings: int = 4) -> np.ndarray:
    """Refine frame i's pose (4x4) with IRLS Gauss-Newton; never increases its data energy."""
    K = problem.level.K
    model = est.albedo * shading[:, None]
    pose = est.poses[i]
    sample = problem.sample(i, pose, points_ref)
    energy = problem.frame_data_energy(sample, est.albedo, shading)
    for _ in range(iterations):
        use = sample.usable
        if use.sum() < 12:
            break
        r = (sample.color - model)[use]
        w = cauchy_weights(r, problem.lam)
        J = pose_jacobian(problem.sample_gradients(i, sample, use), K).reshape(-1, 6)
        wJ = J * w.reshape(-1, 1)
        H = wJ.T @ J
        g = wJ.T @ r.reshape(-1)
        try:
            step = -np.linalg.solve(H + 1e-9 * np.trace(H) * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        accepted = False
        for _ in range(max_halvings + 1):
            trial_pose = se3.exp(step) @ pose
            trial = problem.sample(i, trial_pose, points_ref)
            trial_energy = problem.frame_data_energy(trial, est.albedo, shading)
            if trial_energy <= energy:
                pose, sample, energy, accepted = trial_pose, trial, trial_energy, True
                break
            step = 0.5 * step
        if not accepted or np.linalg.norm(step) < 1e-10:
            break
    return pose


def update_poses(problem: LevelProblem, est: Estimate, iterations: int) -> np.ndarray:
    """All frames' refined poses (n, 4, 4); frame 0 (the reference) stays the identity."""
    points_ref = problem.points(est.z)
    normals, _ = problem.normals(est.z)
    poses = est.poses.copy()
    for i in range(1, problem.n_frames):
        shading = est.lights[i, 0] + normals @ est.lights[i, 1:]
        poses[i] = update_pose(problem, est, i, points_ref, shading, iterations)
    return poses
