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
from ..model.shading import led_vectors
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
        diagonal = np.maximum(np.diag(H), 1e-12 * max(float(np.trace(H)), 1e-300))
        while damping < 1e8:
            try:
                step = np.linalg.solve(H + damping * np.diag(diagonal), b)
            except np.linalg.LinAlgError:
                step = None
            if step is not None and np.isfinite(step).all():
                trial = x + step
                shading_t, g_t = _point_shading(trial, normals, points)
                r_t = colour - albedo * shading_t[:, None]
                energy_t = float(cauchy(r_t, lam).sum())
                if np.isfinite(energy_t) and energy_t < energy:
                    x, g, r, energy = trial, g_t, r_t, energy_t
                    damping = max(damping / 4.0, 1e-6)
                    break
            damping *= 8.0
        else:
            break
    return x, energy


def _host_samples(problem, est, ev, max_pixels: int):
    """Evenly spread pixels (at most ``max_pixels`` per frame) of an evaluation, on the host:
    usable (n, M), colours (n, M, 3), normals, points, albedo (M, 3)."""
    stride = max(1, ev.usable.shape[1] // max_pixels)
    spread = slice(None, None, stride)
    return (to_host(ev.usable[:, spread]), to_host(ev.color[:, spread]).astype(np.float64),
            *(to_host(a[spread]) for a in (ev.normals, problem.points(est.z), est.albedo)))


def fit_point_lights(problem, est, ev, *, iterations: int = POINT_LM_ITERATIONS, max_pixels: int = 2000):
    """Every frame's point light (ambient, intensity, position) refitted to the images with the
    depth and albedo fixed (:class:`PointLight`): per frame, Levenberg-Marquardt on at most
    ``max_pixels`` evenly spread usable pixels (five unknowns need few). Returns (lights (n, 2),
    positions (n, 3), evaluation): the new lights where they lower the full energy, else
    ``est``'s and ``ev``."""
    light = problem.light_model(est)
    usable, colour, normals, points, albedo = _host_samples(problem, est, ev, max_pixels)
    lights, positions = est.lights.copy(), light.offset.copy()
    for i in range(problem.n_frames):
        use = usable[i]
        if use.sum() < 8:
            continue
        x, _ = _fit_point_light(np.r_[lights[i], positions[i]], colour[i, use], albedo[use], normals[use],
                                points[use], problem.lam, iterations)
        lights[i], positions[i] = x[:2], x[2:]
    moved = dataclasses.replace(est, lights=lights, led_offset=positions)
    trial = problem.evaluate_samples(moved, ev.color, ev.usable, ev.normals, ev.dA)
    if trial.energy < ev.energy:
        return lights, positions, trial
    return est.lights, light.offset, ev


def initial_point_lights(problem, est, ev, *, sweeps: int = 4, max_pixels: int = 4000):
    """Starting point lights for :class:`PointLight` on a (coarse) level: per-frame SH lights
    fitted with the albedo (``sweeps`` rounds), then per frame the point light along the SH
    light's direction from the object's centroid at each of :data:`POINT_START_DISTANCES`
    times its distance from the camera, refined by :func:`_fit_point_light`, the best kept.
    est (its albedo is refitted in place), ev its evaluation (its usable pixels are those fitted).
    Returns (lights (n, 2), positions (n, 3), evaluation)."""
    sh_problem = copy.copy(problem)
    sh_problem.light = SHLight()
    sh_est = dataclasses.replace(est, albedo=est.albedo.copy(), lights=sh_problem.light.initial_lights(problem.n_frames, 0.0),
                                 led_offset=None)
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
    return lights, positions, problem.evaluate_samples(est, ev.color, ev.usable, ev.normals, ev.dA)
