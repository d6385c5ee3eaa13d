"""RefineOptions: everything a researcher varies in a refinement."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..model.normals import SCHEMES
from ..model.shading import INITIAL_LIGHT
from .lighting import LIGHT_MODELS


@dataclass
class RefineOptions:
    """Options of :func:`o3d_mvps.refine`.

    frames: number of frames to use (the first ``frames``), a list of indices, or None for all.
    tau: normalised depth-prior weight tau~ (paper default 10; the authors' code used ~100).
    cauchy_lambda: Cauchy scale lambda (intensity units, linear RGB in [0, 1]).
    levels: coarse-to-fine pyramid levels (coarsest is 1 / 2^(levels-1) of the colour size).
    max_iterations: sweep cap per level (one sweep = poses, depth, albedo, lighting).
    tolerance: stop a level when the relative energy change falls below it.
    refine_poses: refine poses jointly (False gives the paper's two-stage baseline).
    occlusion_test: drop reference pixels hidden or out of view in frame i from its data term.
    pose_iterations: Gauss-Newton iterations per frame and sweep.
    pose_tolerance: stop a frame's Gauss-Newton iterations once one lowers its energy by less
        than this fraction (0: always run ``pose_iterations``).
    pose_min_pixels: refine poses only on levels whose reference mask has this many pixels
        (coarser levels see too little of the object to constrain six degrees of freedom).
    cg_tolerance, cg_max_iterations: preconditioned CG for the depth system.
    occlusion_tolerance: relative depth tolerance of the occlusion test.
    difference_scheme: depth derivatives of the normals, "central" or the paper's "forward"
        (see o3d_mvps.model.normals).
    extrapolate: after each sweep, try continuing its move of every unknown (x1, x2, x4) and keep
        the best that lowers the energy; shortens the slow creep of poses, depth and albedo
        against each other.
    joint_pose_depth: on levels that refine poses, replace the paper's pose and depth updates
        by one Gauss-Newton step on both, with the warp's parallax in the depth (see
        o3d_mvps.solver.joint); False runs the paper's two updates.
    joint_cg_tolerance: relative CG tolerance of that step (an inexact Newton step).
    joint_min_pixels: take the joint step only on levels with this many object pixels; coarser
        levels keep the paper's updates (there the joint step let the poses drift toward the
        coarse images' biased minimum).
    project_albedo: eliminate the albedo from the depth and joint steps (variable projection,
        see o3d_mvps.solver.joint), so they move it along with z instead of leaving it to the
        albedo update; False gives the paper's depth step with the albedo held fixed (as
        does a single frame, whose one image cannot tell albedo from shading).
    depth_envelope: keep each pixel's depth between the least and greatest sensor depth around
        it, widened by this relative margin (None: unbounded); see
        o3d_mvps.solver.pyramid.depth_envelope.
    light_model: "led" (a point light moving with the camera, 1/r^2 falloff, plus ambient; the
        paper's future work, see o3d_mvps.solver.lighting) or "sh" (the paper's first-order
        spherical harmonics per frame).
    led_offset: LED position (x, y, z) in metres in the colour camera's frame (x right, y down,
        z forward); None takes ``led_offset`` from the capture's metadata, else (0, 0, 0).
    refine_led_offset: estimate the LED offset jointly, starting from ``led_offset``.
    initial_light: SH lighting every frame starts from (light_model "sh").
    strict_registration: without initial poses, raise when the registration cannot place a
        frame instead of dropping it with a warning (see o3d_mvps.odometry.register_frames).
    progress: show a progress bar per level.
    """

    frames: int | list | None = None
    tau: float = 10.0
    cauchy_lambda: float = 0.04
    levels: int = 5
    max_iterations: int = 10
    tolerance: float = 1e-5
    refine_poses: bool = True
    occlusion_test: bool = True
    pose_iterations: int = 3
    pose_tolerance: float = 1e-3
    pose_min_pixels: int = 1000
    cg_tolerance: float = 1e-4
    cg_max_iterations: int = 300
    occlusion_tolerance: float = 0.02
    difference_scheme: str = "central"
    extrapolate: bool = True
    joint_pose_depth: bool = True
    joint_cg_tolerance: float = 1e-2
    joint_min_pixels: int = 10000
    project_albedo: bool = True
    depth_envelope: float | None = 0.02
    light_model: str = "led"
    led_offset: tuple | None = None
    refine_led_offset: bool = True
    initial_light: tuple = INITIAL_LIGHT
    strict_registration: bool = False
    progress: bool = True

    def __post_init__(self):
        checks = [
            (self.tau > 0, f"tau must be > 0, got {self.tau}"),
            (self.cauchy_lambda > 0, f"cauchy_lambda must be > 0, got {self.cauchy_lambda}"),
            (int(self.levels) >= 1, f"levels must be >= 1, got {self.levels}"),
            (int(self.max_iterations) >= 1, f"max_iterations must be >= 1, got {self.max_iterations}"),
            (self.tolerance >= 0, f"tolerance must be >= 0, got {self.tolerance}"),
            (self.depth_envelope is None or 0 <= self.depth_envelope < 1,
             f"depth_envelope must be None or a relative margin in [0, 1), got {self.depth_envelope}"),
            (int(self.joint_min_pixels) >= 0, f"joint_min_pixels must be >= 0, got {self.joint_min_pixels}"),
            (0 < self.cg_tolerance < 1 and 0 < self.joint_cg_tolerance < 1,
             f"cg_tolerance and joint_cg_tolerance must lie in (0, 1), got {self.cg_tolerance}, "
             f"{self.joint_cg_tolerance}"),
            (len(self.initial_light) == 4, "initial_light must hold 4 SH coefficients"),
            (self.difference_scheme in SCHEMES, f"difference_scheme must be one of {SCHEMES}"),
            (self.light_model in LIGHT_MODELS, f"light_model must be one of {LIGHT_MODELS}, got {self.light_model!r}"),
            (self.led_offset is None or np.shape(self.led_offset) == (3,),
             f"led_offset must be (x, y, z) in metres or None, got {self.led_offset!r}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(message)

    def frame_indices(self, n_available: int) -> list[int]:
        """The frame indices to use out of ``n_available``; frame 0 is always the reference."""
        if self.frames is None:
            return list(range(n_available))
        if np.isscalar(self.frames):
            n = int(self.frames)
            if not 1 <= n <= n_available:
                raise ValueError(f"frames={n} but the capture has {n_available} frames; use 1..{n_available}")
            return list(range(n))
        indices = [int(i) for i in self.frames]
        if not indices or min(indices) < 0 or max(indices) >= n_available or len(set(indices)) != len(indices):
            raise ValueError(f"frames={indices} must be distinct indices in 0..{n_available - 1}")
        return indices

    def to_dict(self) -> dict:
        return asdict(self)
