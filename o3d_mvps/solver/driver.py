"""Coarse-to-fine driver: ``solve(SolverInput) -> SolverOutput`` (NumPy in, NumPy out; the
Open3D-facing ``refine(capture) -> Refinement`` is :func:`o3d_mvps.solving.refine`).

Per level, sweeps of poses -> depth -> albedo -> lighting (paper section 4) until the
relative energy change falls below the tolerance (the finest level: or the data term's alone, or
the next change, predicted from the last two, where they contract fast: :func:`_stalled`) or the
sweep cap is reached.
Where poses are refined, poses and depth take one joint Gauss-Newton step (:mod:`.joint`); the depth and
joint steps move the albedo along (variable projection) and keep z inside the sensor's depth
envelope (:func:`.pyramid.depth_envelope`). Each sweep starts by weighting the smoothness per pixel
by the shading's evidence, and each level ends by tying the depth's low frequencies to the sensor
(:mod:`.weighting`). z and albedo are upsampled bilinearly between levels; lighting and poses
carry over (the authors' code reset lighting at every level).
"""

from __future__ import annotations

import time
import warnings
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import cv2
import numpy as np
from threadpoolctl import threadpool_limits
from tqdm.auto import tqdm

from ..colour import float_frame
from ..covisibility import MEAN_MIN_FRAMES, frames_mean_check, reference_depth_mean
from ..errors import CaptureError
from ..model import se3
from ..model.arrays import array_module, contiguous, fused, like
from ..model.parallel import current_kernel_threads, kernel_threads, set_kernel_threads
from ..model.resampling import fill_nearest_valid, repeat_pixels, resize
from ..model.robust import robust_scale
from .depth import envelope_arrays, update_depth
from .device import CPU, ArrayDevice, array_device, compile_notice, kernels_for, on_gpu, to_host
from .acceleration import ANDERSON_FRACTIONS, Anderson, level_accelerator, partway
from .allocator import map_large_blocks, return_freed_arrays, trim_heap
from .frames_depth import RETARGET_SWEEP, frames_depth_target
from .joint import update_pose_depth
from .kernels import MAX_EXTRAPOLATION_FACTORS, extrapolation_blocks
from .light_selection import select_light_model
from .lighting import make_light_model, preload_light_states, update_led_offset
from .normal_equations import prepare_depth_block
from .options import AUTO, DEFAULT_CAUCHY_LAMBDA, FramesDepth, RefineOptions
from .pose import keep_agreeing_poses, pose_information, update_poses
from .point_light import fit_point_lights, initial_point_lights
from .pose_trust import PoseAnchors, PoseLog
from .problem import Estimate, LevelProblem
from .problem_input import SolverInput
from .pyramid import build_level, coarse_images, depth_prior, level_size
from .reflectance import refit_albedo, update_albedo, update_lighting
from .smoothness import auto_smoothness, grid_mode_weight
from .solution import SolverOutput
from .weighting import (absolute_evidence_weights, albedo_step_factor, albedo_step_weights, evidence_weights,
                        leans_on_smoothness, lowpass_sigma, normal_evidence, tie_low_frequencies)


#: levels with more object pixels than this are the finer ones: the coarse levels place the point
#: lights (:data:`POINT_SWEEP_FACTOR` times the sweeps); on the finer ones the lamps are refitted
#: with the albedo projected out (:data:`.point_light.POINT_FINE_MIN_PIXELS`) every sweep too
#: (first sweep only before: 640x480 D415-like quilt, albedo error 0.71 -> 0.65 %, lamps 6.8 -> 5.3 mm)
POINT_FIT_MAX_PIXELS = 20000
#: on the levels that no longer refit the point lights every sweep (more than
#: :data:`POINT_FIT_MAX_PIXELS`), the depth steps' CG stops at this many times ``cg_tolerance``:
#: on the 640x480 quilt the finest level's steps took 14-22 CG iterations instead of 24-28, for
#: the same normals, albedo and lamps (0.923 deg, 1.596 %, 24.4 mm off; 1280x960: 1.037 deg, 0.982 %);
#: 10 (a static capture's default: a relative residual of 1e-2) the same again at 640x480
#: (0.9232 deg, 1.596 %, 0.053 per mille; 30: 0.9227 deg, 1.596 %)
POINT_SETTLED_CG_FACTOR = 10.0
#: the point lights start on the first level with at least this many object pixels (or the finest):
#: 5 parameters a lamp and an albedo per pixel. From a 20-pixel coarsest level (320x240 colour) the
#: clean bunny's lamps started 450 mm off and never recovered (normals 4.4 deg, albedo error 12 %;
#: from 300 pixels: 2.0 deg, 0.9 %). Coarse levels also place a lamp too far from a nearly flat
#: surface: on the 320x240 D415-like quilt (tests/test_static_camera.py) the 300- and 1200-pixel
#: levels drove the lamps out to 1.3-1.8 times their distance, which the finer levels only
#: partly undid (166 mm off at the end, normals 1.61 deg); started at 4000 pixels, 50 mm (1.29 deg)
POINT_MIN_PIXELS = 4000
#: on the levels that refit the point lights every sweep (up to :data:`POINT_FIT_MAX_PIXELS`),
#: this many times ``max_iterations`` sweeps at most: depth and lamps trade off along a valley
#: (a nearly flat surface: the lamp's distance against the depth's curvature and the albedo),
#: down which the alternating sweeps creep a few per cent of the lamp's distance a sweep; they stop
#: at the energy's tolerance only once the lamps no longer creep (:func:`_lamps_creeping`)
POINT_SWEEP_FACTOR = 6
#: ... that is, once the lamps moved less than this fraction of their mean distance from the camera
#: over the last :data:`POINT_CREEP_SWEEPS` sweeps (mean over the lamps): on the one-ring 320x240
#: quilt (tests/test_static_camera.py) the energy's tolerance stopped them creeping 98 mm off
POINT_CREEP_TOLERANCE = 0.002
POINT_CREEP_SWEEPS = 3
#: on the finer levels (the lamps placed, refitted in the first sweep only) this many sweeps at most
#: (None: ``max_iterations``). The rendered D415-like quilt (20 frames) took up to 8 there to the
#: energy's tolerance; 640x480: none 27.8, 4 19.7, 3 17.9 CPU s for normals 0.922-0.923 deg and
#: albedo 1.60 %; 1280x960: sweeps 4/8/3 66.1 CPU s, 4/4/4 73.6, 3/3/3 56.4 (loaded machine),
#: normals 1.037-1.038 deg, albedo 0.99 % in all. Fewer sweeps on the lamps' levels cost the
#: albedo instead (10 -> 5 sweeps everywhere: 1.60 -> 2.17 % at 640x480). 2 (with the CG factor
#: at 10): 640x480 0.9228 deg against 0.9232, albedo 1.6005 % against 1.5960, low-pass 0.053 per mille
POINT_SETTLED_SWEEPS = 2
#: ... and the finest level (index 0) this many (None: as the others) where a coarser level of
#: those refitted the lamps already (the first such level places them with the albedo projected
#: out: a 320x240 capture's finest level, 1 sweep and no refit there, albedo 1.04 -> 1.64 %).
#: Issue 32's 1280x960 D415-like quilt (20 frames, 2 numba threads, base and 1 sweep run at once):
#: 45.8 -> 33.9 CPU s, normals 0.4736 -> 0.4659 deg, albedo 0.6175 -> 0.6171 %, lamps 3.58 mm
#: either way, but the normals within 2 px of the image's edge 0.572 -> 0.701 deg (the clean
#: render's albedo 0.114 -> 0.133 %, lamps 2.3 -> 3.8 mm; CG to 1e-3 there: the same), so not
#: the default. 1 sweep on every such level: 32.5 CPU s, albedo 0.643 %, lamps 4.4 mm
POINT_FINEST_SWEEPS = None
#: whether the finest level (where a coarser level of those refitted the lamps) refits the point lights
#: (:func:`.point_light.fit_point_lights`) in its sweeps: on that quilt the refit was never kept
#: there (its trial energy never lower: the same figures and final energy to the last digit
#: without it), and each costs two evaluations of every frame and a lamp fit (2.6 CPU s of 47);
#: on the clean render it was kept: without it albedo 0.114 -> 0.132 %, lamps 2.3 -> 3.8 mm off
POINT_FINEST_REFIT = False
#: whether those finer levels extrapolate their sweeps (:func:`_extrapolate`): on the 640x480
#: quilt no extrapolation there was kept at 2 sweeps a level (the same figures to 1e-4 without
#: it), and each tried costs an energy evaluation of every frame
POINT_SETTLED_EXTRAPOLATE = False
#: the CG factor (as :data:`POINT_SETTLED_CG_FACTOR`) of the finest level where a coarser level of
#: those refitted the lamps (static camera: its depth steps the plain hierarchy's). The 1280x960
#: D415-like quilt (20 frames, one numba thread): CG 36 -> 23 iterations there, about 1.3 CPU s,
#: normals 0.3831 -> 0.3836 deg (within 2 px of the image's edge 0.4858 -> 0.4887), albedo
#: 0.6295 -> 0.6296 %, lamps 3.64 mm either way
POINT_FINEST_CG_FACTOR = 30.0
#: whether that finest level refits the albedo after a depth step whose line search refitted it
#: already at the accepted depth (the step's albedo projection): a second IRLS round of the same
#: closed form, an albedo pass and an evaluation of every frame (about 0.35 CPU s a sweep at
#: 1.13 M pixels and 20 frames). Issue 32's 1280x960 D415-like quilt without it: normals 0.3836
#: -> 0.3836 deg (within 2 px of the edge 0.4887 -> 0.4896), albedo 0.6296 -> 0.6294 %, lamps
#: 3.64 mm and low-pass p95 0.0074 per mille either way. Left out on every level of more than
#: :data:`POINT_FIT_MAX_PIXELS` pixels, the edge's normals went 0.4887 -> 0.4935 deg (+1 %)
POINT_FINEST_ALBEDO_REFIT = False
#: pixels per frame read for the image noise of the LED's evidence weights, every sweep (the
#: median of 20 x 90 000 x 3 residuals took 1.4 of a D415 refine's 17.6 s; 10 000 a frame give
#: the noise to well under 1 %)
NOISE_SAMPLES_PER_FRAME = 10_000
#: a level's smoothness is weighted by the evidence (:func:`_weigh_smoothness`) at the start of
#: its first this-many sweeps only, then held, so the rest of the level minimises one energy.
#: Reweighted every sweep, the energy was a moving target: pixels that one frame alone sees (no
#: evidence) take the LED's ceiling weight, the sensor's smoothness over the LED's (1.7e6 at 2 MP,
#: 0.18 mm pixels), and as such pixels came and went with the visibility the prior energy jumped
#: 10-60x between sweeps, so no level reached the relative tolerance (2 MP, 20 frames: 50 sweeps,
#: every level at the cap). 3, not 1: on the speckled LED bunny (tests/test_grain.py) the finest
#: level's albedo-step weights follow the albedo's first sweeps (darkest quarter 10.39 deg at 3,
#: 10.43 at 2, 10.64 at 1, 10.35 reweighting every sweep)
EVIDENCE_SWEEPS = 3

#: the finest level also stops once its next sweep's relative energy drop, predicted from the
#: last two (geometric: d_k^2 / d_{k-1}), is below the tolerance, where the drops contract fast:
#: d_k / d_{k-1} below this ratio (:func:`_stalled`). Saved 2 MP problem (20 frames,
#: one thread): drops 0.150, 0.0119 (ratio 0.079, predicted 9.5e-4), the sixth sweep's actual
#: 9.9e-5 for 17.5 CPU s skipped: solve 116.5 -> 103.4 CPU s, normals 3.6162 -> 3.6153 deg,
#: depth 0.74055 -> 0.74051 mm. D415 (ratios 0.46, 0.41) is left alone: predicted alone (no
#: ratio), its sixth sweep (drop 6.9e-4) was skipped and cost normals 1.2923 -> 1.3156 deg,
#: depth 0.5182 -> 0.5255 mm. Fitted on these two captures (the bound between 0.079 and 0.41).
FINEST_FAST_CONTRACTION = 0.2
#: whether the finest level also stops once its data term (the images' robust misfit; the
#: smoothness weights do not enter it) falls by at most the tolerance in a sweep after the
#: :data:`EVIDENCE_SWEEPS` (:func:`_stalled`). At 2 MP (0.18 mm pixels) the priors outweigh the
#: data term 18 to 1 there: its sweeps 4-6 lowered the energy by 7.4 %, 1.9 % and 0.13 % but the
#: data term by 9.3e-4, 4.3e-4 and 7.8e-4, and the normals went 1.3824, 1.3845, 1.3835 deg (27 CPU s
#: for nothing). On D415 and the 640x480 demo, whose data term still falls by 2e-3 to 1e-2 a sweep
#: while the normals improve, it stops no level earlier: the same results bit for bit. A static
#: camera's finest level (weights held from the start) runs at most :data:`POINT_SETTLED_SWEEPS`.
#: Not on a coarser level: there the priors' settling is the next level's start (2 MP, a rule that
#: also stopped level 1 where a sweep raised its data term: the finest level then ran a sweep more,
#: 68.9 against 60.9 s, 1.3854 deg / 0.7896 mm against 1.3824 / 0.7791; docs/performance.md,
#: "The finest level's data term")
DATA_STALL = True
#: the finest level holds the poses where a coarser level of at least this many object pixels
#: refined them by joint steps, under a light that moves with the camera (:func:`_sweeps`'
#: ``hold_poses``). Its sweeps take the joint step's depth rows alone (the warp's parallax, the
#: albedo projected out, the joint CG tolerance), solved with the plain-aggregation hierarchy (no
#: twists its rounding could reach), and its extrapolation keeps no factor that raises the data
#: term (:func:`_extrapolate`'s ``keep_data``: there the energy is mostly the priors', and
#: extrapolations that lowered them at the images' expense were undone by the next step, sweep
#: after sweep). The twists had been half that level's assembly while moving the frames under
#: their error. A smaller level 1 (960x540: 12 000 pixels) leaves the poses less settled, and a
#: light fixed in the world leaves them to the parallax, which the finest level still improves.
#: Measurements: docs/performance.md, "The finest level holds the poses a coarser level settled"
#: and "The held finest level's hierarchy and extrapolation"
FINEST_HOLD_MIN_PIXELS = 16_000


#: rounds of albedo and lighting refits a sweep takes at most (:func:`_fit_albedo_lighting`;
#: :func:`_light_rounds` says where). One round (an albedo fit, then the lights') leaves a slow mode:
#: with the depth held, the ambient trades against the albedo and the LED's strength, and one
#: round a sweep moved it a few per cent a sweep, so the levels ended before it had (the D415
#: render's lights: consecutive updates at cosine 1.00, each 0.76-0.91 times the last). Rounds
#: until the data term settles, on three D415 renders (1280x720, SF 2, 20 frames, LED; seeds 0-2):
#: normals 1.1773 -> 1.0816, 1.0740 -> 1.0294, 1.1365 -> 1.0827 deg, depth 0.5316 -> 0.5257,
#: 0.5228 -> 0.5307, 0.5425 -> 0.5447 mm, sweeps 33 -> 26, refine 10.05-11.11 -> 10.66-11.02 s;
#: 4 rounds at most: 1.0860, 1.0386, 1.1000 deg; a round tolerance of 1e-3: 1.1147, 1.0566, 1.1222
#: deg. `make demo` (640x480): 2.1929 -> 2.1553 deg, 0.9840 -> 0.9752 mm, 35 -> 29 sweeps
LIGHT_ROUNDS = 8
#: ... until a round lowers the data term by at most this fraction
LIGHT_ROUND_TOLERANCE = 1e-4
#: the light models that take them (point lights, a static camera's, have their own lamp fits
#: and sweep counts, tuned with one round: not measured)
LIGHT_ROUND_MODELS = ("led", "sh", "room")
#: ... on captures whose reference frame sees the object in at most this many colour pixels. The
#: 2 MP renders (948 000, at 0.25 m) gained little and paid: normals 1.3824 -> 1.3606 and 0.9830
#: -> 0.9772 deg, refine 60.2 -> 69.0 and 66.4 -> 111.7 s (the finest level's sweep count follows
#: its start: 4 -> 8 sweeps on one); rounds on their levels of at most 200 000 pixels only: 85.8
#: and 115.6 s. D415's reference sees 86 000, the demo's 22 000
LIGHT_ROUND_MAX_PIXELS = 500_000


def normalised_tau(tau_tilde: float, n_frames: int, mean_intensity: float, n_hr: int, mean_z0: float, n_lr: int,
                   channels: int = 3) -> float:
    """tau = tau~ n mean(I)^2 |Omega_HR| |C| / (mean(z0)^2 |Omega_LR|) (paper section 5.1)."""
    return tau_tilde * n_frames * mean_intensity**2 * n_hr * channels / (mean_z0**2 * max(n_lr, 1))


def normalised_smoothness(mu_tilde: float, n_frames: int, mean_intensity: float, mean_z0: float, level: int,
                          channels: int = 3) -> float:
    """mu = mu~ n mean(I)^2 |C| / (mean(z0)^2 16^level): per pixel on the data term's scale, and
    on every level the same penalty of a surface's curvature (a second difference over pixels
    2^level times wider is 4^level times larger)."""
    return mu_tilde * n_frames * mean_intensity**2 * channels / (mean_z0**2 * 16.0**level)


def _reference_mask(problem_input: SolverInput) -> np.ndarray:
    """(H, W) bool: frame 0's mask, else its valid depth pixels."""
    mask = problem_input.masks[0]
    if mask is None:
        mask = repeat_pixels(problem_input.depths[0] > 0, problem_input.scale_factor)
    if not mask.any():
        raise CaptureError("the reference mask is empty (no object pixel in frame 0); give a mask that covers the object")
    return mask


def _sweeps(problem: LevelProblem, est: Estimate, options: RefineOptions, timings: dict, stats: dict,
            anchors: PoseAnchors | None = None, log: PoseLog | None = None, lamps_settled: bool = False,
            light_rounds: int = 1, hold_poses: bool = False, retarget: Callable | None = None) -> list:
    """Run one level's sweeps in place on ``est``: the albedo fitted to the level's images, then
    sweeps of poses and depth (one joint step, or the paper's two), albedo, lighting, LED offset,
    extrapolation. The level's evaluations live here only (no caller holds a stale one: each
    holds frames x pixels arrays). anchors: what a pose update must not worsen besides the
    photometric energy (:mod:`.pose_trust`; calibrated here per level), log: the rejections.
    lamps_settled: a coarser level of more than :data:`POINT_FIT_MAX_PIXELS` object pixels has
    refitted the point lights (the finest level then takes :data:`POINT_FINEST_SWEEPS` and
    :data:`POINT_FINEST_REFIT`). hold_poses: keep the poses (a coarser level settled them by joint
    steps: :data:`FINEST_HOLD_MIN_PIXELS`); the depth steps take the joint step's parallax rows and
    CG tolerance. retarget: ``retarget(problem, est)`` re-makes the level's depth prior from every
    frame's depth at the start of sweep :data:`.frames_depth.RETARGET_SWEEP` (the finest level's,
    :func:`.frames_depth.frames_depth_target`), or None. ``stats["pose_steps"]`` gains the level's
    [index, object pixels, how its poses were updated: "joint", "alternating", "held" or "none"].

    Returns the level's energy rows; stops at the relative energy change ``options.tolerance``
    (:func:`_stalled`).
    """
    level = problem.level
    t = time.perf_counter()
    prepare_depth_block(problem)  # its sparse products made before any evaluation or coupling is held
    ev = problem.evaluate(est)
    # fit the albedo to this level's images under the current lighting before the sweeps: the
    # coarse (or, on the first level, the reference image's) albedo lacks the detail the pose
    # and depth steps compare against. Fitting lighting first would explain the reference image
    # by ambient light alone, since the initial albedo is that image.
    ev = refit_albedo(problem, est, ev)
    if options.model.cauchy_scale() == AUTO:  # the level's noise floor, once its albedo fits
        problem.lam = robust_scale(ev.residual, ev.usable)
        ev = problem.reevaluate(est, ev, overwrite=True)
    stats["cauchy_lambda"].append(problem.lam)
    timings["setup"] += time.perf_counter() - t
    # a point light per frame is fitted in reference coordinates, for all frames together: a
    # pose step's per-frame shading cannot name its light (and a free light absorbs the pose's)
    refine_poses = (options.refine_poses and problem.n_frames > 1 and level.grid.size >= options.pose_min_pixels
                    and problem.light.name != "point")
    held = refine_poses and hold_poses  # the depth steps keep the joint step's rows and tolerance
    refine_poses = refine_poses and not held
    # a light fixed in the world shades every frame alike: the depth learns from the parallax
    # alone, so every depth step takes it, on every level (the joint step's size limit is for
    # lights that also inform the normals)
    parallax_only = problem.light.fixed_in_world
    joint = refine_poses and options.joint_pose_depth and (parallax_only or level.grid.size >= options.joint_min_pixels)
    stats["pose_steps"].append([level.index, int(level.grid.size),
                                "joint" if joint else "alternating" if refine_poses else "held" if held else "none"])
    if refine_poses and anchors is not None:
        t = time.perf_counter()
        anchors.calibrate(problem.lam, est.poses, problem.points(est.z), ev.usable,
                          pose_information(problem, est, ev) if anchors.trust is not None else None,
                          footprint=(anchors.scale_factor / 2**level.index) ** 2)
        timings["pose_anchors"] += time.perf_counter() - t
    else:
        anchors = None
    # the LED offset is estimated where the poses are (coarser levels constrain it as poorly)
    refine_offset = (options.refine_led_offset and problem.light.name == "led"
                     and level.grid.size >= options.pose_min_pixels)
    # one image cannot tell albedo from shading: projected out, the albedo would absorb all shading
    project_albedo = options.project_albedo and problem.n_frames > 1
    _weigh_smoothness(problem, est, ev, options, timings, stats)
    rows = [{"level": level.index, "iteration": 0, "energy": ev.energy}]
    lamp_history = []  # the point lights at the start of each sweep (_lamps_creeping)
    finest = problem.light.name == "point" and level.index == 0 and lamps_settled
    sweeps = options.max_iterations
    if problem.light.name == "point" and level.grid.size <= POINT_FIT_MAX_PIXELS:
        sweeps *= POINT_SWEEP_FACTOR  # the lamps creep down a valley with the depth
    elif problem.light.name == "point" and POINT_SETTLED_SWEEPS is not None:
        sweeps = min(sweeps, POINT_SETTLED_SWEEPS)  # the lamps placed: the depth's detail settles in a few
        if finest and POINT_FINEST_SWEEPS is not None:
            sweeps = min(sweeps, POINT_FINEST_SWEEPS)
    bar = tqdm(range(1, sweeps + 1), desc=f"level {level.index} ({level.size[1]}x{level.size[0]})",
               disable=not options.progress, leave=False)
    # point lights on a level that no longer places the lamps: their per-pixel fields make the
    # evidence cost a frames x pixels x 3 x 3 sum, weighed once per level; CG to a looser tolerance
    settled = problem.light.name == "point" and level.grid.size > POINT_FIT_MAX_PIXELS
    accelerator = level_accelerator(problem.light.name, level.grid.size)  # across sweeps, tried before the extrapolation
    # a static camera (poses held at the identity): the depth steps' plain-aggregation hierarchy
    # (linear.PLAIN_AMG_OPTIONS); where its smoothness weights are held (settled), S^T S too
    static = not options.refine_poses and problem.identity_poses(est)
    level.prior.hold_products(static and settled)
    drop = None  # the last sweep's relative energy drop (_stalled)
    for iteration in bar:
        refitted = False  # the albedo refitted by this sweep's depth step (below)
        if retarget is not None and iteration == RETARGET_SWEEP:  # before the sweep's first energy
            t = time.perf_counter()
            retarget(problem, est)
            ev.prior = problem.prior_energy(est.z, pending=True)
            timings["frames_depth"] += time.perf_counter() - t
        # the first sweep's weights are set before the level's first energy; then held after
        # EVIDENCE_SWEEPS sweeps, so the rest of the level minimises one energy
        if 1 < iteration <= EVIDENCE_SWEEPS and not settled:
            _weigh_smoothness(problem, est, ev, options, timings, stats)
        previous, previous_data = ev.energy, ev.data
        start = _snapshot(est)
        lamp_history.append(start.led_offset)
        if joint:
            t = time.perf_counter()
            stepped, ev, cg_iterations = update_pose_depth(problem, est, ev, rtol=options.joint_cg_tolerance,
                                                           maxiter=options.cg_max_iterations,
                                                           project_albedo=project_albedo, anchors=anchors)
            poses_before, (est.z, est.albedo, est.poses) = est.poses, (stepped.z, stepped.albedo, stepped.poses)
            timings["poses_depth"] += time.perf_counter() - t
            if anchors is not None:
                t = time.perf_counter()
                est.poses, ev = keep_agreeing_poses(problem, poses_before, est, ev, anchors, log)
                timings["pose_anchors"] += time.perf_counter() - t
        else:
            if refine_poses:
                t = time.perf_counter()
                est.poses, ev = update_poses(problem, est, ev, options.pose_iterations, options.pose_tolerance,
                                             anchors, log)
                timings["poses"] += time.perf_counter() - t
            t = time.perf_counter()
            stepped, ev, cg_iterations = update_depth(problem, est, ev,
                                                      rtol=options.joint_cg_tolerance if held else
                                                      options.cg_tolerance * (
                                                          POINT_FINEST_CG_FACTOR if finest else
                                                          POINT_SETTLED_CG_FACTOR if settled else 1.0),
                                                      maxiter=options.cg_max_iterations,
                                                      project_albedo=project_albedo, parallax=parallax_only or held,
                                                      plain=static or held)
            # the step's line search refitted the albedo at the depth it kept (project_albedo)
            refitted = project_albedo and stepped is not est
            est.z, est.albedo = stepped.z, stepped.albedo
            timings["depth"] += time.perf_counter() - t
        stats["cg_iterations"].append(cg_iterations)
        t = time.perf_counter()
        ev, rounds = _fit_albedo_lighting(problem, est, ev, rounds=light_rounds,
                                          refit_first=not (finest and refitted and not POINT_FINEST_ALBEDO_REFIT))
        stats["light_rounds"].append(rounds)
        if refine_offset:
            est.led_offset, ev = update_led_offset(problem, est, ev, min_decrease=0.1 * options.tolerance,
                                                   relative=True)  # of ev's energy (on a GPU read with the step's)
        # every sweep (point_light.POINT_FINE_MIN_PIXELS: how, by level), but see POINT_FINEST_REFIT
        if problem.light.name == "point" and (POINT_FINEST_REFIT or level.index > 0 or not lamps_settled):
            ev = fit_point_lights(problem, est, ev)
        timings["albedo_lighting"] += time.perf_counter() - t
        if options.extrapolate and (POINT_SETTLED_EXTRAPOLATE or not settled):
            t = time.perf_counter()
            ev = _extrapolate(problem, est, ev, start, anchors, accelerator=accelerator, keep_data=held)
            timings["extrapolation"] += time.perf_counter() - t
        rows.append({"level": level.index, "iteration": iteration, "energy": ev.energy, "cg_iterations": cg_iterations})
        bar.set_postfix(energy=f"{ev.energy:.5g}")
        drop, last_drop = (previous - ev.energy) / abs(previous) if previous else 0.0, drop  # relative
        data_drop = (previous_data - ev.data) / abs(previous_data) if previous_data else 0.0
        if _stalled(level.index, iteration, settled, last_drop, drop, options.tolerance, data_drop) and not (
                problem.light.name == "point" and not settled and _lamps_creeping(est, lamp_history)):
            break
    bar.close()
    if accelerator is not None:
        stats.setdefault("anderson", []).append([level.index, accelerator.proposed, accelerator.kept])
    level.prior.hold_products(False)
    stats["frame_rms"] = ev.frame_rms()  # the finest level's stays: the report's per-frame residual
    return rows


def _light_rounds(light_name: str, object_pixels: int) -> int:
    """The albedo-and-lighting rounds a sweep takes at most (:func:`_fit_albedo_lighting`):
    :data:`LIGHT_ROUNDS` for the light models in :data:`LIGHT_ROUND_MODELS` on a capture whose
    reference sees the object in at most :data:`LIGHT_ROUND_MAX_PIXELS` colour pixels, else 1."""
    return LIGHT_ROUNDS if light_name in LIGHT_ROUND_MODELS and object_pixels <= LIGHT_ROUND_MAX_PIXELS else 1


def _fit_albedo_lighting(problem: LevelProblem, est: Estimate, ev, refit_first: bool = True, rounds: int = 1):
    """The albedo and the lights refitted in turn at the sweep's depth and poses, in place on
    ``est`` (the albedo first where ``refit_first``; a sweep's last step is the lights'), until a
    round lowers the data term by at most :data:`LIGHT_ROUND_TOLERANCE` (relative), or after
    ``rounds`` rounds (:func:`_light_rounds`); returns the evaluation at the result (``ev`` is given
    up) and the rounds taken."""
    previous = ev.data if rounds > 1 else None
    for taken in range(1, rounds + 1):
        if refit_first or taken > 1:
            ev = refit_albedo(problem, est, ev, scored=False)  # the lights' energy is read, not this one
        est.lights = update_lighting(est, ev, problem.lam, problem.light_model(est))
        ev = problem.reevaluate(est, ev, overwrite=True)
        if taken < rounds:
            current = ev.data
            if previous - current <= LIGHT_ROUND_TOLERANCE * abs(previous):
                break
            previous = current
    return ev, taken


def _stalled(level_index: int, iteration: int, settled: bool, last_drop: float | None, drop: float,
             tolerance: float, data_drop: float | None = None) -> bool:
    """Whether a level's sweeps stop after sweep ``iteration`` (from 1): its relative energy drop
    ``drop`` ((previous - new) / previous) is within ``tolerance``. On the finest level
    (``level_index`` 0) also, after :data:`EVIDENCE_SWEEPS` sweeps (the smoothness weights held
    since), where the data term's relative drop ``data_drop`` is in [0, ``tolerance``] (the images
    explained as well as they will be, only the priors' energy still falling: :data:`DATA_STALL`);
    and, once the weights are held (``settled``, or after those sweeps, so ``last_drop``, the
    sweep before's, is of the same energy), where the next drop, predicted as geometric,
    ``drop**2 / last_drop``, is within ``tolerance`` and the drops contract faster than
    :data:`FINEST_FAST_CONTRACTION`."""
    if abs(drop) <= tolerance:
        return True
    if level_index != 0 or not (settled or iteration > EVIDENCE_SWEEPS):
        return False
    if DATA_STALL and iteration > EVIDENCE_SWEEPS and data_drop is not None and 0.0 <= data_drop <= tolerance:
        return True
    if last_drop is None or last_drop <= 0 or drop <= 0:
        return False
    ratio = drop / last_drop
    return ratio < FINEST_FAST_CONTRACTION and drop * ratio <= tolerance


def _lamps_creeping(est: Estimate, history: list) -> bool:
    """Whether the point lights (``est.led_offset`` (n, 3), metres) moved, on average, by more
    than :data:`POINT_CREEP_TOLERANCE` of their mean distance from the camera since the start of
    the sweep :data:`POINT_CREEP_SWEEPS` - 1 sweeps before the last (``history``: their positions
    at each sweep's start). A sweep whose lamp refit is refused moves them not at all, and the
    next one (the depth bent further) moves them again: judged over a few sweeps."""
    before = history[-POINT_CREEP_SWEEPS] if len(history) >= POINT_CREEP_SWEEPS else history[0]
    if est.led_offset is None or before is None or np.shape(est.led_offset) != np.shape(before):
        return False
    moved = np.linalg.norm(np.asarray(est.led_offset) - np.asarray(before), axis=1).mean()
    return bool(moved > POINT_CREEP_TOLERANCE * np.linalg.norm(np.asarray(est.led_offset), axis=1).mean())


def _weigh_smoothness(problem: LevelProblem, est: Estimate, ev, options: RefineOptions, timings: dict,
                      stats: dict) -> None:
    """Weight each pixel's smoothness by the shading's evidence (:mod:`.weighting`; per-frame SH:
    relative to the median pixel, else against an absolute normal precision up to the sensor's
    own smoothness, and on the finest level of a capture that leans on it the albedo's steps too)
    and update ``ev``'s prior energy, where the options ask for it; at the start of every sweep."""
    if not (options.model.evidence_weighted() and problem.mu > 0 and problem.level.prior.S is not None):
        return
    t = time.perf_counter()
    evidence = normal_evidence(problem.light_model(est), est, ev, problem.points(est.z))
    if problem.light.name in ("sh", "point"):  # a large smoothness: relative to the median pixel
        weights = evidence_weights(evidence)
    else:  # a small one (LED): where the shading's normal is noisier than the sensor's
        noise = robust_scale(ev.residual, ev.usable, NOISE_SAMPLES_PER_FRAME)
        ceiling = stats["sensor_smoothness"] / max(stats["smoothness"], 1e-12)
        weights = absolute_evidence_weights(evidence, noise, ceiling)
        # the frames themselves on the finest level, point-sampled (coarser levels: area averages)
        if problem.level.index == 0 and leans_on_smoothness(weights):
            steps = albedo_step_factor(est.albedo, problem.level.grid, ev.shading, ev.usable, noise)
            weights = albedo_step_weights(weights, evidence, steps, noise, ceiling)
    problem.level.prior.weigh_smoothness(weights)
    ev.prior = problem.prior_energy(est.z, pending=True)  # on a GPU read where first used
    timings["evidence_weights"] += time.perf_counter() - t


def _snapshot(est: Estimate) -> Estimate:
    """A copy of the unknowns, taken at the start of a sweep (on a GPU z and albedo themselves,
    no launch: the steps replace those arrays, never write into them)."""
    if on_gpu(est.z):
        z, albedo = est.z, est.albedo
    else:
        z, albedo = est.z.copy(), est.albedo.copy()
    return Estimate(z, albedo, est.lights.copy(), est.poses.copy(),
                    None if est.led_offset is None else est.led_offset.copy())


def _extrapolate(problem: LevelProblem, est: Estimate, ev, before: Estimate, anchors: PoseAnchors | None = None,
                 factors=(1.0, 2.0, 4.0), accelerator: Anderson | None = None, keep_data: bool = False):
    """Extrapolate the last sweep's move of every unknown; keep the best energy-lowering factor.

    Alternating steps creep along the valley where poses, depth and albedo trade off against
    each other (a rotation of a frame about the object moves the image by a fraction of a pixel);
    continuing the sweep's own direction shortens the creep. ``before`` is the snapshot taken at
    the start of the sweep, ``est`` (evaluated as ``ev``) where it ended; unknowns the sweep did
    not move stay put. Returns the evaluation of the result (``ev`` itself, or a new one, and then
    ``ev`` is released). With ``anchors`` the poses' depth agreement and prior count too (a
    factor is kept only where energy plus anchors falls).

    The factors are judged by their energy alone, a few frames at a time (:meth:`.LevelProblem.energy`),
    and only the one kept is evaluated in full, after ``ev`` is released: never two evaluations
    held at once (at 2 MP and 20 frames 1.2 GB each). accelerator: the level's Anderson history
    (:mod:`.acceleration`; None: none): its point is tried first (:func:`_accelerated`), and the
    factors only where it is not kept. keep_data: a factor is kept only where the data term
    (the energy less the prior's) does not rise above ``ev``'s either, and Anderson's point is
    not tried (a held finest level: :data:`FINEST_HOLD_MIN_PIXELS`).
    """
    best = None
    poses_moved = not np.array_equal(est.poses, before.poses)  # else kept exactly (no log/exp round trip)

    def anchored(energy: float, trial: Estimate, usable) -> float:
        if anchors is None or not poses_moved:
            return energy
        points = problem.points(trial.z)
        return energy + sum(anchors.frame_energy(i, trial.poses[i], points, usable[i])
                            for i in range(1, len(trial.poses)))

    current = anchored(ev.energy, est, ev.usable)
    if accelerator is not None and not keep_data:  # Anderson's point first; the factors where it is not kept
        best, current = _accelerated(problem, est, before, accelerator, current, poses_moved, anchored)
        if best is not None:
            ev.release()
            est.z, est.albedo, est.lights, est.poses, est.led_offset = (best.z, best.albedo, best.lights, best.poses,
                                                                        best.led_offset)
            return problem.evaluate(est)
    delta_poses = [se3.log(T @ np.linalg.inv(T0)) for T, T0 in zip(est.poses, before.poses)] if poses_moved else []
    trials = _device_trials(problem, est, before, factors)  # None on the CPU
    batch = None  # on a GPU every factor's energy in one launch and one read (and one copy over)
    if trials is not None:
        candidates = [Estimate(trials[0][j], trials[1][j], *_trial(est, before, factor, delta_poses, poses_moved))
                      for j, factor in enumerate(factors)]
        batch = problem.trial_energies(trials[0], trials[1], candidates)
        if batch is None:  # every factor's poses and lights copied over at once (one copy, not one a factor)
            preload_light_states([(problem.light_model(c), c.lights, c.poses) for c in candidates], est.z)
    for j, factor in enumerate(factors):
        if trials is None:
            z = problem.level.prior.clip(_extrapolated(est.z, before.z, factor))
            if not np.all(z > 0):
                break
            albedo = _extrapolated(est.albedo, before.albedo, factor)
        elif trials[2][j]:
            z, albedo = trials[0][j], trials[1][j]
        else:
            break
        trial = Estimate(z, albedo, *_trial(est, before, factor, delta_poses, poses_moved))
        prior = problem.prior_energy(z) if keep_data else None
        energy, usable = problem.energy(trial, prior=prior) if batch is None else (float(batch[0][j]), batch[1][j])
        trial_energy = anchored(energy, trial, usable)
        if trial_energy < current and (not keep_data or energy - prior <= ev.data):
            best, current = trial, trial_energy
        else:
            break
    if best is None:
        return ev
    ev.release()  # superseded: not held while the kept factor is evaluated
    est.z, est.albedo, est.lights, est.poses, est.led_offset = (best.z, best.albedo, best.lights, best.poses,
                                                                best.led_offset)
    return problem.evaluate(est)


def _accelerated(problem: LevelProblem, est: Estimate, before: Estimate, accelerator: Anderson, current: float,
                 poses_moved: bool, anchored: Callable) -> tuple:
    """(Anderson's point (:mod:`.acceleration`) or None, the energy to beat): the point, its depth
    clipped into the prior's envelope (the poses kept where the sweep did not move them), where its
    energy (plus anchors: ``anchored``) is below ``current``."""
    point = accelerator.propose(est, before)
    if point is None:
        return None, current
    for fraction in ANDERSON_FRACTIONS:
        trial = partway(est, point, fraction)
        trial.z = problem.level.prior.clip(trial.z)
        if not poses_moved:
            trial.poses = est.poses
        if not np.all(trial.z > 0):
            continue
        energy, usable = problem.energy(trial)
        energy = anchored(energy, trial, usable)
        if energy < current:
            break
    else:
        return None, current
    accelerator.kept += 1
    return trial, energy


def _trial(est: Estimate, before: Estimate, factor: float, delta_poses: list, poses_moved: bool) -> tuple:
    """:func:`_extrapolate`'s trial lights (n, k), poses (n, 4, 4) and LED offset (or None) at ``factor``."""
    offset = None if est.led_offset is None else est.led_offset + factor * (est.led_offset - before.led_offset)
    return (est.lights + factor * (est.lights - before.lights),
            np.stack([se3.exp(factor * d) @ T for d, T in zip(delta_poses, est.poses)]) if poses_moved else est.poses,
            offset)


def _device_trials(problem: LevelProblem, est: Estimate, before: Estimate, factors) -> tuple | None:
    """:func:`_extrapolate`'s trial depths and albedos on a GPU, every factor's in one launch
    (:func:`.kernels.extrapolation_trials`: extrapolated, the depth clipped into the prior's
    envelope) and one copy back, none where the envelope is positive
    (:attr:`.pyramid.DepthPrior.envelope_positive`): (z (F, N), albedo (F, N, 3), positive (F,)
    bool: every trial depth > 0); None on the CPU, or for factors or albedos that kernel does not take."""
    if not (on_gpu(est.z) and len(factors) <= MAX_EXTRAPOLATION_FACTORS and est.z.ndim == 1
            and est.albedo.shape == (est.z.size, 3)):
        return None
    xp, prior, N, F = array_module(est.z), problem.level.prior, est.z.size, len(factors)
    z, albedo, bad = xp.empty((F, N)), xp.empty((F, N, 3)), xp.empty((F, extrapolation_blocks(N)))
    kernels_for(est.z).extrapolation_trials(*(contiguous(a, np.float64) for a in (est.z, before.z, est.albedo,
                                                                                 before.albedo)),
                                            tuple(float(f) for f in factors), *envelope_arrays(prior, xp), z, albedo,
                                            bad)
    if getattr(prior, "envelope_positive", False):  # clipped into a positive envelope: no read (a NaN
        return z, albedo, np.ones(F, dtype=bool)      # trial's energy is NaN, and it is not kept)
    return z, albedo, to_host(bad).sum(axis=1) == 0


@fused
def _extrapolated(x, x0, factor):
    """``x + factor (x - x0)`` (any shape; one kernel on a GPU)."""
    return x + factor * (x - x0)


def _tie_to_sensor(problem: LevelProblem, g, est: Estimate, z0: np.ndarray, sigma: float) -> None:
    """At a level's end, give ``est``'s depth the sensor's low frequencies
    (:func:`.weighting.tie_low_frequencies`, Gaussian of ``sigma`` depth pixels; z0 (h, w) the
    sensor depth, metres) and refit the albedo to the tied depth, in place. g: the level's grid
    on the host."""
    tied = tie_low_frequencies(g.scatter(to_host(est.z)), g.mask, z0, sigma)
    est.z = problem.level.prior.clip(like(g.gather(tied), est.z))
    ev = problem.evaluate(est, scored=False)  # its residuals' weights alone are read
    est.albedo = update_albedo(est, ev, problem.lam)
    ev.release()


@dataclass
class Carried:
    """The unknowns handed from one pyramid level to the next: z (H, W) metres and albedo
    (H, W, 3) on the level's full image grid (filled outside the mask), lights (n, k), poses
    (n, 4, 4) and the LED offset (3,) or None."""

    z: np.ndarray
    albedo: np.ndarray
    lights: np.ndarray
    poses: np.ndarray
    led_offset: np.ndarray | None

    def resized(self, size: tuple[int, int]) -> "Carried":
        """The same unknowns with z and albedo bilinearly resampled to a (H, W) grid."""
        return replace(self, z=resize(self.z, size, interpolation=cv2.INTER_LINEAR),
                       albedo=resize(self.albedo, size, interpolation=cv2.INTER_LINEAR))


def coarse_to_fine(n_levels: int, solve_level: Callable[[int, "Carried | None"], "Carried | None"]) -> Carried:
    """Solve levels n_levels - 1 (coarsest) .. 0 (finest) in turn: ``solve_level(index, carried)``
    gets what the last solved level returned (None before the first) and returns the level's
    result, or None to pass ``carried`` on (a level too small to solve). The per-level solve is
    kept apart from the loop (the shape of scikit-image's ``coarse_to_fine(..., solver)``)."""
    carried = None
    for index in reversed(range(n_levels)):
        carried = solve_level(index, carried) or carried
    if carried is None:
        raise CaptureError("no pyramid level has 16 object pixels; give a larger mask or more depth pixels")
    return carried


def solve(problem_input: SolverInput, options: RefineOptions | None = None, device="cpu") -> SolverOutput:
    """Jointly estimate depth (colour resolution), albedo, lighting and poses of ``problem_input``.

    options: None solves with ``problem_input.options``. device: "cpu" ("CPU:0"), "cuda[:N]"
    (the per-pixel arrays on the GPU, with CuPy and numba's CUDA target; pyramid levels of fewer
    than :data:`.device.CUDA_MIN_LEVEL_PIXELS` object pixels on the CPU) or an
    :class:`~.device.ArrayDevice`; a CUDA device that cannot run raises
    :class:`~o3d_mvps.errors.DeviceError` saying what is missing (:func:`.device.check_device`).
    ``info["level_devices"]`` of the result says where each level ran, coarsest first.

    The light model is ``options.light_model``, or where that is None the one that explains the
    images best on a coarse level (:func:`.light_selection.select_light_model`; a declared model
    that fits clearly worse than another is kept with a warning): ``info["light_selection"]``.
    ``info["pose_updates"]`` says how far each frame's pose moved and how many of its updates
    were rejected (:mod:`.pose_trust`); ``info["pose_steps"]`` how each level updated them
    ([level, object pixels, "joint", "alternating", "held" or "none"], coarsest first). On Linux
    with glibc the process's malloc is set (:func:`.allocator.return_freed_arrays`): freed arrays
    of 8 MB and more go back to the system, except that a static camera's frames of any size and a
    moving camera's from 1.5 megapixels on take every block from the heap through the solve,
    glibc's mapping of large blocks set back after it.
    """
    options = problem_input.options if options is None else options
    device = array_device(device)
    pixels = int(np.prod(problem_input.color_size))
    static = not options.refine_poses and bool(np.allclose(problem_input.initial_poses, np.eye(4)))
    return_freed_arrays(pixels, static=static)
    if options.progress and (notice := compile_notice(device)):
        print(notice, flush=True)
    # The solver's BLAS calls are vector dots/norms (CG, AMG) and thin products: on a loaded
    # 2-core machine OpenBLAS's threads made each 60k-vector norm take ~5 ms instead of 30 us
    # (~20 % of a 640x480 refinement); one thread loses nothing on an idle machine.
    try:
        with threadpool_limits(1, user_api="blas"):
            return _solve(problem_input, options, device)
    finally:
        map_large_blocks()  # where the solve took every block from the heap


def frames_mean_depths(problem_input: SolverInput, mode: FramesDepth) -> np.ndarray:
    """The sensor depths (n, h, w) metres the solve ties to: ``problem_input.depths``, or where
    ``mode`` (``average_frames_depth``) is "initial" a copy whose frame 0 is the frames' mean at the
    initial poses (:func:`~o3d_mvps.covisibility.reference_depth_mean`), judged by the depth noise
    the frames' disagreement gave (``problem_input.depth_noise``: a moving camera of 4 frames or
    more; none measured, nothing averaged). Made here, by the solver, so that a saved problem holds
    the sensor's own depth and solves as ``refine`` did. The report's "reference_depth_outliers"
    then counts the averaged pixels ("averaged") and its input checks gain a "frames' mean depth"
    row. A moving camera asked for the frames' depth ("initial" or "finest") without a measured
    noise or with fewer than :data:`~o3d_mvps.covisibility.MEAN_MIN_FRAMES` frames is warned that
    frame 0's depth alone is used (a static camera's reference depth is the frames' already)."""
    depths, noise = problem_input.depths, problem_input.depth_noise
    usable = _frames_depth_usable(problem_input)
    if mode != FramesDepth.OFF and not usable and not np.allclose(problem_input.initial_poses, np.eye(4)):
        warnings.warn(f"average_frames_depth={mode.value!r} needs {MEAN_MIN_FRAMES} frames or more and the depth "
                      f"noise their disagreement gives ({problem_input.n_frames} frames, noise "
                      f"{'not measured' if noise is None else 'measured'}; refine measures it, and a problem saved "
                      "without it must be saved again with --save-problem): the depth is tied to frame 0's alone",
                      stacklevel=4)
    if mode != FramesDepth.INITIAL or not usable:
        return depths
    t = time.perf_counter()
    depths = np.array(depths, copy=True)
    valid = int((depths[0] > 0).sum())
    mean, averaged = reference_depth_mean(depths, problem_input.initial_poses, problem_input.depth_K, noise)
    depths[0] = mean
    report = problem_input.report
    report.setdefault("reference_depth_outliers", {}).update(averaged=int(averaged.sum()),
                                                             averaging_seconds=round(time.perf_counter() - t, 4))
    report.setdefault("inputs", {"checks": [], "conventions": {}})["checks"].append(frames_mean_check(averaged, valid))
    return depths


def _frames_depth_usable(problem_input: SolverInput) -> bool:
    """Whether the frames' depth can enter the prior (either mode of ``average_frames_depth``): their
    disagreement measured the depth noise that judges them, over at least
    :data:`~o3d_mvps.covisibility.MEAN_MIN_FRAMES` frames."""
    return problem_input.depth_noise is not None and problem_input.n_frames >= MEAN_MIN_FRAMES


def _solve(problem_input: SolverInput, options: RefineOptions, device: ArrayDevice) -> SolverOutput:
    timings = defaultdict(float)
    t0 = time.perf_counter()
    K = problem_input.K
    size = problem_input.color_size
    colors = problem_input.colors
    masks = problem_input.masks
    ref_mask = _reference_mask(problem_input)
    declared = None if options.light_model is None else str(options.light_model)
    n_levels = int(options.levels)
    while n_levels > 1 and min(level_size(size, n_levels - 1)) < 8:
        n_levels -= 1
    # the coarse levels' frames, each frame decoded once for all of them (the light selection's
    # level is one of them); a level's are dropped once it is built
    images = coarse_images(colors, [level_size(ref_mask.shape, index) for index in range(1, n_levels)])
    selection = select_light_model(problem_input, ref_mask, declared, occlusion_test=options.occlusion_test,
                                   occlusion_tolerance=options.occlusion_tolerance,
                                   static=bool(np.allclose(problem_input.initial_poses, np.eye(4))), images=images)
    options = replace(options, light_model=selection["chosen"])
    timings["light_selection"] = time.perf_counter() - t0
    if options.progress:
        print(f"light model: {selection['chosen']} ({selection['why']})")
    if not (problem_input.depths[0] > 0).any():
        raise CaptureError("the reference depth has no valid pixel; check the depth image of frame 0")
    noise = problem_input.depth_noise
    sensor_depths = frames_mean_depths(problem_input, options.average_frames_depth)
    z0 = sensor_depths[0].astype(np.float64)
    depth_K = problem_input.depth_K
    sf = problem_input.scale_factor
    n_frames = problem_input.n_frames
    mean_z0 = float(z0[z0 > 0].mean())
    mean_I = float(colors[0][ref_mask].mean())

    light = make_light_model(options.light_model, initial_sh=options.initial_light,
                             led_offset=problem_input.led_offset)
    if light.name == "point" and options.refine_poses and n_frames > 1:
        warnings.warn("the point light model (a lamp per frame, for a static camera) keeps the initial poses: "
                      "they are not refined; for a camera that moved with its own LED use --light-model led "
                      "(RefineOptions(light_model='led'))", stacklevel=3)
    rounds = _light_rounds(light.name, int(ref_mask.sum()))
    smoothness = options.model.smoothness_weight()
    sensor_smoothness = auto_smoothness(options.tau, z0, ref_mask, sf, K)
    if smoothness == AUTO:
        smoothness = sensor_smoothness
    tie_sigma = options.model.lowpass_width()
    if tie_sigma == AUTO:
        tie_sigma = lowpass_sigma(z0, ref_mask, sf)
    history = []
    # given poses answer to their own sensor depth and a prior at their stated trust; registered
    # poses do not: the registration already used the depth, and on the 640x480 bunny (20
    # frames, LED) the depth check held them 3.4 mm from the truth (mean) where the images alone
    # take them to 0.64 mm
    given = problem_input.pose_trust is not None
    anchors = (PoseAnchors(sensor_depths, depth_K, problem_input.initial_poses, problem_input.pose_trust,
                           scale_factor=sf) if given else None)
    pose_log = PoseLog()
    settled_levels = []  # the levels that refitted the point lights with the albedo projected out
    stats = {"cg_iterations": [], "light_rounds": [], "pose_steps": [], "cauchy_lambda": [],
             "smoothness": smoothness,
             "sensor_smoothness": sensor_smoothness,
             "levels": n_levels,
             "level_devices": [], "sensor_lowpass_sigma": tie_sigma}

    moving = options.refine_poses and not np.allclose(problem_input.initial_poses, np.eye(4))

    def retarget(g, problem: LevelProblem, est: Estimate) -> None:
        """The finest level's depth prior from every frame's depth at the current surface and poses
        (:func:`.frames_depth.frames_depth_target`; g: the level's grid on the host);
        ``stats["frames_depth"]`` says how many of frame 0's depth pixels took the frames' mean."""
        target, averaged = frames_depth_target(g.scatter(to_host(est.z)), ref_mask, K, depth_K, sf,
                                               np.asarray(sensor_depths, dtype=np.float64), np.asarray(est.poses),
                                               noise, z0)
        prior = depth_prior(g, target, sf / 2**problem.level.index)
        if prior.z0.shape == problem.level.prior.z0.shape:
            problem.level.prior.retarget(prior.z0)
            stats["frames_depth"] = {"averaged": int(averaged.sum()), "of": int((z0 > 0).sum())}

    finest = options.average_frames_depth == FramesDepth.FINEST and _frames_depth_usable(problem_input)
    frames_retarget = retarget if finest and moving else None
    if finest and not moving:  # the poses held: said, not silent
        warnings.warn("average_frames_depth='finest' compares the frames at the poses the solve refines; with the "
                      "poses held (refine_poses=False, --no-pose-refinement) it is not made and the depth is tied "
                      "to frame 0's alone: 'initial' (--average-frames-depth initial) averages the frames at the "
                      "given poses", stacklevel=3)

    def solve_level(level_index: int, carried: Carried | None) -> Carried | None:
        """:func:`level_solve`, its compiled kernels on as many threads as its size earns
        (:func:`~o3d_mvps.model.parallel.kernel_threads`; the count is restored after)."""
        previous = current_kernel_threads()
        try:
            return level_solve(level_index, carried)
        finally:
            set_kernel_threads(previous)

    def level_solve(level_index: int, carried: Carried | None) -> Carried | None:
        """One level: the level's problem, the unknowns gathered from ``carried`` (None on the
        first level: the sensor depth, the reference image, the initial lights and poses), the
        initial albedo fit and the sweeps; returns the unknowns on the level's full grid (None
        for a level too small to solve, which passes ``carried`` on)."""
        t = time.perf_counter()
        trim_heap()  # the previous level's freed arrays out of the resident set before this level's are made
        level = build_level(level_index, colors, masks, ref_mask, K, z0, sf, options.difference_scheme,
                            options.depth_envelope, options.model.slope_weighted(),
                            grid_modes=partial(grid_mode_weight, light.name, n_frames,
                                               lamp_level_pixels=POINT_FIT_MAX_PIXELS),
                            images=images.pop(level_size(ref_mask.shape, level_index), None))
        g = level.grid
        if g.size < 16 or (light.name == "point" and g.size < POINT_MIN_PIXELS and level_index > 0):
            return None
        set_kernel_threads(kernel_threads(g.size, current_kernel_threads()))  # a coarse level: too short to share
        first = carried is None
        if first:
            z_full = resize(fill_nearest_valid(z0, z0 > 0), level.size, interpolation=cv2.INTER_LINEAR)
            # the LED offset and the point lights' positions are unknowns, like the rest
            offset = (light.offset.copy() if light.name == "led" else np.zeros((n_frames, 3)) if light.name == "point"
                      else None)
            carried = Carried(z_full, float_frame(level.images[0]).astype(np.float64), light.initial_lights(n_frames, mean_z0),
                              problem_input.initial_poses.copy(), offset)
        else:
            carried = carried.resized(level.size)
        level_device = device if g.size >= device.min_level_pixels else CPU
        stats["level_devices"].append(level_device.name)
        est = Estimate(level_device.asarray(level.prior.clip(g.gather(carried.z).astype(np.float64))),
                       level_device.asarray(g.gather(carried.albedo).astype(np.float64)), carried.lights,
                       carried.poses, carried.led_offset)
        carried = z_full = None  # the full-grid z and albedo are not held through the level (30 MB at D415 size)
        tau = normalised_tau(options.tau, n_frames, mean_I, g.size, mean_z0, level.prior.rows)
        mu = normalised_smoothness(smoothness, n_frames, mean_I, mean_z0, level_index)
        # AUTO: the LED's scale for the level's first albedo fit, then the residuals' (_sweeps)
        scale = options.model.cauchy_scale()
        problem = LevelProblem(level.on_device(level_device), tau,
                               DEFAULT_CAUCHY_LAMBDA["led"] if scale == AUTO else scale, light, mu,
                               residual_dtype=level_device.residual_dtype)
        problem.update_visibility(est, occlusion_test=options.occlusion_test, rel_tol=options.occlusion_tolerance,
                                  sensor_depths=sensor_depths, depth_K=depth_K)
        timings["setup"] += time.perf_counter() - t
        if first and light.name == "point":  # the lights' start, from per-frame SH on the first level
            t = time.perf_counter()
            initial_point_lights(problem, est, problem.evaluate(est, scored=False)).release()  # its samples read
            timings["point_lights"] += time.perf_counter() - t
        # the finest level after a coarser level's joint steps on enough pixels to settle the poses
        hold = level_index == 0 and not light.fixed_in_world and any(
            kind == "joint" and pixels >= FINEST_HOLD_MIN_PIXELS for _, pixels, kind in stats["pose_steps"])
        history.extend(_sweeps(problem, est, options, timings, stats, anchors, pose_log,
                               lamps_settled=bool(settled_levels), light_rounds=rounds, hold_poses=hold,
                               retarget=partial(frames_retarget, g) if level_index == 0 and frames_retarget else None))
        if light.name == "point" and g.size > POINT_FIT_MAX_PIXELS:
            settled_levels.append(level_index)
        if tie_sigma is not None:
            t = time.perf_counter()
            _tie_to_sensor(problem, g, est, z0, tie_sigma)
            timings["sensor_tie"] += time.perf_counter() - t
        return Carried(fill_nearest_valid(g.scatter(to_host(est.z)), g.mask),
                       fill_nearest_valid(g.scatter(to_host(est.albedo)), g.mask), est.lights, est.poses, est.led_offset)

    result = coarse_to_fine(n_levels, solve_level)
    trim_heap()  # the finest level's freed arrays: not resident through what the caller does next (report, export)
    z_full, albedo_full, lights, poses, led_offset = (result.z, result.albedo, result.lights, result.poses,
                                                      result.led_offset)
    depth = np.where(ref_mask, z_full, 0.0)
    albedo = np.clip(np.where(ref_mask[..., None], albedo_full, 0.0), 0.0, None)
    timings["total"] = time.perf_counter() - t0
    frame_rms = stats.pop("frame_rms", [])
    stats["residuals"] = [{"frame": int(f), "rms": None if np.isnan(v) else v}
                          for f, v in zip(problem_input.frames, frame_rms)]
    stats["initial_poses"] = np.asarray(problem_input.initial_poses, dtype=np.float64).tolist()
    return SolverOutput(
        depth, ref_mask, albedo, K, lighting=lights, poses=poses, energy=history, timings=dict(timings),
        info={"frames": problem_input.frames, "options": options.to_dict(), "device": device.name,
              "light_model": (light if led_offset is None else light.at(led_offset)).describe(),
              "light_selection": selection,
              "pose_updates": pose_log.report(problem_input.initial_poses, poses, problem_input.pose_trust,
                                             problem_input.frames),
              **stats},
    )

