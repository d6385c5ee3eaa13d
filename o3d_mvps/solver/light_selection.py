"""The light model chosen from the data (issue #32, item 2).

Each candidate (:data:`STATIC_CANDIDATES` or :data:`MOVING_CANDIDATES`) is fitted on one coarse
pyramid level (about :data:`LEVEL_PIXELS` object pixels) with the initial depth and poses: a few
sweeps of the closed-form albedo and lighting updates (and the LED offset or the point lights), on half of the reference pixels
(a checkerboard). On the other half the albedo is then fitted per pixel under the fitted lights
and the score is the robust RMS of those held-out residuals,
``sqrt(2 mean phi(r))`` (linear intensity, Cauchy scale :data:`SCORE_CAUCHY_LAMBDA`): a model with
more light parameters than the data determine gains nothing there. Of the models within
:data:`TIE_MARGIN` of the best score the one with the fewest light parameters is chosen (room
light is first-order SH with one light for all frames: on a room-lit capture the two explain the
images alike, and room is the model that says so).

A declared model (the capture's "light" or the user's option) is kept; where it scores clearly
worse than another (by more than :data:`WARN_MARGIN`) a warning says so.
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np

from ..colour import float_frame
from ..model.resampling import fill_nearest_valid, resize
from ..model.robust import cauchy
from .device import to_host
from .lighting import LIGHT_MODELS, make_light_model, update_led_offset
from .point_light import fit_point_lights, initial_point_lights
from .problem import Estimate, LevelProblem
from .problem_input import SolverInput
from .pyramid import build_level, level_mask, level_size
from .reflectance import refit_albedo, update_lighting

#: object pixels of the level the models are fitted on (the coarsest level with at least this many)
LEVEL_PIXELS = 1000
#: sweeps of albedo and lighting (and LED offset) per model
SWEEPS = 4
#: Cauchy scale of the fits and scores (linear intensity), the same for every model
SCORE_CAUCHY_LAMBDA = 0.04
#: models scoring within this fraction of the best count as equally good (the smallest wins)
TIE_MARGIN = 0.02
#: a declared model scoring worse than the best by more than this fraction is warned about
WARN_MARGIN = 0.10


def light_parameters(name: str, n_frames: int) -> int:
    """How many light parameters model ``name`` has for n frames (LED: 2 per frame and the
    offset; room: one SH light and n - 1 gains; SH: 4 per frame; point: 5 per frame)."""
    return {"led": 2 * n_frames + 3, "room": 4 + n_frames - 1, "sh": 4 * n_frames, "point": 5 * n_frames}[name]


#: the candidates for a static camera (a light moved around it: per-frame SH or point lights)
#: and for a moving one (every model but the free point light, whose positions need a camera
#: that stays put)
STATIC_CANDIDATES = ("sh", "point")
MOVING_CANDIDATES = tuple(name for name in LIGHT_MODELS if name != "point")


def select_light_model(problem_input: SolverInput, ref_mask: np.ndarray, declared: str | None = None, *,
                       occlusion_test: bool = True, occlusion_tolerance: float = 0.02, static: bool = False,
                       images: dict | None = None) -> dict:
    """Fit every light model on a coarse level and pick the one that explains the images best.

    problem_input: the solver's input (n >= 2 frames; its initial poses and LED offset are
    used); ref_mask (H, W) bool the reference mask; declared: the model the capture or the user
    named, or None. Returns info["light_selection"]: {"chosen", "declared", "scores" {model:
    held-out robust RMS residual}, "parameters" {model: count}, "level" (H, W), "why"}; with a
    declared model "chosen" is the declared one (a warning says when another fits clearly better).
    static: the camera stands still (identity poses): the candidates are :data:`STATIC_CANDIDATES`,
    else :data:`MOVING_CANDIDATES` (and the declared model). images: coarse levels' frames by
    level size (:func:`.pyramid.coarse_images`), read where the selection's level is among them.
    """
    n = problem_input.n_frames
    if n < 2:
        chosen = declared or "led"
        return {"chosen": chosen, "declared": declared, "scores": {}, "parameters": {}, "level": None,
                "why": "one frame: its albedo explains any shading, the images cannot tell light models apart; "
                       + ("as declared" if declared else "the LED model by default")}
    level = _selection_level(problem_input, ref_mask, images or {})
    g = level.grid
    held_out = to_host((g.u + g.v) % 2 == 1)
    samples = None  # the same depth and poses for every model: the frames warped once
    scores = {}
    candidates = STATIC_CANDIDATES if static else MOVING_CANDIDATES
    candidates = tuple(dict.fromkeys(candidates + ((declared,) if declared else ())))
    for name in candidates:
        scores[name], samples = _held_out_score(problem_input, level, name, held_out, samples, occlusion_test,
                                                occlusion_tolerance)
    parameters = {name: light_parameters(name, n) for name in candidates}
    best = min(scores.values())
    near = [name for name in candidates if scores[name] <= best * (1 + TIE_MARGIN)]
    picked = min(near, key=lambda name: parameters[name])
    ranking = ", ".join(f"{name} {scores[name]:.4f}" for name in sorted(scores, key=scores.get))
    why = (f"held-out robust RMS residual on a {level.size[1]}x{level.size[0]} level: {ranking}; "
           f"{picked} is the smallest model ({parameters[picked]} light parameters) within "
           f"{100 * TIE_MARGIN:.0f} % of the best")
    if declared is not None:
        if scores[declared] > best * (1 + WARN_MARGIN) and picked != declared:
            warnings.warn(f"the declared light model {declared!r} explains the images clearly worse than {picked!r} "
                          f"(held-out robust RMS residual {scores[declared]:.4f} against {scores[picked]:.4f}); "
                          f"keeping {declared!r} as declared. If the capture was lit otherwise, pass --light-model "
                          f"{picked} (RefineOptions(light_model={picked!r})) or fix \"light\" in capture.json",
                          stacklevel=3)
            why = f"declared {declared}, kept, though {picked} fits better ({why})"
        else:
            why = f"declared {declared}, consistent with the data ({why})"
    return {"chosen": declared or picked, "declared": declared,
            "scores": {name: round(float(s), 6) for name, s in scores.items()}, "parameters": parameters,
            "level": list(level.size), "why": why}


def _selection_level(problem_input: SolverInput, ref_mask: np.ndarray, images: dict):
    """The coarsest pyramid level with at least :data:`LEVEL_PIXELS` object pixels (else the finest),
    found from the reference mask alone (:func:`.pyramid.level_mask`) and then built: the levels
    passed over are not built (each one every frame's images resized: 2 MP, 20 frames, 0.7 of the
    selection's 1.2 CPU s)."""
    index = 0
    while min(level_size(ref_mask.shape, index + 1)) >= 8:
        index += 1
    while index > 0 and np.count_nonzero(level_mask(ref_mask, index)) < LEVEL_PIXELS:
        index -= 1
    return build_level(index, problem_input.colors, problem_input.masks, ref_mask, problem_input.K,
                       problem_input.depths[0].astype(np.float64), problem_input.scale_factor,
                       images=images.get(tuple(level_size(ref_mask.shape, index))))


def _held_out_score(problem_input: SolverInput, level, name: str, held_out: np.ndarray, samples,
                    occlusion_test: bool, occlusion_tolerance: float) -> tuple[float, tuple]:
    """Model ``name`` fitted on the level's pixels but ``held_out`` (N,) bool; the robust RMS
    residual of the held-out pixels with their albedo fitted under those lights, and the
    frames' samples (warped colours (n, N, 3), usable (n, N), normals (N, 3), dA (N,)) at the
    initial depth and poses (warped here, after the occlusion test, where ``samples`` is None)."""
    z0 = problem_input.depths[0].astype(np.float64)
    mean_z0 = float(z0[z0 > 0].mean())
    light = make_light_model(name, initial_sh=problem_input.options.initial_light, led_offset=problem_input.led_offset)
    g = level.grid
    z = resize(fill_nearest_valid(z0, z0 > 0), level.size, interpolation=cv2.INTER_LINEAR)
    est = Estimate(level.prior.clip(g.gather(z)), g.gather(float_frame(level.images[0])).astype(np.float64),
                   light.initial_lights(problem_input.n_frames, mean_z0), problem_input.initial_poses.copy(),
                   light.offset.copy() if name == "led"
                   else np.zeros((problem_input.n_frames, 3)) if name == "point" else None)
    problem = LevelProblem(level, 0.0, SCORE_CAUCHY_LAMBDA, light)
    if samples is None:
        problem.update_visibility(est, occlusion_test=occlusion_test, rel_tol=occlusion_tolerance,
                                  sensor_depths=problem_input.depths, depth_K=problem_input.depth_K)
        ev = problem.evaluate(est, scored=False)  # for its samples
        samples = (ev.color, ev.usable, ev.normals, ev.dA)
    color, usable, normals, dA = samples
    # fit on the other half (its albedo refitted before any energy is read)
    ev = problem.evaluate_samples(est, color, usable & ~held_out[None, :], normals, dA, scored=False)
    if name == "point":
        ev = initial_point_lights(problem, est, ev)
    for _ in range(SWEEPS):
        ev = refit_albedo(problem, est, ev, scored=False)  # the lights' refit follows
        est.lights = update_lighting(est, ev, problem.lam, problem.light_model(est))
        ev = problem.reevaluate(est, ev, overwrite=True)
        if name == "led":
            est.led_offset, ev = update_led_offset(problem, est, ev)
        if name == "point":
            ev = fit_point_lights(problem, est, ev)
    # the held-out pixels' albedo under these lights
    ev = problem.evaluate_samples(est, color, usable, normals, dA, scored=False)
    for _ in range(2):  # the albedo's IRLS weights settle (the score reads the residuals alone)
        ev = refit_albedo(problem, est, ev, scored=False)
    use = to_host(ev.usable) & held_out[None, :]
    r = to_host(ev.residual)[use]
    return (float(np.sqrt(2.0 * cauchy(r, SCORE_CAUCHY_LAMBDA).mean())) if r.size else float("inf")), samples
