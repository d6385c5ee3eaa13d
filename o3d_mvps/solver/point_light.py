"""The per-frame point lights of :class:`.lighting.PointLight` (a lamp moved by hand around a
static camera): their start from per-frame SH lights and their refit, each frame's ambient,
intensity and position (3,) by Levenberg-Marquardt with the depth and albedo fixed. The shading's
maths is :mod:`o3d_mvps.model.shading`'s (the LED's: ``v = (p - X) / |p - X|^3``).
"""

from __future__ import annotations

import copy
import dataclasses
import math

import numba
import numpy as np

from ..model.robust import cauchy, cauchy_weights
from ..model.shading import led_irradiance_at, led_point_gradient_of, led_vector_jacobian, led_vectors
from .device import to_host
from .lighting import PointLight, SHLight
from .reflectance import update_albedo, update_lighting

#: Levenberg-Marquardt iterations per frame of :func:`fit_point_lights`
POINT_LM_ITERATIONS = 4
#: rounds of :func:`fit_point_lights`: the lights fitted frame by frame, then the albedo of the
#: sampled pixels to them, until no light moves by more than :data:`POINT_ROUND_TOLERANCE` (m).
#: Fitted in turn once per sweep, a common falloff passes slowly between the lamps and the
#: albedo: on the 640x480 bunny (D415-like) the lamps ended 44 mm from the truth (albedo error
#: 2.8 %); with rounds 21 mm (1.1 %)
POINT_ROUNDS = 3
POINT_ROUND_TOLERANCE = 1e-4
#: how far a lamp may go from the object's centroid, in units of the object's distance from the
#: camera (a lamp held by hand is at arm's length): a step beyond is refused. Far away, a point
#: light becomes a directional one whose intensity grows with its distance squared; unbounded,
#: one lamp of the clean 320x240 bunny started on a 20-pixel level ran off to some 700 km
POINT_MAX_DISTANCE = 5.0
#: the distances, in units of the object's distance from the camera, at which
#: :func:`initial_point_lights` tries each frame's light along its SH light's direction (a lamp
#: held at arm's length beside a camera 0.5-1 m from the object is 0.7-1.5 of that away)
POINT_START_DISTANCES = (0.5, 1.0, 2.0)
#: levels with more pixels than this refit the lamps with the albedo projected out
#: (:func:`_fit_projected`, all frames together) on :data:`POINT_FINE_PIXELS` pixels with
#: :data:`POINT_FINE_ITERATIONS` iterations, not frame by frame: on the fine levels the depth
#: is settled and each lamp's last millimetres trade off against the albedo, which the
#: alternation leaves behind (640x480 quilt, clean render: lamps 7.5 -> 5.1 mm off, albedo
#: error 0.54 -> 0.16 %, the shading it kept 0.54 -> 0.13 %; D415-like: 1.60 -> 1.25 %, with
#: the frames' mean depth 1.02 -> 0.72 %). Coarser levels keep the frame-by-frame fit: there
#: the projected fit explained the bunny's cast shadows with lamps close to the object
POINT_FINE_MIN_PIXELS = 20000
#: :func:`_fit_projected` stops when a step lowers the sampled energy by less than this fraction
POINT_PROJECTED_TOLERANCE = 1e-5
POINT_FINE_PIXELS = 8000
POINT_FINE_ITERATIONS = 12


@numba.njit(parallel=True, cache=True)
def _frame_sums(X, colour, albedo, usable, normals, points, lam, frames, system, energy, H, b):  # pragma: no cover - compiled
    """Per frame i where ``frames`` (n,) bool is set the robust energy ``sum_p,c phi(I - rho s)``
    over its usable pixels of the light X[i] = (ambient, intensity, position (3,)) written into
    energy (n,); with ``system`` also the Levenberg-Marquardt model's H (n, 5, 5) and b (n, 5):
    ``sum_p (sum_c w rho^2) J J^T`` and ``sum_p (sum_c w rho r) J``, J = d(shading)/dX = (1,
    max(0, <n, v>), d<n, v>/d(position) times the intensity where lit), w the Cauchy weights
    (:func:`o3d_mvps.model.robust.cauchy_weights`) of the residuals r = I - rho s. float64 X
    (n, 5), colour (n, M, 3), albedo, normals, points (M, 3); usable (n, M) bool. One pass per
    frame (NumPy's version made a dozen (n, M, 3) temporaries per call) and one logarithm per
    pixel: :func:`o3d_mvps.model.robust.cauchy`'s phi summed over the 3 channels as
    ``lam^2 / 2 log(prod_c (1 + (r_c / lam)^2))``. In parallel over the frames (each frame's
    sums in its own order: the same values on any thread count)."""
    inv_lam, half = 1.0 / lam, 0.5 * lam * lam
    intensities, positions = X[:, 1].copy(), X[:, 2:].copy()
    for i in numba.prange(X.shape[0]):
        if not frames[i]:
            continue
        J = np.empty(5)
        e = 0.0
        if system:
            H[i] = 0.0
            b[i] = 0.0
        for p in range(points.shape[0]):
            if not usable[i, p]:
                continue
            g = led_irradiance_at(normals, points, positions[i, 0], positions[i, 1], positions[i, 2], p)
            lit = max(g, 0.0)
            s = X[i, 0] + X[i, 1] * lit
            product, wa2, war = 1.0, 0.0, 0.0
            for c in range(3):
                r = colour[i, p, c] - albedo[p, c] * s
                y = r * inv_lam
                factor = 1.0 + y * y
                product *= factor
                if system:
                    wa2 += albedo[p, c] * albedo[p, c] / factor
                    war += albedo[p, c] * r / factor
            e += math.log(product)
            if system:
                d0, d1, d2 = led_point_gradient_of(intensities, normals, points, positions, i, p)
                J[0], J[1], J[2], J[3], J[4] = 1.0, lit, -d0, -d1, -d2
                for k in range(5):
                    b[i, k] += war * J[k]
                    for m in range(k, 5):
                        H[i, k, m] += wa2 * J[k] * J[m]
        if system:
            for k in range(5):
                for m in range(k):
                    H[i, k, m] = H[i, m, k]
        e *= half
        energy[i] = e if math.isfinite(e) else math.inf


def _frame_energies(X: np.ndarray, colour: np.ndarray, albedo: np.ndarray, usable: np.ndarray, normals: np.ndarray,
                    points: np.ndarray, lam: float, frames: np.ndarray | None = None, system: bool = False) -> tuple:
    """Per frame the robust energy (n,) of lights X (n, 5) against colour (n, M, 3) with albedo
    (M, 3) over the usable (n, M) pixels (:func:`_frame_sums`), of the ``frames`` (n,) bool
    (default all; inf elsewhere); with ``system`` also the Levenberg-Marquardt model's H (n, 5, 5)
    and b (n, 5) there (else None, None). The arrays as :func:`_fit_frames` prepares them
    (float64, contiguous)."""
    n = len(X)
    energy = np.full(n, np.inf)
    H, b = (np.zeros((n, 5, 5)), np.zeros((n, 5))) if system else (np.empty((0, 5, 5)), np.empty((0, 5)))
    frames = np.ones(n, bool) if frames is None else np.ascontiguousarray(frames, dtype=bool)
    _frame_sums(np.ascontiguousarray(X, dtype=np.float64), colour, albedo, usable, normals, points, float(lam), frames,
                system, energy, H, b)
    return (energy, H, b) if system else (energy, None, None)


def _fit_frames(X: np.ndarray, colour: np.ndarray, albedo: np.ndarray, usable: np.ndarray, normals: np.ndarray,
                points: np.ndarray, lam: float, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Every frame's point light x_i = (ambient, intensity, position (3,)) minimising its robust
    energy sum phi(I_i - rho s_i) over its usable pixels (colour (n, M, 3), usable (n, M), albedo
    (M, 3), unit normals, points (M, 3)), the albedo fixed: Levenberg-Marquardt on the IRLS model,
    the frames' 5x5 systems solved together, each frame's step kept only where its energy falls
    (its damping grows 8 times per refusal, up to 1e8, and shrinks 4 times after a kept step).
    Frames with fewer than 8 usable pixels keep their light. The sums are compiled
    (:func:`_frame_sums`). Returns (X (n, 5), energies (n,))."""
    X = np.array(X, dtype=np.float64)
    colour, albedo, normals, points = (np.ascontiguousarray(a, dtype=np.float64)
                                       for a in (colour, albedo, normals, points))
    usable = np.ascontiguousarray(usable, dtype=bool)
    energy = _frame_energies(X, colour, albedo, usable, normals, points, lam)[0]
    active = usable.sum(axis=1) >= 8
    damping = np.full(len(X), 1e-3)
    for _ in range(iterations):
        if not active.any():
            break
        _, H, b = _frame_energies(X, colour, albedo, usable, normals, points, lam, active, system=True)
        diagonal = np.maximum(np.diagonal(H, axis1=1, axis2=2),
                              1e-12 * np.maximum(np.trace(H, axis1=1, axis2=2), 1e-300)[:, None])
        trying = active.copy()
        while trying.any():
            with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
                A = H[trying] + damping[trying, None, None] * (diagonal[trying, :, None] * np.eye(5))
                try:
                    step = np.linalg.solve(A, b[trying][..., None])[..., 0]
                except np.linalg.LinAlgError:  # a singular frame: its own solves, NaN where singular
                    step = np.stack([_solve_or_nan(a, v) for a, v in zip(A, b[trying])])
            trial = X.copy()
            trial[trying] += np.where(np.isfinite(step), step, 0.0)
            trial_energy = _frame_energies(trial, colour, albedo, usable, normals, points, lam, trying)[0]
            better = trying & (trial_energy < energy) & _within_reach(trial, X, points)
            better[trying] &= np.isfinite(step).all(axis=1)
            X[better], energy[better] = trial[better], trial_energy[better]
            damping[better] = np.maximum(damping[better] / 4.0, 1e-6)
            refused = trying & ~better
            damping[refused] *= 8.0
            active &= damping < 1e8  # a frame that no damping improves stops
            trying = refused & active
    return X, energy


def _within_reach(trial: np.ndarray, X: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n,) whether each frame's trial light (n, 5) has a positive intensity and its lamp within
    :data:`POINT_MAX_DISTANCE` object distances of the centroid of ``points`` (M, 3), or no
    farther than the light X (n, 5) it replaces."""
    centre = points.mean(axis=0)
    reach = np.maximum(POINT_MAX_DISTANCE * np.linalg.norm(centre), np.linalg.norm(X[:, 2:] - centre, axis=1))
    return (trial[:, 1] > 0) & (np.linalg.norm(trial[:, 2:] - centre, axis=1) <= reach)


def _solve_or_nan(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A^-1 b (k,), or NaN where A (k, k) is singular."""
    try:
        return np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return np.full(len(b), np.nan)


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
        wr2 = (w * rho[None] ** 2).sum(axis=2)  # (n, M); the sums as matmuls (an einsum of three: 5x slower)
        S = np.zeros((n, 5, n, 5))
        S[np.arange(n), :, np.arange(n), :] = np.matmul(J.transpose(0, 2, 1) * wr2[:, None, :], J)
        b = np.matmul(J.transpose(0, 2, 1), (w * r * rho[None]).sum(axis=2)[..., None])[..., 0].ravel()
        C = (w * rho[None] * shading[..., None])[..., None] * J[:, :, None, :]  # (n, M, 3, 5): lights x albedo
        C = C.transpose(1, 2, 0, 3).reshape(M * 3, n * 5)
        A = np.einsum("nmc,nm->mc", w, shading**2).reshape(-1)
        S = S.reshape(n * 5, n * 5) - (C / np.maximum(A, 1e-300)[:, None]).T @ C

        def accept(step, X=X, w=w, energy=energy):
            trial = X + step.reshape(n, 5)
            if not (np.isfinite(trial).all() and _within_reach(trial, X, points).all() and (trial[:, 0] >= 0).all()):
                return None
            found = state(trial, w)
            return (trial, found) if np.isfinite(found[-1]) and found[-1] < energy else None

        accepted, damping = _damped_step(S, b, accept, damping)
        if accepted is None:
            break
        previous = energy
        X, (shading, g, rho, r, energy) = accepted
        if previous - energy <= POINT_PROJECTED_TOLERANCE * previous:  # settled: the rest is cost
            break
    return X


def fit_point_lights(problem, est, ev, *, iterations: int | None = None, max_pixels: int | None = None,
                     projected: bool | None = None, rounds: int = POINT_ROUNDS):
    """Every frame's point light (ambient, intensity, position) refitted to the images with the
    depth fixed, on at most ``max_pixels`` evenly spread pixels (5 unknowns per frame need few),
    then the albedo refitted (:func:`.reflectance.update_albedo`): per frame with the albedo fixed
    (:func:`_fit_frames`), alternated with the sampled pixels' albedo for up to ``rounds`` rounds
    (:data:`POINT_ROUNDS`), or with ``projected`` all frames together with the albedo
    projected out (:func:`_fit_projected`). The projected fit starts the lights
    (:func:`initial_point_lights`); in the coarse levels' sweeps it also fitted the bunny's cast
    shadows, which the model lacks, with lamps close to the object (320x240, D415-like: normals
    5.1 -> 7.0 deg, albedo error 3.1 -> 9.2 %), so they refit frame by frame there. None
    (``projected``, ``iterations``, ``max_pixels``): projected on the levels of more than
    :data:`POINT_FINE_MIN_PIXELS` pixels (:data:`POINT_FINE_ITERATIONS`,
    :data:`POINT_FINE_PIXELS`), else frame by frame (:data:`POINT_LM_ITERATIONS`, 1500 pixels).
    Updates ``est``'s lights, positions (``led_offset``) and albedo in place where that lowers the
    level's energy and returns the evaluation (else ``ev``)."""
    fine = problem.level.grid.size > POINT_FINE_MIN_PIXELS
    projected = fine if projected is None else projected
    iterations = iterations or (POINT_FINE_ITERATIONS if fine and projected else POINT_LM_ITERATIONS)
    max_pixels = max_pixels or (POINT_FINE_PIXELS if fine and projected else 1500)
    light = problem.light_model(est)
    usable, colour, normals, points, albedo = _host_samples(problem, est, ev, max_pixels)
    X = np.concatenate([est.lights, light.offset], axis=1)
    if projected:
        X = _fit_projected(X, colour, usable, normals, points, problem.lam, iterations)
    else:
        u = usable[..., None].astype(np.float64)
        for _ in range(rounds):
            before = X[:, 2:].copy()
            X = _fit_frames(X, colour, albedo, usable, normals, points, problem.lam, iterations)[0]
            if rounds == 1 or np.abs(X[:, 2:] - before).max() < POINT_ROUND_TOLERANCE:
                break
            shading = _frames_shading(X, normals, points)[0]
            r = (colour - albedo[None] * shading[..., None]) * u
            albedo = _projected_albedo(colour, shading, cauchy_weights(r, problem.lam) * u)
    moved = dataclasses.replace(est, lights=X[:, :2].copy(), led_offset=X[:, 2:].copy())
    # its energy unread: the albedo is refitted and the trial evaluated again at it
    trial = problem.evaluate_samples(moved, ev.color, ev.usable, ev.normals, ev.dA, scored=False)
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
    times its distance from the camera, refined by :func:`_fit_frames` with that albedo, the
    best kept; then all together with the albedo (:func:`fit_point_lights`). Updates est's
    lights, positions (``led_offset``) and albedo in place; ev its evaluation (its usable pixels
    are those fitted). Returns the evaluation of the result."""
    sh_problem = copy.copy(problem)
    sh_problem.light = SHLight()
    sh_est = dataclasses.replace(est, albedo=est.albedo.copy(), led_offset=None,
                                 lights=sh_problem.light.initial_lights(problem.n_frames, 0.0))
    sh_ev = sh_problem.evaluate_samples(sh_est, ev.color, ev.usable, ev.normals, ev.dA, scored=False)  # refitted first
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
    best, best_energy = None, None
    for factor in POINT_START_DISTANCES:
        start_lights, start_positions = light.initial_positions(sh_est.lights, centre,
                                                                factor * float(np.linalg.norm(centre)))
        X, energy = _fit_frames(np.concatenate([start_lights, start_positions], axis=1), colour, albedo, usable,
                                normals, points, problem.lam, 2 * POINT_LM_ITERATIONS)
        keep = slice(None) if best is None else energy < best_energy
        best = X if best is None else np.where(keep[:, None], X, best)
        best_energy = energy if best_energy is None else np.where(keep, energy, best_energy)
    est.lights, est.led_offset = best[:, :2].copy(), best[:, 2:].copy()
    return fit_point_lights(problem, est, problem.evaluate_samples(est, ev.color, ev.usable, ev.normals, ev.dA),
                            iterations=4 * POINT_LM_ITERATIONS, max_pixels=1500, projected=True)
