"""RefineOptions: everything a researcher varies in a refinement, in three groups.

Like the option structs of Open3D's pipelines, the options are grouped by meaning:
:class:`ModelOptions` (the energy: paper section 3), :class:`ConvergenceCriteria` (when the
iterations of paper section 4 stop) and :class:`StepOptions` (which updates a sweep runs; docs/method.md). ``RefineOptions(tau=100, refine_poses=False)``
still takes every field by its flat name and ``options.tau`` still reads it.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field, fields
from enum import Enum

import numpy as np

from ..model.normals import SCHEMES
from ..model.shading import INITIAL_LIGHT
from .lighting import LIGHT_MODELS


class _Choice(str, Enum):
    """A string option with fixed values; equal to its plain string (``LightModel.LED == "led"``)."""

    def __str__(self) -> str:
        return self.value

    __format__ = str.__format__

    @classmethod
    def parse(cls, name: str, value):
        """``value`` (a member or its string) as a member; ValueError naming ``name`` and the choices."""
        try:
            return cls(value)
        except ValueError:
            raise ValueError(f"{name} must be one of {[m.value for m in cls]}, got {value!r}") from None


class FramesDepth(_Choice):
    """Where a moving camera's other frames' depth enters the depth prior (``average_frames_depth``)."""

    FINEST = "finest"
    INITIAL = "initial"
    OFF = "off"


#: smoothness (mu~) per light model when none is given. With the LED, 0.3 keeps the pixels that
#: only the reference frame sees (they carry no data once the albedo is projected out) near the
#: smooth fit: an LED scene of the bunny on a table (640x480, SF 4, 360-degree ring) went from
#: 5.2 to 1.6 mm RMSE, and the accuracy rows' MAE moved by -0.11 to +0.06 deg. Per-frame SH
#: ("sh"): mu~ 0 / 30 / 100 gave a room-lit bunny's normals 44.6 / 19.4 / 16.2 deg MAE (bicubic
#: 42.7). Room light ("room"): the depth learns from parallax alone, which is noisy pixel to pixel,
#: and the sensor depth's noise needs smoothing: "auto" sets mu~ from the sensor depth's roughness
#: and the pixels' footprint (:func:`o3d_mvps.solver.smoothness.auto_smoothness`).
DEFAULT_SMOOTHNESS = {"led": 0.3, "sh": 30.0, "room": "auto", "point": 30.0}

#: Cauchy scale lambda per light model when none is given: a number (linear intensity), or
#: "auto", the residuals' robust standard deviation (1.4826 x their median absolute deviation) at
#: each pyramid level's start (:func:`o3d_mvps.model.robust.robust_scale`). Under room light the
#: noise floor differs between captures by 3x (noiseless renders 0.003, noisy 0.008) and 0.04
#: let the aliased albedo edges pull the depth.
DEFAULT_CAUCHY_LAMBDA = {"led": 0.04, "sh": 0.04, "room": "auto", "point": 0.04}

#: whether the smoothness rows are weighted down on steep slopes, per light model when not given
#: (:func:`o3d_mvps.solver.smoothness.slope_weights`; with the LED they freed the pixels only the
#: reference sees at the rims)
DEFAULT_SLOPE_WEIGHTS = {"led": False, "sh": False, "room": True, "point": False}
AUTO = "auto"

#: the sensor tie (:func:`o3d_mvps.solver.weighting.tie_low_frequencies`) per light model when
#: not given: on ("auto") with per-frame SH, the model of static-camera, hand-held-light captures,
#: whose shading bias bent a rendered quilt into a bowl (low-pass difference from the sensor
#: 12.1 -> 1.8 per mille of depth, RMSE 2.89 -> 1.09 mm). Off (0) with the LED, where the photometric
#: low frequencies are good and the tie passes on the sensor's own (a bunny, 640x480, SF 4, 20
#: frames: 2.33 deg / 0.895 mm without, 2.32 deg / 0.944 mm with), and under room light (not measured).
DEFAULT_SENSOR_LOWPASS = {"led": 0, "sh": AUTO, "room": 0, "point": AUTO}

#: the evidence weights per light model when not given: on with per-frame SH and point lights,
#: relative to the median pixel (:func:`o3d_mvps.solver.weighting.evidence_weights`; a plaid
#: quilt's dark patches: normals 2.02 -> 1.68 deg, the smoothed sensor 4.29); on with the LED
#: against an absolute normal precision (:func:`o3d_mvps.solver.weighting.absolute_evidence_weights`:
#: a dark-speckled bunny with the D415-like sensor, 320x240, 10 frames: darkest albedo quarter
#: 23.6 -> 13.1 deg; the accuracy benchmark's bunny, 640x480, SF 4, 20 frames: 2.32 deg / 0.895 mm
#: -> 2.30 / 0.897, where the median rule had cost depth accuracy, 0.985 mm); off under room
#: light, whose smoothness is already the sensor's (the absolute rule's ceiling).
DEFAULT_EVIDENCE_WEIGHTS = {"led": True, "sh": True, "room": False, "point": True}

LightModel = _Choice("LightModel", {v.upper(): v for v in LIGHT_MODELS})
LightModel.__doc__ = ('Light model: LED ("led", a point light moving with the camera, paper section 6\'s '
                      'future work), SH ("sh", first-order spherical harmonics per frame, paper section 3.2) or '
                      'ROOM ("room", one SH light fixed in the room, times a per-frame exposure gain) or POINT '
                      '("point", a free point light per frame: a lamp moved by hand around a static camera).')
DifferenceScheme = _Choice("DifferenceScheme", {v.upper(): v for v in SCHEMES})
DifferenceScheme.__doc__ = 'Depth derivatives of the normals: CENTRAL ("central") or the paper\'s FORWARD ("forward").'


def _number(name, value, low, high, *, integer=False, low_open=False, high_open=False, none_ok=False, auto_ok=False):
    """``value`` checked to lie in the range and converted to int/float; ValueError naming all three."""
    if value is None and none_ok:
        return None
    lo, hi = ("(" if low_open else "[") + f"{low:g}", f"{high:g}" + (")" if high_open else "]")
    kind = "an integer" if integer else "a number"
    allowed = f"{kind} in {lo}, {hi}" + (f", {AUTO!r} or None" if auto_ok else " or None" if none_ok else "")
    ok = isinstance(value, numbers.Integral if integer else numbers.Real) and not isinstance(value, (bool, np.bool_))
    if ok:
        v = float(value)
        ok = math.isfinite(v) and (v > low if low_open else v >= low) and (v < high if high_open else v <= high)
    if not ok:
        raise ValueError(f"{name} must be {allowed}, got {value!r}")
    return int(value) if integer else float(value)


def _flag(name, value):
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def _vector(name, value, size, what, *, none_ok=False):
    if value is None and none_ok:
        return None
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        v = None
    if v is None or v.shape != (size,) or not np.isfinite(v).all():
        raise ValueError(f"{name} must be {what}" + (" or None" if none_ok else "") + f", got {value!r}")
    return tuple(v.tolist())


def _set(obj, **values):
    for k, v in values.items():
        object.__setattr__(obj, k, v)


@dataclass(frozen=True)
class ModelOptions:
    """The energy being minimised (paper section 3.4) and its light model.

    tau: normalised depth-prior weight tau~ (paper default 10; the authors' code used ~100), > 0.
    smoothness: normalised weight mu~ >= 0 of the depth's squared second differences (not in the
        paper; see ``slope_weights``), or "auto" (from the sensor depth's roughness and the
        pixels' footprint: :func:`o3d_mvps.solver.smoothness.auto_smoothness`); None:
        :data:`DEFAULT_SMOOTHNESS` of the light model. Under
        room light every frame sees the same light, the albedo absorbs the shading and only the
        parallax informs the depth: without smoothness it keeps the sensor's 1 mm terraces and the
        parallax's pixel-to-pixel noise. The LED lights each frame differently and needs little
        (0.3: only the pixels no other frame sees lean on it; 30 raised a bunny's RMSE 1.11 ->
        1.25 mm).
    slope_weights: weight the smoothness rows down where the sensor's surface is steep
        (:func:`o3d_mvps.solver.smoothness.slope_weights`); None: :data:`DEFAULT_SLOPE_WEIGHTS` of
        the light model (room light only).
    cauchy_lambda: Cauchy scale lambda (intensity units, linear RGB in [0, 1]), > 0, or "auto"
        (the residuals' robust standard deviation at each level's start); None:
        :data:`DEFAULT_CAUCHY_LAMBDA` of the light model.
    light_model: :class:`LightModel` "led" (point light moving with the camera, 1/r^2 falloff,
        plus ambient; o3d_mvps.solver.lighting), "sh" (the paper's first-order SH per frame) or
        "room" (one SH light fixed in the room, a gain per frame) or "point" (a point light per
        frame at its own, estimated position: a lamp moved around a static camera; the poses are
        then not refined); None takes it from the capture
        (capture.json's "light": "led" -> "led", "room" -> "room"; "led", with a warning, when
        the capture does not say).
    led_offset: LED position (x, y, z) in metres in the colour camera's frame (x right, y down,
        z forward); None takes ``led_offset`` from the capture's metadata, else (0, 0, 0).
    initial_light: the 4 SH coefficients every frame starts from (light_model "sh"; section 4).
    difference_scheme: :class:`DifferenceScheme` of the normals' depth derivatives, "central" or
        the paper's "forward" (o3d_mvps.model.normals).
    depth_envelope: keep each pixel's depth between the least and greatest sensor depth around it,
        widened by this relative margin in [0, 1) (None: unbounded; docs/method.md).
    occlusion_test: drop reference pixels hidden or out of view in frame i from its data term.
    occlusion_tolerance: relative depth tolerance of that test, in [0, 1).
    sensor_lowpass: at each pyramid level's end, replace the depth's low frequencies by the sensor
        depth's (:func:`o3d_mvps.solver.weighting.tie_low_frequencies`): the Gaussian sigma in
        depth pixels (> 0), "auto" (from the sensor's noise, at least 4:
        :func:`o3d_mvps.solver.weighting.lowpass_sigma`) or 0 (off: the paper's model, where the
        photometric terms may bend the whole surface); None: :data:`DEFAULT_SENSOR_LOWPASS` of
        the light model.
    evidence_weights: weight each pixel's smoothness by how little the frames' shading says
        about its normal (:func:`o3d_mvps.solver.weighting.evidence_weights`: dark albedo, few
        frames, little light diversity lean on the smoothness); False: one weight everywhere;
        None: :data:`DEFAULT_EVIDENCE_WEIGHTS` of the light model.
    drop_depth_outliers: replace the reference depth pixels the other frames' depth contradicts
        (flying pixels; :func:`o3d_mvps.covisibility.reference_depth_outliers`, at 4 sigma of the
        capture's own noise) by what the frames agree on there, else by the harmonic fill of the
        kept neighbours, never behind the reference's own nearest kept neighbour
        (:func:`o3d_mvps.covisibility.reference_depth_fill`); moving camera, 4 frames or more (a
        static camera's are always left out). False keeps them (they are counted and reported
        either way). On the D415-like peers render 3.31 -> 1.56 mm, the clean D415 render
        unchanged (none flagged) (docs/fidelity.md, "Flying pixels of a moving camera").
    average_frames_depth: how a moving camera's other frames' depth enters the depth prior (4
        frames or more). "off" (the default): frame 0's depth alone, the paper's prior. "finest"
        (where the poses are refined): the finest level's prior is re-made after its first sweep
        from every frame's depth, each compared with the surface as that frame's own pixels see
        it, their residuals averaged (:func:`o3d_mvps.solver.frames_depth.frames_depth_target`; 20-frame
        renders: normals 2.16 -> 1.56 deg at 640x480, 1.07 -> 0.86 at D415 size; not the default:
        10 speckled frames at 320x240 lose a little). "initial": the reference depth is the frames'
        mean at the initial poses before any level (:func:`o3d_mvps.covisibility.reference_depth_mean`),
        for a noisy sensor with poses consistent with its depth (a room-lit D415 render 8.9 -> 5.0
        deg, but a frame whose pose is millimetres off moves the target; under the LED, where the
        images carry the detail, a 40x30 relief with kicked poses lost it), applied by the solver
        (:func:`o3d_mvps.solver.driver.frames_mean_depths`). docs/fidelity.md, "The frames' mean
        depth for a moving camera".
    """

    tau: float = 10.0
    smoothness: float | str | None = None
    slope_weights: bool | None = None
    cauchy_lambda: float | str | None = None
    light_model: LightModel | None = None
    led_offset: tuple | None = None
    initial_light: tuple = INITIAL_LIGHT
    difference_scheme: DifferenceScheme = DifferenceScheme.CENTRAL
    depth_envelope: float | None = 0.02
    occlusion_test: bool = True
    occlusion_tolerance: float = 0.02
    sensor_lowpass: float | str | None = None
    evidence_weights: bool | None = None
    drop_depth_outliers: bool = True
    average_frames_depth: FramesDepth = FramesDepth.OFF

    def smoothness_weight(self) -> float | str:
        """mu~, or :data:`AUTO`: ``smoothness``, else the light model's default (the light model
        must be known)."""
        return DEFAULT_SMOOTHNESS[str(self.light_model)] if self.smoothness is None else self.smoothness

    def lowpass_width(self) -> float | str | None:
        """The sensor tie's sigma (depth pixels), :data:`AUTO`, or None (off): ``sensor_lowpass``,
        else the light model's default (the light model must be known)."""
        width = DEFAULT_SENSOR_LOWPASS[str(self.light_model)] if self.sensor_lowpass is None else self.sensor_lowpass
        return None if width == 0 else width

    def evidence_weighted(self) -> bool:
        """``evidence_weights``, else the light model's default (the light model must be known)."""
        if self.evidence_weights is None:
            return DEFAULT_EVIDENCE_WEIGHTS[str(self.light_model)]
        return self.evidence_weights

    def slope_weighted(self) -> bool:
        """``slope_weights``, else the light model's default (the light model must be known)."""
        return DEFAULT_SLOPE_WEIGHTS[str(self.light_model)] if self.slope_weights is None else self.slope_weights

    def cauchy_scale(self) -> float | str:
        """lambda, or :data:`AUTO`: ``cauchy_lambda``, else the light model's default (the light
        model must be known)."""
        return DEFAULT_CAUCHY_LAMBDA[str(self.light_model)] if self.cauchy_lambda is None else self.cauchy_lambda

    def __post_init__(self):
        _set(self,
             tau=_number("tau", self.tau, 0, math.inf, low_open=True, high_open=True),
             smoothness=self.smoothness if self.smoothness in (None, AUTO) else _number(
                 "smoothness", self.smoothness, 0, math.inf, high_open=True, auto_ok=True),
             slope_weights=None if self.slope_weights is None else _flag("slope_weights", self.slope_weights),
             cauchy_lambda=self.cauchy_lambda if self.cauchy_lambda in (None, AUTO) else _number(
                 "cauchy_lambda", self.cauchy_lambda, 0, math.inf, low_open=True, high_open=True, auto_ok=True),
             light_model=None if self.light_model is None else LightModel.parse("light_model", self.light_model),
             led_offset=_vector("led_offset", self.led_offset, 3, "(x, y, z) in metres", none_ok=True),
             initial_light=_vector("initial_light", self.initial_light, 4, "4 SH coefficients"),
             difference_scheme=DifferenceScheme.parse("difference_scheme", self.difference_scheme),
             depth_envelope=_number("depth_envelope", self.depth_envelope, 0, 1, high_open=True, none_ok=True),
             occlusion_test=_flag("occlusion_test", self.occlusion_test),
             occlusion_tolerance=_number("occlusion_tolerance", self.occlusion_tolerance, 0, 1, high_open=True),
             sensor_lowpass=self.sensor_lowpass if self.sensor_lowpass in (None, AUTO) else _number(
                 "sensor_lowpass", self.sensor_lowpass, 0, math.inf, high_open=True, auto_ok=True),
             evidence_weights=None if self.evidence_weights is None else _flag("evidence_weights",
                                                                                self.evidence_weights),
             drop_depth_outliers=_flag("drop_depth_outliers", self.drop_depth_outliers),
             average_frames_depth=FramesDepth.parse("average_frames_depth", self.average_frames_depth))


@dataclass(frozen=True)
class ConvergenceCriteria:
    """When the iterations stop (paper section 4: coarse-to-fine sweeps until the relative energy
    change falls below 1e-5; the default here is 1e-3, which ends most levels after 6-8 sweeps
    instead of the 10-sweep cap, for at most 0.03 deg normal error on the accuracy benchmark's
    renders).

    levels: coarse-to-fine pyramid levels, >= 1 (coarsest is 1 / 2^(levels-1) of the colour size).
    max_iterations: sweep cap per level, >= 1 (one sweep = poses, depth, albedo, lighting); point
        lights: 3 times that on the levels that refit the lamps every sweep (``driver.POINT_SWEEP_FACTOR``).
    tolerance: stop a level when the relative energy change falls below it, in [0, 1) (the finest
        level: or, its smoothness weights held, the data term's, or the next sweep's, predicted
        from two fast-contracting drops; ``driver._stalled``).
    pose_iterations: Gauss-Newton iterations per frame and sweep, >= 1.
    pose_tolerance: stop a frame's Gauss-Newton iterations once one lowers its energy by less than
        this fraction, in [0, 1) (0: always run ``pose_iterations``).
    cg_tolerance, cg_max_iterations: preconditioned CG for the depth system (tolerance in (0, 1)).
    joint_cg_tolerance: relative CG tolerance of the joint pose-depth step (an inexact Newton
        step), in (0, 1).
    """

    levels: int = 5
    max_iterations: int = 10
    tolerance: float = 1e-3
    pose_iterations: int = 3
    pose_tolerance: float = 1e-3
    cg_tolerance: float = 1e-4
    cg_max_iterations: int = 300
    joint_cg_tolerance: float = 1e-2

    def __post_init__(self):
        _set(self,
             levels=_number("levels", self.levels, 1, math.inf, integer=True),
             max_iterations=_number("max_iterations", self.max_iterations, 1, math.inf, integer=True),
             tolerance=_number("tolerance", self.tolerance, 0, 1, high_open=True),
             pose_iterations=_number("pose_iterations", self.pose_iterations, 1, math.inf, integer=True),
             pose_tolerance=_number("pose_tolerance", self.pose_tolerance, 0, 1, high_open=True),
             cg_tolerance=_number("cg_tolerance", self.cg_tolerance, 0, 1, low_open=True, high_open=True),
             cg_max_iterations=_number("cg_max_iterations", self.cg_max_iterations, 1, math.inf, integer=True),
             joint_cg_tolerance=_number("joint_cg_tolerance", self.joint_cg_tolerance, 0, 1,
                                        low_open=True, high_open=True))


@dataclass(frozen=True)
class StepOptions:
    """Which updates a sweep runs (paper section 4's sweep and the departures docs/method.md
    describes).

    refine_poses: refine poses jointly (False gives the paper's two-stage baseline, section 5.1).
    pose_min_pixels: refine poses only on levels whose reference mask has this many pixels, >= 0
        (coarser levels see too little of the object to constrain six degrees of freedom).
    joint_pose_depth: on levels that refine poses, replace the paper's pose and depth updates by one
        Gauss-Newton step on both, with the warp's parallax in the depth (o3d_mvps.solver.joint).
    joint_min_pixels: take the joint step only on levels with this many object pixels, >= 0;
        coarser levels keep the paper's updates.
    project_albedo: eliminate the albedo from the depth and joint steps (variable projection,
        o3d_mvps.solver.joint); False gives the paper's depth step with the albedo held fixed.
    extrapolate: after each sweep, try continuing its move of every unknown and keep the best that
        lowers the energy.
    refine_led_offset: estimate the LED offset jointly, starting from ``led_offset``.
    strict_registration: without initial poses, raise when the registration cannot place a frame
        instead of dropping it with a warning (o3d_mvps.odometry.register_frames).
    """

    refine_poses: bool = True
    pose_min_pixels: int = 1000
    joint_pose_depth: bool = True
    joint_min_pixels: int = 10000
    project_albedo: bool = True
    extrapolate: bool = True
    refine_led_offset: bool = True
    strict_registration: bool = False

    def __post_init__(self):
        _set(self, **{f.name: (_number(f.name, getattr(self, f.name), 0, math.inf, integer=True)
                               if f.name.endswith("_pixels") else _flag(f.name, getattr(self, f.name)))
                      for f in fields(self)})


GROUPS = {"model": ModelOptions, "convergence": ConvergenceCriteria, "steps": StepOptions}
_GROUP_OF = {f.name: group for group, cls in GROUPS.items() for f in fields(cls)}


@dataclass(frozen=True)
class RefineOptions:
    """Options of :func:`o3d_mvps.refine`: three groups plus the frames to use and the progress bar.

    ``RefineOptions(model=ModelOptions(tau=100), convergence=ConvergenceCriteria(levels=3))`` or,
    equally, ``RefineOptions(tau=100, levels=3)``: every field of a group is also a keyword (it
    overrides that field of a group given alongside) and a read-only attribute (``options.tau``).
    ``dataclasses.replace(options, tau=20)`` works too.

    frames: number of frames to use (the first ``frames``), a list of indices, or None for all.
    progress: show a progress bar per level.
    """

    model: ModelOptions = field(default_factory=ModelOptions)
    convergence: ConvergenceCriteria = field(default_factory=ConvergenceCriteria)
    steps: StepOptions = field(default_factory=StepOptions)
    frames: int | list | None = None
    progress: bool = True

    def __init__(self, model: ModelOptions | None = None, convergence: ConvergenceCriteria | None = None,
                 steps: StepOptions | None = None, frames: int | list | None = None, progress: bool = True,
                 **flat):
        unknown = sorted(set(flat) - set(_GROUP_OF))
        if unknown:
            valid = ", ".join([*GROUPS, "frames", "progress", *_GROUP_OF])
            raise TypeError(f"RefineOptions got unknown keyword(s) {', '.join(unknown)}; valid keywords: {valid}")
        given = {"model": model, "convergence": convergence, "steps": steps}
        groups = {}
        for group, cls in GROUPS.items():
            base = given[group] if given[group] is not None else cls()
            if not isinstance(base, cls):
                raise TypeError(f"{group} must be a {cls.__name__}, got {type(base).__name__}")
            changes = {k: v for k, v in flat.items() if _GROUP_OF[k] == group}
            groups[group] = cls(**{**asdict(base), **changes}) if changes else base
        _set(self, **groups, frames=_frames(frames), progress=_flag("progress", progress))

    def frame_indices(self, n_available: int) -> list[int]:
        """The frame indices to use out of ``n_available``; frame 0 is always the reference."""
        if self.frames is None:
            return list(range(n_available))
        if isinstance(self.frames, int):
            if not self.frames <= n_available:
                raise ValueError(f"frames={self.frames} but the capture has {n_available} frames; "
                                 f"use 1..{n_available}")
            return list(range(self.frames))
        if max(self.frames) >= n_available:
            raise ValueError(f"frames={self.frames} must be distinct indices in 0..{n_available - 1}")
        return list(self.frames)

    def to_dict(self) -> dict:
        """JSON-ready nested dict: {"model": {...}, "convergence": {...}, "steps": {...}, "frames", "progress"}."""
        d = asdict(self)
        for group in GROUPS:
            d[group] = {k: (v.value if isinstance(v, Enum) else list(v) if isinstance(v, tuple) else v)
                        for k, v in d[group].items()}
        return d

    @classmethod
    def from_dict(cls, d: dict) -> RefineOptions:
        """The options ``to_dict`` gave (nested), or flat keywords as a dict."""
        return cls(**{k: (GROUPS[k](**v) if k in GROUPS else v) for k, v in d.items()})


def _frames(frames):
    """``frames`` checked: None, a count >= 1, or distinct indices >= 0 (a list of int)."""
    if frames is None:
        return None
    if isinstance(frames, numbers.Integral) and not isinstance(frames, (bool, np.bool_)):
        return _number("frames", frames, 1, math.inf, integer=True)
    try:
        indices = [int(i) for i in frames if isinstance(i, numbers.Integral) and not isinstance(i, bool)]
        ok = len(indices) == len(frames) and indices and min(indices) >= 0 and len(set(indices)) == len(indices)
    except TypeError:
        ok = False
    if not ok:
        raise ValueError(f"frames must be None, a count >= 1 or a list of distinct indices >= 0, got {frames!r}")
    return indices


def _group_property(group: str, name: str) -> property:
    return property(lambda self: getattr(getattr(self, group), name),
                    doc=f"``{group}.{name}`` (read-only; see {GROUPS[group].__name__}).")


for _name, _group in _GROUP_OF.items():
    setattr(RefineOptions, _name, _group_property(_group, _name))
del _name, _group
