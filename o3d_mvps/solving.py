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

from .capture import Capture, to_host
from .errors import CaptureError
from .fileio import check_output_files
from .model import se3
from .refinement import Refinement
from .solver.device import check_device
from .solver.driver import solve
from .solver.options import RefineOptions
from .solver.pose_trust import DEFAULT_POSE_TRUST
from .solver.problem_input import SolverInput, write_problem
from .views import MIN_OTHER_FRAMES, ViewSelection, frames_seeing_reference


def refine(capture: Capture, options: RefineOptions | None = None, device="CPU:0", initial_poses=None, *,
           pose_trust=None, save_problem=None, overwrite: bool = False) -> Refinement:
    """Jointly estimate depth (colour resolution), albedo, lighting and poses from a capture.

    capture: frame 0 is the reference; ``initial_poses`` (n, 4, 4) reference -> frame i, an array
    or an o3d.core.Tensor on any device (default: the registration chain of
    :func:`o3d_mvps.odometry.register_frames`, which drops a frame it cannot place, with a warning,
    unless ``options.strict_registration``). pose_trust: how far given ``initial_poses`` are
    trusted, (millimetres, degrees) (default :data:`o3d_mvps.solver.pose_trust.DEFAULT_POSE_TRUST`,
    2 mm and 0.2 deg): the refinement keeps them unless the images and every frame's own depth
    agree on a better one (``info["pose_updates"]`` says how far each moved and how many
    updates were rejected); False: refine them freely, like registered poses (for poses from
    :func:`o3d_mvps.odometry.initial_poses`). device: "CPU:0" or "CUDA:0" (see
    :func:`o3d_mvps.solver.device.check_device`). save_problem: also write the solver's input to
    this .npz once the frames are registered (``python -m o3d_mvps.solver`` solves it; refuses an
    existing file unless ``overwrite``). Of more than three frames, those that see too little of
    the reference's surface are left out (:func:`o3d_mvps.views.frames_seeing_reference`).
    Returns a :class:`~o3d_mvps.Refinement`; ``info["frames"]`` lists the capture's frames it
    used, ``info["views"]`` each frame's covisibility and why a frame was left out.
    """
    options = options or RefineOptions()
    check_device(device)
    if save_problem is not None:
        check_output_files([save_problem], overwrite)
    t0 = time.perf_counter()
    problem_input, views = problem_from_capture(capture, options, initial_poses, pose_trust)
    odometry = time.perf_counter() - t0
    if save_problem is not None:
        write_problem(problem_input, save_problem, overwrite=overwrite)
    output = solve(problem_input, problem_input.options, device)
    return Refinement.from_arrays(
        output.depth, output.mask, output.K, albedo=output.albedo, poses=output.poses, lighting=output.lighting,
        method="ours", energy=output.energy, info={**output.info, **({"views": views.to_dict()} if views else {})},
        timings={"odometry": odometry, **output.timings, "total": time.perf_counter() - t0},
    )


def problem_from_capture(capture: Capture, options: RefineOptions, initial_poses=None,
                         pose_trust=None) -> tuple[SolverInput, ViewSelection | None]:
    """The solver's input from a capture: the frames ``options.frames`` picks, minus those the
    registration drops when no ``initial_poses`` are given and those that do not see the
    reference (see :func:`refine`); and that view selection (None with three frames or fewer).
    The input's options name the light model (:func:`with_light_model`); its pose trust is
    ``pose_trust`` (mm, degrees) or the default where poses are given, None where registered
    (or ``pose_trust`` is False)."""
    options = with_light_model(options, capture)
    frames = options.frame_indices(capture.n_frames)
    if initial_poses is not None:
        initial_poses = np.asarray(to_host(initial_poses), dtype=np.float64)
        if initial_poses.shape != (capture.n_frames, 4, 4):
            raise ValueError(f"initial_poses must be ({capture.n_frames}, 4, 4), got {initial_poses.shape}")
        initial_poses = se3.relative_to_reference(initial_poses[frames])  # onto the first frame used
        trust = DEFAULT_POSE_TRUST if pose_trust is None else None if pose_trust is False else _pose_trust(pose_trust)
    else:
        trust = None
    capture = capture.select(frames)
    if initial_poses is None:
        if capture.n_frames > 1:
            from .odometry import register_frames

            registration = register_frames(capture, strict=options.strict_registration, progress=options.progress)
            capture, initial_poses = capture.select(registration.frames), registration.poses
            frames = [frames[k] for k in registration.frames]
        else:
            initial_poses = np.eye(4)[None]
    views = None
    if capture.n_frames > MIN_OTHER_FRAMES + 1:  # e.g. a ring: keep the frames that see the reference's surface
        views = frames_seeing_reference(capture, initial_poses, frame_ids=frames)
        keep = [frames.index(i) for i in views.frames]
        capture, initial_poses, frames = capture.select(keep), initial_poses[keep], views.frames
    n = capture.n_frames
    return SolverInput(
        colors=[capture.color_array(i) for i in range(n)],  # the capture's frames, not a copy
        depths=np.stack([capture.depth_array(i) for i in range(n)]),
        masks=[capture.mask_array(i) for i in range(n)],
        K=capture.color_K(), depth_K=capture.depth_K(), scale_factor=capture.scale_factor,
        initial_poses=initial_poses, led_offset=_led_offset(options, capture), frames=frames, options=options,
        pose_trust=trust,
    ), views


def _pose_trust(pose_trust) -> tuple[float, float]:
    """(metres, radians) of a pose trust given as (millimetres, degrees); ValueError naming it otherwise."""
    trust = np.asarray(pose_trust, dtype=np.float64).reshape(-1)
    if trust.shape != (2,) or not np.all(np.isfinite(trust)) or not np.all(trust > 0):
        raise ValueError(f"pose_trust (--pose-trust MM DEG) must be two positive numbers, millimetres and degrees "
                         f"(e.g. 2 0.2), got {pose_trust!r}")
    return float(trust[0]) * 1e-3, float(np.radians(trust[1]))


#: The solver's light model for each capture.json "light".
LIGHT_MODEL_OF_CAPTURE = {"led": "led", "room": "room"}


def with_light_model(options: RefineOptions, capture: Capture) -> RefineOptions:
    """``options`` with the declared light model: the one given, else the capture's
    (:data:`LIGHT_MODEL_OF_CAPTURE`), else None: the solver then chooses it from the images
    (:func:`o3d_mvps.solver.light_selection.select_light_model`, reported in
    ``info["light_selection"]``)."""
    if options.light_model is not None or capture.light is None:
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
        raise CaptureError(f"led_offset {offset.tolist()} must be (x, y, z) in metres within 1 m of the camera; "
                           "fix 'led_offset' in capture.json's metadata or pass RefineOptions(led_offset=...)")
    return offset
