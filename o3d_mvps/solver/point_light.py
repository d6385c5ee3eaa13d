"""The per-frame point lights of :class:`.lighting.PointLight` (a lamp moved by hand around a
static camera): their start from per-frame SH lights and their refit, each frame's ambient,
intensity and position (3,) by Levenberg-Marquardt with the depth and albedo fixed. The shading's
maths is :mod:`o3d_mvps.model.shading`'s (the LED's: ``v = (p - X) / |p - X|^3``).
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np

from ..model.robust import cauchy, cauchy_weights
from ..model.shading import led_vector_jacobian, led_vectors
from .device import to_host
from .lighting import PointLight, SHLight, lit_point_gradients
from .reflectance import update_albedo, update_lighting

#: Levenberg-Marquardt iterations per frame of :func:`fit_point_lights`
POINT_LM_ITERATIONS = 4
#: the distances, in units of the object's distance from the camera, at which
#: :func:`initial_point_lights` tries each frame's light along its SH light's direction (a lamp
#: held at arm's length beside a camera 0.5-1 m from the object is 0.7-1.5 of that away)
POINT_START_DISTANCES = (0.5, 1.0, 2.0)


def _point_shading(x: np.ndarray, normals: np.ndarray, points: np.ndarray) -> tuple:
    """Shading (M,) of light parameters x = (ambient, intensity, position (3,)) and the
    unclamped irradiance <n, v> (M,) per unit intensity (:func:`~o3d_mvps.model.shading.led_vectors`;
    in NumPy: a few thousand host pixels, where a parallel kernel's start costs more)."""
    g = np.einsum("ij,ij->i", normals, led_vectors(points, x[2:]))
    return x[0] + x[1] * np.maximum(g, 0.0), g


def _fit_point_light(x: np.ndarray, colour: np.ndarray, albedo: np.ndarray, normals: np.ndarray,
                     points: np.ndarray, lam: float, iterations: int) -> tuple[np.ndarray, float]:
    """One frame's point light x = (ambient, intensity, position (3,)) minimising the robust
    energy sum phi(I - rho s) of its pixels (colour, albedo (M, 3), unit normals, points (M, 3)):
    Levenberg-Marquardt on the IRLS model, a step kept only where the robust energy falls.
    Returns (x (5,), energy)."""
    shading, g = _point_shading(x, normals, points)
    r = colour - albedo * shading[:, None]
    energy = float(cauchy(r, lam).sum())
    damping = 1e-3
    for _ in range(iterations):
        w = cauchy_weights(r, lam)
        dpos = -lit_point_gradients(x[None, :2], normals, points, x[None, 2:])[0]  # (M, 3)
        J = np.column_stack([np.ones(len(g)), np.maximum(g, 0.0), dpos])  # d(shading)/dx (M, 5)
        H = (J * (w * albedo**2).sum(axis=1)[:, None]).T @ J
        b = J.T @ (w * albedo * r).sum(axis=1)  # r = I - rho s: the IRLS model's descent direction

        def accept(step, x=x, energy=energy):
            trial = x + step
            shading_t, g_t = _point_shading(trial, normals, points)
            r_t = colour - albedo * shading_t[:, None]
            energy_t = float(cauchy(r_t, lam).sum())
            return (trial, g_t, r_t, energy_t) if np.isfinite(energy_t) and energy_t < energy else None

        found, damping = _damped_step(H, b, accept, damping)
        if found is None:
            break
        x, g, r, energy = found
    return x, energy


def _damped_step(H: np.ndarray, b: np.ndarray, accept, damping: float) -> tuple:
    """One Levenberg-Marquardt step of the system H (k, k), b (k,): ``H + damping diag(H)`` is
    solved and the step offered to ``accept(step)``, which returns what the step leads to or None
    to refuse it; the damping grows 8 times per refusal (up to 1e8) and shrinks 4 times after an
    accepted step. Returns (what ``accept`` returned, or None; the new damping)."""
    diagonal = np.maximum(np.diag(H), 1e-12 * max(float(np.trace(H)), 1e-300))
    while damping < 1e8:
        try:
            step = np.linalg.solve(H + damping * np.diag(diagonal), b)
        except np.linalg.LinAlgError:
            step = None
        found = accept(step) if step is not None and np.isfinite(step).all() else None
        if found is not None:
            return found, max(damping / 4.0, 1e-6)
        damping *= 8.0
    return None, damping


def _host_samples(problem, est, ev, max_pixels: int):
    """Evenly spread pixels (at most ``max_pixels`` per frame) of an evaluation, on the host:
    usable (n, M), colours (n, M, 3), normals, points, albedo (M, 3)."""
    stride = max(1, ev.usable.shape[1] // max_pixels)
    spread = slice(None, None, stride)
    return (to_host(ev.usable[:, spread]), to_host(ev.color[:, spread]).astype(np.float64),
            *(to_host(a[spread]) for a in (ev.normals, problem.points(est.z), est.albedo)))


def _frames_shading(X: np.ndarray, normals: np.ndarray, points: np.ndarray) -> tuple:
    """Shading (n, M) of n frames' lights X (n, 5) = (ambient, intensity, position) on unit
    normals and points (M, 3), and the unclamped irradiances <n, v> (n, M)."""
    g = np.einsum("mj,nmj->nm", normals, led_vectors(points, X[:, 2:]))
    return X[:, :1] + X[:, 1:2] * np.maximum(g, 0.0), g


def _projected_albedo(colour: np.ndarray, shading: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per pixel and channel the albedo (M, 3) minimising sum_i w (I - rho s)^2 over the frames:
    colour (n, M, 3), shading (n, M), weights (n, M, 3) (zero where unusable)."""
    num = np.einsum("nmc,nm->mc", weights * colour, shading)
    den = np.einsum("nmc,nm->mc", weights, shading**2)
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def _fit_projected(X: np.ndarray, colour: np.ndarray, usable: np.ndarray, normals: np.ndarray, points: np.ndarray,
                   lam: float, iterations: int) -> np.ndarray:
    """All frames' point lights X (n, 5) at once, the albedo projected out (variable projection):
    Levenberg-Marquardt on the IRLS model whose normal matrix is the Schur complement of the
    per-pixel albedo, so that lights and albedo move together. Fitted in turn, a common falloff
    passes slowly between them (the albedo takes the light's misfit, the lights fit that albedo):
    on a quilt the lamps settled 1.3-1.55 times too far away. colour (n, M, 3), usable (n, M),
    normals, points (M, 3); returns X (n, 5)."""
    n, M = usable.shape
    u = usable[..., None].astype(np.float64)

    def state(X, w):
        shading, g = _frames_shading(X, normals, points)
        rho = _projected_albedo(colour, shading, w)
        r = (colour - rho[None] * shading[..., None]) * u
        return shading, g, rho, r, float((cauchy(r, lam) * u).sum())

    w = u
    shading, g, rho, r, energy = state(X, w)
    damping = 1e-3
    for _ in range(iterations):
        w = cauchy_weights(r, lam) * u
        shading, g, rho, r, energy = state(X, w)  # the albedo of these weights
        lit = g > 0
        dpos = -led_vector_jacobian(points, X[:, 2:], normals) * (X[:, 1:2] * lit)[..., None]  # (n, M, 3)
        J = np.concatenate([np.ones((n, M, 1)), np.maximum(g, 0.0)[..., None], dpos], axis=2)  # (n, M, 5)
        wr2 = w * rho[None] ** 2
        S = np.zeros((n, 5, n, 5))
        S[np.arange(n), :, np.arange(n), :] = np.einsum("nmc,nmk,nml->nkl", wr2, J, J)
        b = np.einsum("nmc,nmk->nk", w * r * rho[None], J).ravel()
        C = (w * rho[None] * shading[..., None])[..., None] * J[:, :, None, :]  # (n, M, 3, 5): lights x albedo
        C = C.transpose(1, 2, 0, 3).reshape(M * 3, n * 5)
        A = np.einsum("nmc,nm->mc", w, shading**2).reshape(-1)
        S = S.reshape(n * 5, n * 5) - (C / np.maximum(A, 1e-300)[:, None]).T @ C

        def accept(step, X=X, w=w, energy=energy):
            trial = X + step.reshape(n, 5)
            if not (np.isfinite(trial).all() and (trial[:, 1] > 0).all() and (trial[:, 0] >= 0).all()):
                return None
            found = state(trial, w)
            return (trial, found) if np.isfinite(found[-1]) and found[-1] < energy else None

        accepted, damping = _damped_step(S, b, accept, damping)
        if accepted is None:
            break
        X, (shading, g, rho, r, energy) = accepted
    return X


def fit_point_lights(problem, est, ev, *, iterations: int = POINT_LM_ITERATIONS, max_pixels: int = 1500,
                     projected: bool = False):
    """Every frame's point light (ambient, intensity, position) refitted to the images with the
    depth fixed, on at most ``max_pixels`` evenly spread pixels (5 unknowns per frame need few),
    then the albedo refitted (:func:`.reflectance.update_albedo`): per frame with the albedo fixed
    (:func:`_fit_point_light`), or with ``projected`` all frames together with the albedo
    projected out (:func:`_fit_projected`). The projected fit starts the lights
    (:func:`initial_point_lights`); in the sweeps it also fitted the bunny's cast shadows, which
    the model lacks, with lamps close to the object (320x240, D415-like: normals 5.1 -> 7.0 deg,
    albedo error 3.1 -> 9.2 %), so they refit frame by frame. Updates ``est``'s lights, positions
    (``led_offset``) and albedo in place where that lowers the level's energy and returns the
    evaluation (else ``ev``)."""
    light = problem.light_model(est)
    usable, colour, normals, points, albedo = _host_samples(problem, est, ev, max_pixels)
    X = np.concatenate([est.lights, light.offset], axis=1)
    if projected:
        X = _fit_projected(X, colour, usable, normals, points, problem.lam, iterations)
    else:
        for i in range(problem.n_frames):
            use = usable[i]
            if use.sum() >= 8:
                X[i] = _fit_point_light(X[i], colour[i, use], albedo[use], normals[use], points[use], problem.lam,
                                        iterations)[0]
    moved = dataclasses.replace(est, lights=X[:, :2].copy(), led_offset=X[:, 2:].copy())
    trial = problem.evaluate_samples(moved, ev.color, ev.usable, ev.normals, ev.dA)
    moved.albedo = update_albedo(moved, trial, problem.lam)
    trial = problem.reevaluate(moved, trial, overwrite=True)
    if trial.energy < ev.energy:
        est.lights, est.led_offset, est.albedo = moved.lights, moved.led_offset, moved.albedo
        return trial
    return ev


def initial_point_lights(problem, est, ev, *, sweeps: int = 4, max_pixels: int = 4000):
    """Starting point lights for :class:`PointLight` on a (coarse) level: per-frame SH lights
    fitted with the albedo (``sweeps`` rounds), then per frame the point light along the SH
    light's direction from the object's centroid at each of :data:`POINT_START_DISTANCES`
    times its distance from the camera, refined by :func:`_fit_point_light` with that albedo, the
    best kept; then all together with the albedo (:func:`fit_point_lights`). Updates est's
    lights, positions (``led_offset``) and albedo in place; ev its evaluation (its usable pixels
    are those fitted). Returns the evaluation of the result."""
    sh_problem = copy.copy(problem)
    sh_problem.light = SHLight()
    sh_est = dataclasses.replace(est, albedo=est.albedo.copy(), led_offset=None,
                                 lights=sh_problem.light.initial_lights(problem.n_frames, 0.0))
    sh_ev = sh_problem.evaluate_samples(sh_est, ev.color, ev.usable, ev.normals, ev.dA)
    for _ in range(sweeps):
        sh_est.albedo = update_albedo(sh_est, sh_ev, problem.lam)
        sh_ev = sh_problem.reevaluate(sh_est, sh_ev, overwrite=True)
        sh_est.lights = update_lighting(sh_est, sh_ev, problem.lam, sh_problem.light)
        sh_ev = sh_problem.reevaluate(sh_est, sh_ev, overwrite=True)
    est.albedo = sh_est.albedo
    P = to_host(problem.points(est.z))
    centre = P.mean(axis=0)
    usable, colour, normals, points, albedo = _host_samples(problem, est, sh_ev, max_pixels)
    light = PointLight(np.zeros((problem.n_frames, 3)))
    lights, positions = np.zeros((problem.n_frames, 2)), np.zeros((problem.n_frames, 3))
    for i in range(problem.n_frames):
        use = usable[i]
        best = None
        for factor in POINT_START_DISTANCES:
            start_light, start_position = light.initial_positions(sh_est.lights[i:i + 1], centre,
                                                                  factor * float(np.linalg.norm(centre)))
            x0 = np.r_[start_light[0], start_position[0]]
            fitted = _fit_point_light(x0, colour[i, use], albedo[use], normals[use], points[use], problem.lam,
                                      2 * POINT_LM_ITERATIONS) if use.sum() >= 8 else (x0, 0.0)
            if best is None or fitted[1] < best[1]:
                best = fitted
        lights[i], positions[i] = best[0][:2], best[0][2:]
    est.lights, est.led_offset = lights, positions
    return fit_point_lights(problem, est, problem.evaluate_samples(est, ev.color, ev.usable, ev.normals, ev.dA),
                            iterations=4 * POINT_LM_ITERATIONS, projected=True)
