"""Pose update: robust Gauss-Newton on the twist of each frame (like dense visual odometry)."""

from __future__ import annotations

import numpy as np

from ..model import se3
from ..model.arrays import array_module, like
from ..model.robust import cauchy_weights
from .device import to_host_together
from .kernels import pose_sums
from .line_search import backtrack
from .linear import ridge_solve
from .pose_trust import PoseAnchors, PoseLog
from .problem import Estimate, Evaluation, FrameGradients, FrameSample, LevelProblem


def pose_jacobian(gradients: FrameGradients, K: np.ndarray) -> np.ndarray:
    """d(warped colour)/d(xi) for a left update exp(xi) T: (N, 3, 6), xi = (v, w)."""
    X, Y, Z = (c[:, None] for c in gradients.points.T)  # (N, 1) each
    iz = 1.0 / Z
    J = array_module(gradients.grad_u).empty(gradients.grad_u.shape + (6,))
    a = np.multiply(gradients.grad_u, K[0, 0] * iz, out=J[..., 0])  # (N, 3): dI/dX'
    b = np.multiply(gradients.grad_v, K[1, 1] * iz, out=J[..., 1])  # dI/dY'
    c = np.multiply(-iz, a * X + b * Y, out=J[..., 2])  # dI/dZ'
    J[..., 3] = Y * c - Z * b  # rotation part: P' x (a, b, c)
    J[..., 4] = Z * a - X * c
    J[..., 5] = X * b - Y * a
    return J


def update_pose(problem: LevelProblem, est: Estimate, i: int, points_ref: np.ndarray, normals: np.ndarray,
                iterations: int, max_halvings: int = 4, tolerance: float = 0.0) -> np.ndarray:
    """Refine frame i's pose (4x4) with IRLS Gauss-Newton; never increases its data energy.

    points_ref (N, 3) and unit normals (N, 3) are the reference surface. Stops early once an
    iteration lowers the frame's energy by less than ``tolerance`` (relative).
    """
    return refine_pose(problem, est, i, points_ref, normals, iterations, max_halvings, tolerance)[0]


def pose_system(problem: LevelProblem, est: Estimate, i: int, pose: np.ndarray, sample: FrameSample,
                points_ref: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(H (6, 6), g (6,)) on the host: frame i's robust (IRLS) Gauss-Newton terms of its
    photometric energy for a left update exp(xi) ``pose``, from its ``sample`` (the frame seen
    from the reference points (N, 3) with unit normals (N, 3)); None under 12 usable pixels.
    With a light model whose shading depends on the pose (the LED), the shading's derivative
    enters the Jacobian."""
    use = sample.usable
    if use.sum() < 12:
        return None
    model, light, albedo = problem.light_model(est), est.lights[i], est.albedo
    points = points_ref[use]
    shading = model.basis(normals[use], points, pose) @ like(light, points)
    if array_module(points) is np:  # the Jacobian and the sums in one compiled pass
        gradients = problem.warped_gradients(i, pose, points)
        dshading = model.shading_jacobian(light, normals[use], points, pose)
        H, g = np.empty((6, 6)), np.empty(6)
        pose_sums(gradients.points, gradients.grad_u, gradients.grad_v, problem.level.K, sample.color[use],
                   np.ascontiguousarray(albedo[use], dtype=np.float64), shading,
                   np.zeros((1, 6)) if dshading is None else np.ascontiguousarray(dshading, dtype=np.float64),
                   dshading is not None, 1.0 / problem.lam, H, g)
        return H, g
    r = sample.color[use] - albedo[use] * shading[:, None]
    w = cauchy_weights(r, problem.lam)
    J = pose_jacobian(problem.warped_gradients(i, pose, points), problem.level.K)
    dshading = model.shading_jacobian(light, normals[use], points, pose)
    if dshading is not None:
        J -= albedo[use][:, :, None] * dshading[:, None, :]
    J = J.reshape(-1, 6)
    wJ = J * w.reshape(-1, 1)
    return to_host_together(wJ.T @ J, wJ.T @ r.reshape(-1))  # on a GPU one copy for both


def pose_information(problem: LevelProblem, est: Estimate, ev: Evaluation) -> np.ndarray:
    """(n, 6): each frame's photometric curvature along the six twist axes (the diagonal of
    :func:`pose_system`'s H, energy per (metre or radian)^2) at its current pose; frame 0 and
    frames with under 12 usable pixels: 0. What a frame's images say about its pose, the scale
    a prior towards given poses is measured against (:meth:`.pose_trust.PoseAnchors.calibrate`)."""
    points_ref = problem.points(est.z)
    information = np.zeros((problem.n_frames, 6))
    for i in range(1, problem.n_frames):
        system = pose_system(problem, est, i, est.poses[i], FrameSample(ev.color[i], ev.usable[i]), points_ref,
                             ev.normals)
        if system is not None:
            information[i] = np.diag(system[0])
    return information


def refine_pose(problem: LevelProblem, est: Estimate, i: int, points_ref: np.ndarray, normals: np.ndarray,
                iterations: int, max_halvings: int = 4, tolerance: float = 0.0, anchors: PoseAnchors | None = None,
                log: PoseLog | None = None) -> tuple[np.ndarray, FrameSample]:
    """:func:`update_pose`, also returning frame i's sample under the refined pose.

    With a light model whose shading depends on the pose (the LED), the shading is recomputed
    for every trial pose and its derivative enters the Jacobian. With ``anchors``
    (:class:`.pose_trust.PoseAnchors`) a step is accepted only where the frame's photometric
    energy plus its depth agreement and pose prior does not rise (the prior also enters the
    Gauss-Newton system); an iteration that finds no such step although the photometric
    energy alone fell (at the shortest step tried) is counted in ``log``.
    """
    model, light, albedo = problem.light_model(est), est.lights[i], est.albedo
    last = {}

    def energy_of(sample: FrameSample, pose: np.ndarray) -> float:
        photometric = problem.frame_data_energy(sample, albedo,
                                                model.basis(normals, points_ref, pose) @ like(light, points_ref))
        last["photometric"] = photometric
        return photometric if anchors is None else photometric + anchors.frame_energy(i, pose, points_ref,
                                                                                       sample.usable)

    pose = est.poses[i]
    sample = problem.sample(i, pose, points_ref)
    energy = energy_of(sample, pose)
    photometric = last["photometric"]
    for _ in range(iterations):
        system = pose_system(problem, est, i, pose, sample, points_ref, normals)
        if system is None:
            break
        H, g = system
        prior = None if anchors is None else anchors.prior_system(i, pose)
        if prior is not None:
            H, g = H + prior[0], g + prior[1]
        step = ridge_solve(H, -g)
        if step is None:
            break

        def trial(t: float):
            trial_pose = se3.exp(t * step) @ pose
            trial_sample = problem.sample(i, trial_pose, points_ref)
            return (trial_pose, trial_sample), energy_of(trial_sample, trial_pose)

        found = backtrack(trial, energy, max_halvings)
        if found is None:
            if log is not None and anchors is not None and last["photometric"] < photometric:
                log.reject(i, "pose step: depth or prior disagree")  # the images alone would have taken it
            break
        t, (pose, sample), trial_energy = found
        photometric = last["photometric"]
        converged = energy - trial_energy <= tolerance * energy
        energy = trial_energy
        if converged or t * np.linalg.norm(step) < 1e-10:
            break
    return pose, sample


def update_poses(problem: LevelProblem, est: Estimate, ev: Evaluation, iterations: int,
                 tolerance: float = 0.0, anchors: PoseAnchors | None = None,
                 log: PoseLog | None = None) -> tuple[np.ndarray, Evaluation]:
    """All frames' refined poses (n, 4, 4) and the evaluation under them (``ev`` is that of ``est``).

    Frame 0 (the reference) stays the identity. The evaluation reuses the samples the
    Gauss-Newton steps ended with instead of warping every frame again. anchors, log: see
    :func:`refine_pose`.
    """
    points_ref = problem.points(est.z)
    poses = est.poses.copy()
    color, usable = ev.color.copy(), ev.usable.copy()
    for i in range(1, problem.n_frames):
        poses[i], sample = refine_pose(problem, est, i, points_ref, ev.normals, iterations, tolerance=tolerance,
                                       anchors=anchors, log=log)
        color[i], usable[i] = sample.color, sample.usable
    moved = Estimate(est.z, est.albedo, est.lights, poses, est.led_offset)
    return poses, problem.evaluate_samples(moved, color, usable, ev.normals, ev.dA)



def keep_agreeing_poses(problem: LevelProblem, previous: np.ndarray, est: Estimate, ev: Evaluation,
                        anchors: PoseAnchors, log: PoseLog | None = None) -> tuple[np.ndarray, Evaluation]:
    """After a step that moved z and the poses together (the joint step): each frame's pose back
    at ``previous`` (n, 4, 4) where the move raised that frame's photometric energy plus its
    depth agreement and prior (:class:`.pose_trust.PoseAnchors`) at the new z; returns the
    poses (n, 4, 4) and their evaluation (``ev``, that of ``est``, where none went back).

    The joint step's line search lowers the total energy, which one frame's pose can do by
    fitting the others' errors; a frame whose anchors did not rise is kept without a warp.
    """
    points = problem.points(est.z)
    model = problem.light_model(est)
    poses = est.poses.copy()
    for i in range(1, problem.n_frames):
        if np.array_equal(poses[i], previous[i]):
            continue
        anchored = anchors.frame_energy(i, poses[i], points, ev.usable[i])
        if anchored <= anchors.frame_energy(i, previous[i], points, ev.usable[i]):
            continue
        old = problem.sample(i, previous[i], points)
        light = like(est.lights[i], points)
        before = problem.frame_data_energy(old, est.albedo, model.basis(ev.normals, points, previous[i]) @ light)
        before += anchors.frame_energy(i, previous[i], points, old.usable)
        after = problem.frame_data_energy(FrameSample(ev.color[i], ev.usable[i]), est.albedo, ev.shading[i]) + anchored
        if after > before:
            poses[i] = previous[i]
            if log is not None:
                log.reject(i, "joint step: depth or prior disagree")
    if np.array_equal(poses, est.poses):
        return poses, ev
    ev.release()
    return poses, problem.evaluate(Estimate(est.z, est.albedo, est.lights, poses, est.led_offset))
