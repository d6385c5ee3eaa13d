"""``refine(capture) -> Refinement``: the Open3D side of the solver.

A capture's frames are picked and registered, and its images, masks, intrinsics and LED offset
read into a :class:`~o3d_mvps.solver.problem_input.SolverInput` (plain NumPy arrays);
:func:`o3d_mvps.solver.driver.solve` solves it without Open3D, and its output comes back as a
:class:`~o3d_mvps.Refinement`.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import replace

import numpy as np

from .capture import Capture, CameraSetting, camera_setting, frame_white_balance, to_host
from .capture.static import MIN_FRAMES_FOR_MEDIAN, reference_depth_mean, reference_depth_outliers, unsteady_depth
from .capture.checks import check_inputs
from .capture.layout import COLOR_DIR
from .capture.poses import GivenPoses
from .colour import CodedColours
from .errors import CaptureError
from .fileio import check_output_files
from .model import se3
from .refinement import Refinement
from .run_report import NOT_PICKED, peak_memory_mb, recorded_warnings
from .solver.allocator import map_large_blocks, return_freed_arrays, trim_heap
from .solver.device import check_device
from .solver.driver import solve
from .solver.options import AUTO, ConvergenceCriteria, ModelOptions, RefineOptions
from .solver.pose_trust import DEFAULT_POSE_TRUST
from .solver.problem_input import SolverInput, write_problem
from .solver.solution import SolverOutput
from .solver.smoothness import sensor_noise_smoothness
from .covisibility import (MIN_OTHER_FRAMES, OUTLIER_MIN_FRAMES, WEAK_COVERAGE_NOTE, ViewSelection,
                           frames_seeing_reference)
from .covisibility import flying_pixels_check, frame_depths_in_reference
from .covisibility import reference_depth_fill as moving_reference_fill
from .covisibility import reference_depth_outliers as moving_reference_outliers

#: the depth step's CG tolerance for a static camera, where ``cg_tolerance`` is left at its default
#: (1e-4): each depth step of the reweighted least squares is a linearisation anyway, and on the
#: rendered bunny (20 frames, D415-like) 1e-3 gave the same normals, depth and albedo to 0.001 deg,
#: 0.001 mm and 0.01 points, in about 0.7 of the refine's CPU time at 1280x960 (10.7 s against 15.0)
STATIC_CG_TOLERANCE = 1e-3


def refine(capture: Capture, options: RefineOptions | None = None, device="auto", initial_poses=None, *,
           pose_trust=None, save_problem=None, overwrite: bool = False, checks: bool = True) -> Refinement:
    """Jointly estimate depth (colour resolution), albedo, lighting and poses from a capture.

    capture: frame 0 is the reference; ``initial_poses`` (n, 4, 4) reference -> frame i, an array
    or an o3d.core.Tensor on any device, or a :class:`~o3d_mvps.capture.poses.GivenPoses` (a pose
    file read by :func:`~o3d_mvps.capture.poses.given_poses`) (default: the registration chain of
    :func:`o3d_mvps.odometry.register_frames`, which drops a frame it cannot place, with a warning,
    unless ``options.strict_registration``). pose_trust: how far given ``initial_poses`` are
    trusted, (millimetres, degrees) (default :data:`o3d_mvps.solver.pose_trust.DEFAULT_POSE_TRUST`,
    2 mm and 0.2 deg): the refinement keeps them unless the images and every frame's own depth
    agree on a better one (``info["pose_updates"]`` says how far each moved and how many
    updates were rejected); False: refine them freely, like registered poses (for poses from
    :func:`o3d_mvps.odometry.initial_poses`). device: "auto" (the GPU when it can solve, else the
    CPU), "CPU:0" or "CUDA:0" (see :func:`o3d_mvps.solver.device.check_device`); ``info["device"]``
    says where it solved. save_problem: also write the solver's input to
    this .npz once the frames are registered (``python -m o3d_mvps.solver`` solves it; refuses an
    existing file unless ``overwrite``). Of more than three frames, those that see too little of
    the reference's surface are left out (:func:`o3d_mvps.covisibility.frames_seeing_reference`).
    A static-camera capture (:func:`o3d_mvps.capture.camera_setting`: declared in capture.json or
    detected from the depth) is not registered: its poses are the identity (or ``initial_poses``),
    not refined, and every frame is used; ``info["camera"]`` says how it was decided.
    Before the solve, ``checks`` runs :func:`o3d_mvps.capture.checks.check_inputs` (intrinsics,
    depth scale, frame quality, poses against depth; well under 1 % of a solve), which raises
    CaptureError naming a mix-up and its fix and drops bad frames with a warning.
    Returns a :class:`~o3d_mvps.Refinement`; ``info["frames"]`` lists the capture's frames it
    used, ``info["views"]`` each frame's covisibility and why a frame was left out,
    ``info["inputs"]`` the checks, ``info["frames_report"]`` every frame, used or why not,
    ``info["dropped_frames"]`` the frames the registration could not place, ``info["warnings"]``
    the warnings raised, ``info["stage_peak_memory_mb"]`` the process's peak memory after each
    stage; :meth:`~o3d_mvps.Refinement.report` gathers them.
    """
    options = options or RefineOptions()
    device = check_device(device)
    if save_problem is not None:
        check_output_files([save_problem], overwrite)
    # before the registration too (the solver sets it again); a heap-only mode (2 MP moving frames)
    # ends however the refine does
    return_freed_arrays(int(np.prod(capture.color_size)))
    t0 = time.perf_counter()
    said, dropped, memory = [], {}, {}
    try:
        with recorded_warnings(said):
            camera = camera_setting(capture, _host_poses(initial_poses))
            problem_input, views = problem_from_capture(capture, options, initial_poses, camera=camera,
                                                        dropped=dropped, checks=checks, pose_trust=pose_trust)
            # the solver's input holds what the solve reads of the capture (its colour frames, not
            # copied): where the caller lets go of the capture too (the command line), its masks,
            # depth images and ground truth are freed before the solve
            capture_frames, capture = capture.n_frames, None
            odometry = time.perf_counter() - t0
            memory["odometry"] = peak_memory_mb()
            if save_problem is not None:
                write_problem(problem_input, save_problem, overwrite=overwrite)
            output = solve(problem_input, problem_input.options, device)
            if camera.static and all(mask is None for mask in problem_input.masks):
                output = _unsteady_left_out(output, problem_input)
            memory["solve"] = peak_memory_mb()
    finally:
        map_large_blocks()
    # the solver's input goes, and with it the frames where the caller let go of the capture: their
    # pages given back now (glibc keeps freed heap blocks resident: 210 MB at D415 size)
    report, problem_input = problem_input.report, None
    trim_heap()
    info = {**output.info, **({"views": views.to_dict()} if views else {}), **report,
            "camera": camera.to_dict(), "capture_frames": capture_frames,
            "dropped_frames": {str(i): why for i, why in dropped.items()}, "stage_peak_memory_mb": memory,
            "warnings": said}
    return Refinement.from_arrays(
        output.depth, output.mask, output.K, albedo=output.albedo, poses=output.poses, lighting=output.lighting,
        method="ours", energy=output.energy, info=info,
        timings={"odometry": odometry, **output.timings, "total": time.perf_counter() - t0},
    )


def _unsteady_left_out(output: SolverOutput, problem_input: SolverInput) -> SolverOutput:
    """``output`` without the colour pixels of the depth pixels that a static camera's frames other
    than the reference disagree on (:func:`~o3d_mvps.capture.static.unsteady_depth`: flying in most
    of them), for a capture without masks, whose output is where the reference has depth; their
    count in the report's ``reference_depth_outliers``. Only the output: the solve keeps them."""
    depths = problem_input.depths
    if len(depths) <= MIN_FRAMES_FOR_MEDIAN:
        return output
    unsteady = unsteady_depth(np.asarray(depths[1:]))
    (H, W), (h, w) = output.mask.shape, unsteady.shape
    sf = problem_input.scale_factor
    cut = output.mask & unsteady[np.minimum(np.arange(H) // sf, h - 1)][:, np.minimum(np.arange(W) // sf, w - 1)]
    problem_input.report.setdefault("reference_depth_outliers", {})["left_out_of_output"] = int(cut.sum())
    if not cut.any():
        return output
    return replace(output, mask=output.mask & ~cut, depth=np.where(cut, 0.0, output.depth),
                   albedo=np.where(cut[..., None], 0.0, output.albedo))


def _host_poses(initial_poses) -> np.ndarray | None:
    """(n, 4, 4) reference -> frame i on the host, from any form ``refine`` takes, or None."""
    if initial_poses is None:
        return None
    return initial_poses.poses if isinstance(initial_poses, GivenPoses) else to_host(initial_poses)


def problem_from_capture(capture: Capture, options: RefineOptions, initial_poses=None, *,
                         camera: CameraSetting | None = None, dropped: dict | None = None,
                         checks: bool = True, pose_trust=None) -> tuple[SolverInput, ViewSelection | None]:
    """The solver's input from a capture: the frames ``options.frames`` picks, minus those the
    input checks drop (``checks``), those the registration drops when no ``initial_poses`` are
    given and those that do not see the reference (see :func:`refine`); and that view selection
    (None with three frames or fewer). The input's options name the light model
    (:func:`with_light_model`); its ``report`` holds ``inputs`` and ``frames_report``; its pose
    trust is ``pose_trust`` (mm, degrees) or the default where poses are given, None where
    registered (or ``pose_trust`` is False). A static-camera capture (``camera``, default
    :func:`~o3d_mvps.capture.camera_setting` of the capture) keeps every frame, identity poses
    (unless given) and no pose refinement. ``dropped``: a dict given here gets {capture frame
    index: why} of the frames the registration dropped."""
    camera = camera_setting(capture, _host_poses(initial_poses)) if camera is None else camera
    if camera.static:
        capture = replace(capture, camera="static")
        options = replace(options, refine_poses=False)
        if options.cg_tolerance == ConvergenceCriteria.cg_tolerance:  # left at the default
            options = replace(options, cg_tolerance=STATIC_CG_TOLERANCE)
    options = with_light_model(options, capture)
    all_frames = [f"{COLOR_DIR}/{name}" for name in capture.frame_names] if capture.frame_names \
        else [None] * capture.n_frames
    frames = options.frame_indices(capture.n_frames)
    given = None
    if initial_poses is not None:
        given = initial_poses if isinstance(initial_poses, GivenPoses) else GivenPoses.from_array(
            np.asarray(to_host(initial_poses), dtype=np.float64))
        if given.world_to_camera.shape != (capture.n_frames, 4, 4):
            raise ValueError(f"initial_poses must be ({capture.n_frames}, 4, 4), got {given.world_to_camera.shape}")
        trust = DEFAULT_POSE_TRUST if pose_trust is None else None if pose_trust is False else _pose_trust(pose_trust)
    else:
        trust = None
    capture = capture.select(frames)
    why = {i: NOT_PICKED for i in range(len(all_frames)) if i not in frames}
    report = {}
    if checks:
        t0 = time.perf_counter()
        found = check_inputs(capture, given, frames=frames, frames_asked=options.frames is not None,
                             pose_trust=trust)
        why.update({row["index"]: row["reason"] for row in found.frames if not row["used"]})
        capture, frames = capture.select(found.usable), [frames[k] for k in found.usable]
        found.checks.append(camera.check())  # its warning was said when it was decided (camera_setting)
        report["inputs"] = {**found.to_dict(), "seconds": round(time.perf_counter() - t0, 4)}
    if given is not None:
        initial_poses = se3.relative_to_reference(given.world_to_camera[frames])  # onto the first frame used
    elif camera.static:
        initial_poses = np.tile(np.eye(4), (capture.n_frames, 1, 1))
    if initial_poses is None:
        if capture.n_frames > 1:
            from .odometry import register_frames

            registration = register_frames(capture, strict=options.strict_registration, progress=options.progress)
            lost = {frames[k]: reason for k, reason in registration.dropped.items()}
            if dropped is not None:
                dropped.update(lost)
            why.update(lost)
            capture, initial_poses = capture.select(registration.frames), registration.poses
            frames = [frames[k] for k in registration.frames]
        else:
            initial_poses = np.eye(4)[None]
    views = None
    # e.g. a ring: keep the frames that see the reference's surface (a static camera's all see it)
    if capture.n_frames > MIN_OTHER_FRAMES + 1 and not camera.static:
        ids = frames if capture.frame_ids is None else [int(i) for i in capture.frame_ids]  # as the user knows them
        local = dict(zip(ids, frames))  # -> its index in the capture given
        views = frames_seeing_reference(capture, initial_poses, frame_ids=ids)
        keep = [ids.index(i) for i in views.frames]
        capture, initial_poses, frames = capture.select(keep), initial_poses[keep], [local[i] for i in views.frames]
        why.update({local[int(i)]: reason for i, reason in views.left_out.items()})
        weak = views.weak_coverage()
        if weak is not None:
            options = lean_on_sensor(options, capture)
            warnings.warn(f"{weak}: the refinement leans on the sensor depth ({WEAK_COVERAGE_NOTE}); capture more "
                          "frames 15-30 degrees around the reference for photometric detail", stacklevel=3)
    report["frames_report"] = [{"index": i, "file": name, "used": i in frames, "reason": why.get(i)}
                               for i, name in enumerate(all_frames)]
    n = capture.n_frames
    colors = capture_colours(capture)
    masks = [capture.mask_array(i) for i in range(n)]
    if camera.static and n > 1:
        # the light models have one intensity per frame: a white balance that drifts between
        # frames would stay in the albedo (D415-like drift of +-4 %: 640x480 bunny 0.8 % -> 0.5 %)
        balance = frame_white_balance(colors, masks)
        colors = (colors.divided(balance) if isinstance(colors, CodedColours) else
                  [(c / balance[i].astype(np.float32)).astype(np.float32) for i, c in enumerate(colors)])
        report["white_balance"] = {"frames": np.round(balance, 6).tolist(),
                                   "detail": "each frame's colour divided by its white balance relative to the "
                                             "frames' mean (o3d_mvps.capture.frame_white_balance)"}
    depths = np.stack([capture.depth_array(i) for i in range(n)])
    depth_noise = None  # measured by a moving camera's flying-pixel check
    if camera.static and n >= MIN_FRAMES_FOR_MEDIAN:
        # flying pixels of the reference (the depth prior's) left out: at the 640x480 D415-like
        # bunny's silhouette they pulled the rim back and brightened its albedo
        flying = reference_depth_outliers(depths)
        depths[0][flying] = 0.0
        # the frames' mean depth, its speckle holes filled: the frames' depth noise averages out
        # (640x480 D415-like quilt: normals 0.92 -> 0.45 deg, albedo 1.60 -> 1.02 %), and without
        # masks the holes were cut out of the output
        depths[0], fill = reference_depth_mean(depths)
        report["reference_depth_outliers"] = {"pixels": int(flying.sum()), "fraction": round(float(flying.mean()), 6),
                                              "filled": int(fill.sum())}
    elif not camera.static and n > OUTLIER_MIN_FRAMES:
        # a moving camera's the same way, the frames' depth moved into the reference by the initial
        # poses: at the speckled, room-lit bunny's rim they held the depth centimetres back, where
        # depth fusion averages them away (docs/fidelity.md, "Flying pixels of a moving camera").
        # Always counted and reported; replaced unless drop_depth_outliers=False (each one's depth
        # from the frames that agree there, else from its kept neighbours, never behind the
        # reference's own nearest kept neighbour: on the room scene of tests/test_scenes.py, 80 x 60
        # depth, the frames agreed on the wall behind the object)
        t0 = time.perf_counter()
        K_depth = capture.depth_K()
        warped = frame_depths_in_reference(depths, initial_poses, K_depth)
        flying, noise = moving_reference_outliers(depths, initial_poses, K_depth, warped=warped, return_noise=True)
        depth_noise = noise
        found = {"pixels": int(flying.sum()), "fraction": round(float(flying.mean()), 6),
                 "noise_mm_at_1m": round(1000 * noise, 4), "replaced": bool(options.drop_depth_outliers)}
        from_frames = foreground = None
        if options.drop_depth_outliers:
            values, from_frames, foreground = moving_reference_fill(depths, initial_poses, K_depth, flying, noise,
                                                                    warped=warped)
            found.update(from_frames=int(from_frames.sum()), from_foreground=int(foreground.sum()),
                         from_neighbours=int((flying & ~from_frames & ~foreground).sum()))
        valid = int((depths[0] > 0).sum())
        if from_frames is not None:
            depths[0][flying] = values[flying]
        report["reference_depth_outliers"] = {**found, "seconds": round(time.perf_counter() - t0, 4)}
        inputs = report.setdefault("inputs", {"checks": [], "conventions": {}})
        inputs["checks"].append(flying_pixels_check(flying, from_frames, valid, noise, foreground))
    return SolverInput(
        colors=colors,
        depths=depths,
        masks=masks,
        K=capture.color_K(), depth_K=capture.depth_K(), scale_factor=capture.scale_factor,
        initial_poses=initial_poses, led_offset=_led_offset(options, capture), frames=frames, options=options,
        report=report, pose_trust=trust, depth_noise=depth_noise,
    ), views


def capture_colours(capture: Capture) -> CodedColours | list:
    """The capture's colour frames as the solver reads them, not copied: frames read from files
    (codes) as :class:`~o3d_mvps.colour.CodedColours` decoded by the capture's
    ``color_encoding`` (a quarter of the float32 frames' memory for 8-bit files), float frames
    as a list of (H, W, 3) float32 arrays."""
    codes = [capture.color_codes(i) for i in range(capture.n_frames)]
    if codes and all(c is not None for c in codes):
        return CodedColours.from_codes(codes, srgb=capture.color_encoding == "srgb")
    return [capture.color_array(i) for i in range(capture.n_frames)]


#: how many times the depth prior's weight tau~ a refinement of a reference few frames see
#: takes (:func:`lean_on_sensor`): on 8 frames 45 degrees apart around a speckled LED-lit bunny
#: (320x240, SF 2, D415-like sensor) the normals were 11.1 deg off at 1x, 7.6 at 10x and 100x,
#: 8.6 at 1000x (bicubic 9.8)
WEAK_COVERAGE_TAU_FACTOR = 10.0


def lean_on_sensor(options: RefineOptions, capture: Capture) -> RefineOptions:
    """``options`` for a reference few frames see (:meth:`ViewSelection.weak_coverage`): the depth
    prior weighed :data:`WEAK_COVERAGE_TAU_FACTOR` times more, the smoothness the sensor's own
    noise calls for (:func:`o3d_mvps.solver.smoothness.sensor_noise_smoothness` of ``capture``'s
    reference depth, at that weight), no evidence weights (they would raise the smoothness to
    the sensor's with the stereo's floor, 10 x more here) and the sensor tie on; tau~ only where
    left at its default, the smoothness, tie and evidence weights only where the caller left them
    unset. Three frames' shading adds more error than detail: with 3 of 8 frames 45 degrees
    apart seeing an LED-lit speckled bunny's reference (320x240, SF 2, D415-like sensor) the normals were 23.1 deg off with the
    LED's defaults, 11.0 with the sensor's smoothness (auto) and tie, and are 7.6 so (bicubic
    upsampling's 9.8; the darkest albedo quarter 9.3 against 10.3: docs/fidelity.md,
    tests/test_grain.py)."""
    tau = options.tau * WEAK_COVERAGE_TAU_FACTOR if options.tau == ModelOptions.tau else options.tau  # unless chosen
    smoothness = options.smoothness
    if smoothness is None:
        smoothness = sensor_noise_smoothness(tau, capture.depth_array(0).astype(np.float64), capture.mask_array(0),
                                             capture.scale_factor, capture.color_K())
    return replace(options, tau=tau, smoothness=smoothness,
                   evidence_weights=False if options.evidence_weights is None else options.evidence_weights,
                   sensor_lowpass=AUTO if options.sensor_lowpass is None else options.sensor_lowpass)


def _pose_trust(pose_trust) -> tuple[float, float]:
    """(metres, radians) of a pose trust given as (millimetres, degrees); ValueError naming it otherwise."""
    trust = np.asarray(pose_trust, dtype=np.float64).reshape(-1)
    if trust.shape != (2,) or not np.all(np.isfinite(trust)) or not np.all(trust > 0):
        raise ValueError(f"pose_trust (--pose-trust MM DEG) must be two positive numbers, millimetres and degrees "
                         f"(e.g. 2 0.2), got {pose_trust!r}")
    return float(trust[0]) * 1e-3, float(np.radians(trust[1]))


#: The solver's light model for each capture.json "light".
LIGHT_MODEL_OF_CAPTURE = {"led": "led", "room": "room", "point": "point"}


def with_light_model(options: RefineOptions, capture: Capture) -> RefineOptions:
    """``options`` with the declared light model: the one given, else the capture's
    (:data:`LIGHT_MODEL_OF_CAPTURE`), else None: the solver then chooses it from the images
    (:func:`o3d_mvps.solver.light_selection.select_light_model`, reported in
    ``info["light_selection"]``; for a static camera, a light moved by hand, between per-frame SH
    and a point light per frame)."""
    if options.light_model is not None:
        return options
    if capture.light is None:
        return options
    return replace(options, light_model=LIGHT_MODEL_OF_CAPTURE[capture.light])


def _led_offset(options: RefineOptions, capture: Capture) -> np.ndarray:
    """The LED offset (3,) metres to start from: the option, else the capture's metadata, else 0."""
    offset = options.led_offset if options.led_offset is not None else capture.metadata.get("led_offset")
    if offset is None:
        if options.light_model == "led":
            warnings.warn("no LED offset given: starting from an LED at the colour lens (0, 0, 0). Measure where "
                          "the LED sits relative to the lens (within ~1 cm) and pass RefineOptions(led_offset=...) "
                          "or --led-offset, or write metadata.led_offset into capture.json", stacklevel=4)
        return np.zeros(3)
    offset = np.asarray(offset, dtype=np.float64)
    if offset.shape != (3,) or not np.isfinite(offset).all() or np.abs(offset).max() > 1.0:
        values = " ".join(f"{v:g}" for v in np.ravel(offset))
        hint = (f" (in millimetres? that is {' '.join(f'{v / 1000:g}' for v in offset)} m)"
                if offset.shape == (3,) and np.isfinite(offset).all() and np.abs(offset).max() <= 1000.0 else "")
        if options.led_offset is not None:  # the caller's value: --led-offset or RefineOptions(led_offset=...)
            raise CaptureError(f"--led-offset {values} (RefineOptions(led_offset=...)) must be the LED's x y z in "
                               f"metres, within 1 m of the colour lens{hint}")
        raise CaptureError(f"led_offset [{values}] in the capture's capture.json (metadata.led_offset) must be the "
                           f"LED's x y z in metres, within 1 m of the colour lens{hint}; fix it there or pass "
                           "--led-offset X Y Z (RefineOptions(led_offset=...)), which takes precedence")
    return offset
