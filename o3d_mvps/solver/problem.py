"""The energy of one pyramid level and the quantities every update step reads.

E = sum_i sum_{p visible in i} sum_c phi(I~_ic(p) - rho_c(p) s_i(p)) + tau ||D z - z0||^2 + mu ||S z||^2,
with the shading ``s_i(p) = <B_i(p), l_i>`` of the level's light model (see :mod:`.lighting`) and
S the depth's second differences (:func:`.pyramid.second_differences`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.arrays import array_module, contiguous, like
from ..model.camera import backproject
from ..model.normals import unit_normals
from ..model.robust import cauchy_energy
from ..model.shading import FRAME_CHUNK, frame_chunk
from ..model.warping import in_view, visible, warp
from .device import kernels_for, to_host
from .kernels import albedo_refit_residuals, energy_blocks, led_energy_frame, log_products_sum
from .krylov import pixel_prolongations
from .lighting import LEDLight, RoomLight, SHLight, device_light_state, preload_light_states
from .pyramid import Level


#: Frames x pixels per batch of :meth:`LevelProblem.energy`: all frames at once up to this size (as
#: many compiled-loop launches as an evaluation), 5 frames a batch at D415 size (90 000 object
#: pixels: some 30 MB of temporaries instead of 110 MB for all 20), one at 2 MP (the host warps
#: frame by frame anyway; a batch adds three launches).
ENERGY_BATCH_PIXELS = 2**19


@dataclass
class Estimate:
    """Unknowns on one level: z (N,) metres, albedo (N, 3), lights (n, k), poses (n, 4, 4) and
    the LED offset (3,) metres in the camera frame (None: the light model's own, or a model
    without one)."""

    z: np.ndarray
    albedo: np.ndarray
    lights: np.ndarray
    poses: np.ndarray
    led_offset: np.ndarray | None = None


@dataclass
class FrameSample:
    """Frame i seen from the reference pixels: colour (N, 3) float32 and the usable mask (N,)."""

    color: np.ndarray
    usable: np.ndarray


@dataclass
class FrameGradients:
    """What a pose Jacobian reads of frame i at the reference pixels: the frame-i points (N, 3)
    metres and the frame's colour gradients grad_u, grad_v (N, 3) per pixel at their projections."""

    points: np.ndarray
    grad_u: np.ndarray
    grad_v: np.ndarray


class PendingSums:
    """The (data, prior) energies of a one-pass kernel's partial sums (B, 2) on the GPU, read to
    the host at the first use (one copy, a synchronisation), not at the launch: an evaluation
    whose energy no step reads (the albedo's, the smoothness weighing's prior) costs no copy.
    scale: the data sum's factor (lambda^2 / 2); prior: the prior energy where the caller had it
    (then the kernel's prior sum is not read)."""

    def __init__(self, partial, scale: float, prior: float | None = None):
        self._partial, self._scale, self._prior, self._values = partial, scale, prior, None

    @staticmethod
    def known_prior(prior) -> float | None:
        """The prior energy ``prior`` (a float, a :class:`PendingSums` or None) where it is known
        without a read, else None."""
        if isinstance(prior, PendingSums):
            return prior._prior if prior._values is None else prior._values[1]
        return None if prior is None else float(prior)

    def value(self, index: int) -> float:
        """The data (index 0) or prior (1) energy (a given prior without a read)."""
        if index == 1 and self._prior is not None:
            return self._prior
        if self._values is None:
            data, prior = to_host(self._partial).sum(axis=0)
            self._values = (self._scale * float(data), float(prior) if self._prior is None else self._prior)
            self._partial = None
        return self._values[index]


class Unscored(PendingSums):
    """The data energy of an evaluation made without it (:meth:`LevelProblem.evaluate` with
    ``scored=False``): reading it is an error. For a line search's trial whose albedo is refitted
    at once: only the refitted evaluation's energy is compared, and the trial's own (a pass of
    logarithms over every residual, 0.15 of a 2 MP trial's 2.1 CPU s) went unread."""

    def __init__(self):
        super().__init__(None, 0.0)

    def value(self, index: int) -> float:
        raise RuntimeError("the evaluation was made without its data energy (LevelProblem.evaluate(scored=False)); "
                           "reevaluate it (LevelProblem.reevaluate) before reading its energy")


class _Energy:
    """A data descriptor of :class:`Evaluation`'s ``data`` and ``prior``: a float, or a
    :class:`PendingSums` read at the first get (and then kept as the float)."""

    def __init__(self, index: int):
        self.index = index

    def __set_name__(self, owner, name):
        self.key = "_" + name

    def __get__(self, obj, owner=None):
        if obj is None:
            return self
        value = obj.__dict__[self.key]
        if isinstance(value, PendingSums):
            value = obj.__dict__[self.key] = value.value(self.index)
        return value

    def __set__(self, obj, value):
        obj.__dict__[self.key] = value


@dataclass
class Evaluation:
    """Residuals r (n, N, 3), usable (n, N), warped colours (n, N, 3) float32, shading (n, N)
    and light bases (m, N, k) (m = 1 when all frames share one) (r, shading and bases in the
    problem's residual_dtype), unit normals (N, 3), dA (N,), and the energy split into data and
    prior terms."""

    residual: np.ndarray
    usable: np.ndarray
    color: np.ndarray
    shading: np.ndarray
    normals: np.ndarray
    dA: np.ndarray
    basis: np.ndarray
    data: float
    prior: float

    #: The per-pixel arrays of an evaluation (what :meth:`release` drops).
    ARRAYS = ("residual", "usable", "color", "shading", "normals", "dA", "basis")

    def release(self, keep: tuple[str, ...] = ()) -> None:
        """Drop the per-pixel arrays, keeping the energy: for a step that has read them and
        evaluates its result anew, so that they are not held through its solve and line search
        (1.2 GB at 1M object pixels and 20 frames). A released evaluation is not read again.
        keep: names of :data:`ARRAYS` kept for now (a step that reads only those drops the others
        before it allocates its own arrays, and the rest once read)."""
        for name in self.ARRAYS:
            if name not in keep:
                setattr(self, name, None)

    def frame_rms(self) -> list[float]:
        """Per frame, the RMS of the data term's residuals (linear intensity) over its usable
        pixels and the three channels: (n,) floats, NaN for a frame with no usable pixel. One pass
        over the residuals, a frame at a time (no frames x pixels temporary)."""
        xp = array_module(self.residual)
        if xp is not np:  # two reductions over all frames and one copy, not a launch and a read per frame
            squares = xp.einsum("inc,inc->i", self.residual, self.residual, dtype=np.float64)
            sums = to_host(xp.stack([squares, 3.0 * self.usable.sum(axis=1)]))
            return [float(np.sqrt(total / count)) if count else float("nan") for total, count in sums.T]
        rms = []
        for i in range(len(self.usable)):
            r = self.residual[i].ravel()
            count = 3 * int(self.usable[i].sum())
            rms.append(float(xp.sqrt(xp.vdot(r, r).astype(np.float64) / count)) if count else float("nan"))
        return rms

    def pending(self, name: str):
        """The ``data`` or ``prior`` energy as held: a float, or the :class:`PendingSums` not yet
        read (passed on without a copy)."""
        return self.__dict__["_" + name]

    def frame_basis(self, i: int) -> np.ndarray:
        """Frame i's light basis (N, k)."""
        return self.basis[min(i, len(self.basis) - 1)]

    @property
    def energy(self) -> float:
        return self.data + self.prior


# data and prior: floats, or device sums read at the first use (the GPU's evaluations)
Evaluation.data, Evaluation.prior = _Energy(0), _Energy(1)
Evaluation.data.__set_name__(Evaluation, "data")
Evaluation.prior.__set_name__(Evaluation, "prior")


class LevelProblem:
    """Evaluates the level energy; holds the per-level visibility, tau and mu (the smoothness weight).

    The level's arrays may live on a GPU (:meth:`.pyramid.Level.on_device`): the per-pixel
    arrays of the estimates and evaluations then live there too. residual_dtype: the
    evaluations' residuals and shading (:attr:`.device.ArrayDevice.residual_dtype`).
    """

    def __init__(self, level: Level, tau: float, cauchy_lambda: float, light=None, smoothness: float = 0.0, *,
                 residual_dtype=np.float64):
        self.level = level
        self.residual_dtype = residual_dtype
        self.light = SHLight() if light is None else light
        self.tau = float(tau)
        self.mu = float(smoothness)
        self.lam = float(cauchy_lambda)
        self.n_frames = len(level.images)
        self._prolongations = None
        #: (indptr, indices) of the depth block's sparse pattern on the host, built at the first
        #: joint or depth step (:func:`.normal_equations.depth_block`)
        self.depth_pattern = None
        self._pixels = None
        self._last_points = None  # (z, its points) on a GPU: see points
        self.visibility = like(np.ones((self.n_frames, level.grid.size), dtype=bool), level.grid.u)
        #: the frames' samples (colours, usable) at identity poses, which do not depend on z
        self._static_samples = None
        #: the level's intrinsics (3, 3) where its arrays live, for the kernels
        self.device_K = like(level.K, level.grid.u)
        self._no_frames = None  # on a GPU: empty frames x pixels arrays, for the prior's energy alone
        self._grid_arrays = None  # on a GPU: the grid's per-pixel arrays, C-contiguous, for the kernels

    def pixel_prolongations(self) -> list:
        """The level's pixel aggregation for the GPU path's multigrid (:func:`.krylov.pixel_prolongations`),
        built at the first call: aggregates of pixels 2 apart, or neighbours under a light fixed
        in the world (whose large smoothness weight suits them: the measured best of each)."""
        if self._prolongations is None:  # from the host's pixels (the grid's mask stays there): no launch
            g = self.level.grid
            v, u = np.nonzero(g.mask)
            self._prolongations = pixel_prolongations(u, v, stride=1 if self.light.fixed_in_world else 2, like=g.u)
        return self._prolongations

    # geometry ----------------------------------------------------------------------------
    def points(self, z: np.ndarray) -> np.ndarray:
        """Reference-camera points (N, 3) of the masked depth z (N,). On a GPU those of the last
        z asked for are kept and given again for that same array (a step asks for the points of
        one z several times: two launches each); depth arrays are never written in place."""
        if self._pixels is None:  # float64 pixel coordinates, once per level
            self._pixels = (self.level.grid.u.astype(np.float64), self.level.grid.v.astype(np.float64))
        if self._last_points is not None and self._last_points[0] is z:
            return self._last_points[1]
        points = backproject(z, self.level.K, *self._pixels)
        if array_module(z) is not np:
            self._last_points = (z, points)
        return points

    def normals(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit normals (N, 3) and dA (N,) of z."""
        return unit_normals(self.level.grid, z, self.level.K)

    def sample(self, i: int, pose: np.ndarray, points_ref: np.ndarray) -> FrameSample:
        """Frame i under ``pose`` seen from the reference points (N, 3): its colour and usable mask."""
        xp = array_module(points_ref)
        sample = FrameSample(xp.empty(points_ref.shape, dtype=np.float32), xp.empty(len(points_ref), dtype=bool))
        self._warp_sample(i, pose, points_ref, sample.color, sample.usable)
        return sample

    def _warp_sample(self, i: int, pose: np.ndarray, points_ref: np.ndarray, color: np.ndarray,
                     usable: np.ndarray) -> None:
        """:meth:`sample` written into color (N, 3) float32 and usable (N,) bool
        (:func:`.kernels.warp_sample`: warp, in-view test and bilinear samples in one pass);
        pose (4, 4) on the host or already where the points are."""
        kernels_for(points_ref).warp_sample(points_ref, like(pose, points_ref), self.device_K, self.level.images[i],
                                            self.visibility[i], color, usable)

    def _sample_frames(self, points_ref: np.ndarray, poses: np.ndarray, frames: slice, color: np.ndarray,
                       usable: np.ndarray) -> None:
        """:meth:`_warp_sample` of the frames ``frames`` (a slice with step 1) written into color
        (m, N, 3) and usable (m, N); poses (n, 4, 4) where the points are. On the GPU one launch
        for them all (:func:`.kernels.warp_sample_frames`)."""
        if self.level.image_stack is not None:
            kernels_for(points_ref).warp_sample_frames(points_ref, poses[frames], self.device_K,
                                                       self.level.image_stack[frames], self.visibility[frames],
                                                       color, usable)
        else:
            for k, i in enumerate(range(*frames.indices(self.n_frames))):
                self._warp_sample(i, poses[i], points_ref, color[k], usable[k])

    def identity_poses(self, est: Estimate) -> bool:
        """Whether every pose of ``est`` is the identity (a static camera: the frames' samples
        do not depend on z, :attr:`_static_samples`)."""
        return bool(np.array_equal(to_host(est.poses), np.broadcast_to(np.eye(4), (self.n_frames, 4, 4))))

    def warped_gradients(self, i: int, pose: np.ndarray, points_ref: np.ndarray) -> FrameGradients:
        """Frame i's colour gradients at the reference points (N, 3) warped by ``pose``, by the
        per-pixel function of the assembly's kernel (:func:`.kernels.warp_gradients`)."""
        xp = array_module(points_ref)
        gradients = FrameGradients(*(xp.empty(points_ref.shape) for _ in range(3)))
        kernels_for(points_ref).warp_gradients(points_ref, like(pose, points_ref), self.device_K,
                                               self.level.images[i], gradients.points, gradients.grad_u,
                                               gradients.grad_v)
        return gradients

    def update_visibility(self, est: Estimate, *, occlusion_test: bool, rel_tol: float, sensor_depths=None,
                          depth_K=None) -> None:
        """Recompute which reference pixels each frame sees (held fixed while a level runs). Where
        every pose is the identity (a static camera) each pixel lands on itself in every frame:
        the warp is made once and no z-buffer is needed (the same visibility)."""
        self._static_samples = None
        P = to_host(self.points(est.z))  # the z-buffer's scatter-min runs on the host
        identity = self.identity_poses(est)
        sensor_uv = None  # the sensor's pixel of each point: one for all frames where the poses are the identity
        for i in range(self.n_frames):
            if not identity or i == 0:
                points, u, v, Z = warp(P, est.poses[i], self.level.K)
            if i == 0 or not occlusion_test:
                self.visibility[i] = like(in_view(u, v, Z, self.level.size), self.visibility) if i else True
                continue
            sensor = None if sensor_depths is None else sensor_depths[i]
            if not identity:
                sensor_uv = None
            if sensor is not None and sensor_uv is None:
                su = depth_K[0, 0] * points[:, 0] / Z + depth_K[0, 2]
                sv = depth_K[1, 1] * points[:, 1] / Z + depth_K[1, 2]
                sensor_uv = (su, sv)
            self.visibility[i] = like(visible(u, v, Z, self.level.size, rel_tol=rel_tol, sensor_depth=sensor,
                                              sensor_uv=sensor_uv, frame_mask=self.level.frame_masks[i],
                                              zbuffer=not identity), self.visibility)

    # energy ------------------------------------------------------------------------------
    def prior_energy(self, z: np.ndarray, pending: bool = False) -> float:
        """The prior's energy at depth z (N,) metres (:meth:`.pyramid.DepthPrior.energy`; on a GPU
        one launch of :func:`.kernels.evaluation_partials` on no frames and one copy, or with
        ``pending`` a :class:`PendingSums` for an :class:`Evaluation`'s prior, read when used)."""
        if array_module(z) is np:
            return self.level.prior.energy(z, self.tau, self.mu)
        if self._no_frames is None:
            xp, N = array_module(z), self.level.grid.size
            k, dtype = self.light.size, self.residual_dtype
            self._no_frames = (xp.empty((0, N, 3), np.float32), xp.empty((0, 3)), xp.empty((0, N, k), dtype),
                               xp.empty((0, k)), xp.empty((0, N), bool), xp.empty((0, N), dtype),
                               xp.empty((0, N, 3), dtype))
        sums = self._device_sums(z, self._no_frames, None)
        return sums if pending else sums.value(1)

    def _prior_arrays(self, with_prior: bool) -> tuple:
        """The prior's terms for the one-pass kernels (:func:`.kernels.prior_term`): D's CSR
        arrays, z0, S's CSR arrays (D's where there is no smoothness term), tau and mu (both 0
        without the prior: ``with_prior`` False)."""
        prior = self.level.prior
        D = prior.D
        smooth = self.mu > 0 and prior.S is not None
        S = prior.S if smooth else D
        tau, mu = (self.tau, self.mu if smooth else 0.0) if with_prior else (0.0, 0.0)
        return D.indptr, D.indices, D.data, prior.z0, S.indptr, S.indices, S.data, tau, mu

    def _device_sums(self, z: np.ndarray, frames: tuple, prior) -> PendingSums:
        """The (data, prior) energies of :func:`.kernels.evaluation_partials` on the GPU, read when
        first used: frames = (color, albedo, basis, lights, usable, shading, residual) (shading and
        residual written), the prior's at z unless ``prior`` is known (a float, or a
        :class:`PendingSums` holding one: :meth:`PendingSums.known_prior`; one not yet read is
        computed again, so that one copy reads both). One launch, and one copy where the energy
        is read."""
        usable = frames[4]
        xp = array_module(z)
        given = PendingSums.known_prior(prior)
        partial = xp.empty((energy_blocks(usable.size + self.level.prior.rows), 2))
        kernels_for(z).evaluation_partials(*frames, 1.0 / self.lam, *self._prior_arrays(given is None), z, partial)
        return PendingSums(partial, 0.5 * self.lam * self.lam, given)

    def _one_pass_light(self, est: Estimate):
        """(led, offset) for the one-pass kernels (:func:`.kernels.energy_partials`,
        :func:`.kernels.evaluate_partials`): whether ``est``'s light model is the LED (else SH or
        room light) and the LED's offset (3,) metres; None where they do not apply (another light
        model, a static camera's shared samples, frames not in one stack)."""
        light = self.light_model(est)
        led = type(light) is LEDLight
        if not (led or type(light) in (SHLight, RoomLight)) or self.level.image_stack is None or (
                self._static_samples is not None and self.identity_poses(est)):
            return None
        return led, (tuple(float(o) for o in light.offset) if led else (0.0, 0.0, 0.0))

    def _grid_and_views(self, est: Estimate) -> tuple:
        """The one-pass kernels' arguments from z to the lights: z, the grid's arrays (made
        C-contiguous once per level), K, the poses (n, 4, 4), images, visibility, albedo and
        lights (n, k) float64 (the poses and lights copied over together, and only where they
        differ from the last ones copied: :meth:`_device_poses_lights`)."""
        g = self.level.grid
        if self._grid_arrays is None:  # once per level (no launch: the device's grid is contiguous)
            self._grid_arrays = tuple(contiguous(a) for a in (g.u, g.v, g.fwd_u, g.bwd_u, g.wf_u, g.wb_u, g.fwd_v,
                                                              g.bwd_v, g.wf_v, g.wb_v))
        poses, lights = self._device_poses_lights(est)
        return (est.z, *self._grid_arrays, self.device_K, poses, self.level.image_stack, self.visibility, est.albedo,
                lights)

    def _device_poses_lights(self, est: Estimate) -> tuple:
        """``est``'s poses (n, 4, 4) and lights (n, k), float64, on the GPU: one copy of them and
        the light model's LED arrays, none where they equal a state copied lately (views of one
        device array, never written: :func:`.lighting.device_light_state`, which the LED's
        Jacobians, fields and offset step of this state then read without a copy)."""
        state = device_light_state(self.light_model(est), est.lights, est.poses, est.z)
        return state.poses, state.lights

    def trial_energies(self, z: np.ndarray, albedo: np.ndarray, trials: list) -> tuple | None:
        """On a GPU: the energies (F,) (a host array) and usable masks (F, n, N) of F trial
        estimates whose depths z (F, N) and albedos (F, N, 3) lie in one device array each
        (:func:`.kernels.extrapolation_trials`'), ``trials`` their :class:`Estimate` (of one light
        model), in one launch and one read (:func:`.kernels.trial_energy_partials`), their poses,
        lights and LED offsets copied over in one copy with their light states (the kept one's
        evaluation then copies nothing); None where :meth:`_one_pass_energy` would not apply.
        Each trial's energy is :meth:`energy`'s (the same sums in another order)."""
        if array_module(z) is np:
            return None
        chosen = [self._one_pass_light(trial) for trial in trials]
        if None in chosen or len({led for led, _ in chosen}) != 1:
            return None
        led = chosen[0][0]
        F, n, N = len(trials), self.n_frames, self.level.grid.size
        xp = array_module(z)
        host = [np.stack([np.asarray(to_host(getattr(t, name)), np.float64) for t in trials]).ravel()
                for name in ("poses", "lights")] + [np.asarray([offset for _, offset in chosen], np.float64).ravel()]
        poses, lights, offsets = preload_light_states(
            [(self.light_model(t), t.lights, t.poses) for t in trials], z, host)
        k = len(host[1]) // (F * n)
        usable = xp.empty((F, n, N), dtype=bool)
        partial = xp.empty((F, energy_blocks(n * N + self.level.prior.rows), 2))
        grid = self._grid_and_views(trials[0])
        kernels_for(z).trial_energy_partials(z, *grid[1:12], poses.reshape(F, n, 4, 4), self.level.image_stack,
                                             self.visibility, albedo, lights.reshape(F, n, k), led,
                                             offsets.reshape(F, 3), 1.0 / self.lam,
                                             self.residual_dtype == np.float32, *self._prior_arrays(True), usable,
                                             partial)
        sums = to_host(partial).sum(axis=1)
        return 0.5 * self.lam * self.lam * sums[:, 0] + sums[:, 1], usable

    def _one_pass_energy(self, est: Estimate, prior: float | None):
        """:meth:`energy` on a GPU in one launch (:func:`.kernels.energy_partials`: every frame's
        warp, normals, shading and robust terms, and the prior) and one or two copies (the poses
        and lights over where they changed, the partial sums back), or None where that kernel
        does not apply (:meth:`_one_pass_light`)."""
        chosen = self._one_pass_light(est)
        if chosen is None:
            return None
        led, offset = chosen
        n, N = self.n_frames, self.level.grid.size
        xp = array_module(est.z)
        usable = xp.empty((n, N), dtype=bool)
        partial = xp.empty((energy_blocks(n * N + self.level.prior.rows), 2))
        kernels_for(est.z).energy_partials(*self._grid_and_views(est), led, *offset, 1.0 / self.lam,
                                           self.residual_dtype == np.float32, *self._prior_arrays(prior is None),
                                           usable, partial)
        data, prior_sum = to_host(partial).sum(axis=0)
        return 0.5 * self.lam * self.lam * float(data) + (float(prior_sum) if prior is None else prior), usable

    def evaluate_refit(self, est: Estimate) -> Evaluation | None:
        """On a GPU: ``est``'s evaluation with its albedo refitted (``est.albedo`` set to
        :func:`.reflectance.update_albedo`'s from the evaluation's IRLS weights, the evaluation
        the one at it) in one launch (:func:`.kernels.evaluate_albedo_partials`); None on the
        host, or where the one-pass kernels do not apply (:meth:`_one_pass_light`)."""
        if array_module(est.z) is np or self.identity_poses(est):
            return None
        return self._one_pass_evaluation(est, refit_albedo=True)

    def _one_pass_evaluation(self, est: Estimate, refit_albedo: bool = False):
        """:meth:`evaluate` on a GPU in one launch (:func:`.kernels.evaluate_partials`: the points,
        normals, warped samples, bases, shading, residuals, data and prior energy), the light
        state's copy where it changed and the energy's where it is read, or None where that
        kernel does not apply (:meth:`_one_pass_light`). The points are kept for :meth:`points`
        of this z. refit_albedo: ``est.albedo`` refitted in the same launch
        (:func:`.kernels.evaluate_albedo_partials`, :meth:`evaluate_refit`)."""
        chosen = self._one_pass_light(est)
        if chosen is None:
            return None
        led, offset = chosen
        n, N, dtype = self.n_frames, self.level.grid.size, self.residual_dtype
        xp = array_module(est.z)
        points, normals, dA = xp.empty((N, 3)), xp.empty((N, 3)), xp.empty(N)
        color, usable = xp.empty((n, N, 3), dtype=np.float32), xp.empty((n, N), dtype=bool)
        basis = xp.empty((n, N, 2) if led else (1, N, 4), dtype=dtype)
        shading, residual = xp.empty((n, N), dtype=dtype), xp.empty((n, N, 3), dtype=dtype)
        partial = xp.empty((energy_blocks(n * N + self.level.prior.rows), 2))
        args = (*self._grid_and_views(est), led, *offset, 1.0 / self.lam, dtype == np.float32,
                *self._prior_arrays(True), points, normals, dA, color, usable, basis, shading, residual, partial)
        if refit_albedo:  # and the albedo refitted at those residuals, in the same launch
            refit = xp.empty_like(est.albedo)
            kernels_for(est.z).evaluate_albedo_partials(*args, xp.empty_like(est.albedo), xp.empty_like(est.albedo),
                                                        refit)
            est.albedo = refit
        else:
            kernels_for(est.z).evaluate_partials(*args)
        self._last_points = (est.z, points)
        sums = PendingSums(partial, 0.5 * self.lam * self.lam)  # read where the energy is used
        return Evaluation(residual, usable, color, shading, normals, dA, basis, sums, sums)

    def light_model(self, est: Estimate):
        """The level's light model at the estimate's LED offset (its own where the estimate has none)."""
        return self.light if est.led_offset is None else self.light.at(est.led_offset)

    def bases(self, est: Estimate, normals: np.ndarray) -> np.ndarray:
        """Light bases (m, N, k) of every frame, or (1, N, k) when the model shares one."""
        return self.light_model(est).bases(normals, self.points(est.z), est.poses, dtype=self.residual_dtype)

    def frame_data_energy(self, sample: FrameSample, albedo: np.ndarray, shading: np.ndarray) -> float:
        """Robust data energy of one frame for given shading (N,)."""
        r = sample.color - albedo * shading[:, None]
        return cauchy_energy(r[sample.usable], self.lam, kernels_for(r).log1p_square_sum)

    def evaluate(self, est: Estimate, *, scored: bool = True) -> Evaluation:
        """Residuals and energy of the estimate over all frames (each frame warped and sampled in
        one pass: :func:`.kernels.warp_sample`). Where every pose is the identity (a static
        camera) each reference pixel sees its own pixel in every frame, whatever z: the frames
        are sampled once per visibility and the samples shared (read-only) by the evaluations.
        scored: False leaves the host's data energy uncomputed (:class:`Unscored`; its prior
        energy is computed), for a caller that reevaluates before it reads the energy."""
        n, N = self.n_frames, self.level.grid.size
        identity = self.identity_poses(est)
        if array_module(est.z) is not np and not identity:  # one launch on a GPU
            found = self._one_pass_evaluation(est)
            if found is not None:
                return found
        P = self.points(est.z)
        xp = array_module(P)
        if identity and self._static_samples is not None:
            return self.evaluate_samples(est, *self._static_samples, *self.normals(est.z), scored=scored)
        color = xp.empty((n, N, 3), dtype=np.float32)  # sampled from float32 images
        usable = xp.empty((n, N), dtype=bool)
        self._sample_frames(P, like(est.poses, P), slice(0, n), color, usable)
        if identity:
            self._static_samples = (color, usable)
        return self.evaluate_samples(est, color, usable, *self.normals(est.z), scored=scored)

    def energy(self, est: Estimate, samples: tuple | None = None, normals: np.ndarray | None = None,
               prior: float | None = None) -> tuple[float, np.ndarray]:
        """The energy of :meth:`evaluate` (equal up to the order of the float64 sum) and the usable
        mask (n, N), computed a batch of frames at a time (:data:`ENERGY_BATCH_PIXELS`): no
        frames x pixels arrays but the mask (at 2 MP and 20 frames some 140 MB of temporaries
        instead of the evaluation's 1.2 GB), for a trial that is kept only if it lowers the energy.

        samples: the warped colours (n, N, 3) and usable (n, N) of ``est``'s z and poses where the
        caller has them (an evaluation's, for a trial that moves neither, e.g. the LED offset):
        read instead of warping the frames again; normals (N, 3): ``est``'s unit normals, likewise;
        prior: the prior energy of ``est.z`` where the caller has it (None: computed).

        On a GPU without ``samples``: :meth:`_one_pass_energy` (one launch; ``normals`` unread,
        the kernel forms each pixel's from z)."""
        if samples is None and array_module(est.z) is not np:
            found = self._one_pass_energy(est, prior)
            if found is not None:
                return found
        n, N = self.n_frames, self.level.grid.size
        P = self.points(est.z)
        xp, kernels = array_module(P), kernels_for(P)
        if normals is None:
            normals, _ = self.normals(est.z)
        poses, lights = like(est.poses, P), like(est.lights, P, dtype=np.float64)
        light = self.light_model(est)
        if xp is np and samples is None and type(light) is LEDLight and not self.identity_poses(est):
            return self._led_energy(est, P, normals, poses, lights, light, prior)
        batch = min(n, max(1, ENERGY_BATCH_PIXELS // max(N, 1)))
        usable = xp.empty((n, N), dtype=bool) if samples is None else samples[1]
        color = xp.empty((batch, N, 3), dtype=np.float32) if samples is None else None
        shading, residual = xp.empty((batch, N), self.residual_dtype), xp.empty((batch, N, 3), self.residual_dtype)
        per_frame = isinstance(light, LEDLight)  # a basis per frame (else one for all frames, SH)
        basis = None if per_frame else light.bases(normals, P, est.poses[:1], dtype=self.residual_dtype)  # (1, N, k)
        static = samples if samples is not None else self._static_samples if self.identity_poses(est) else None
        data = 0.0
        for start in range(0, n, batch):
            stop = min(n, start + batch)
            m, frames = stop - start, slice(start, stop)
            if static is None:
                self._sample_frames(P, poses, frames, color[:m], usable[frames])
                sampled = color[:m]
            elif samples is not None:
                sampled = static[0][frames]
            else:  # the static samples of every z
                sampled, usable[frames] = static[0][frames], static[1][frames]
            kernels.shading_residuals(sampled, est.albedo, light.frames(frames).bases(normals, P, est.poses[frames],
                                                                                      dtype=self.residual_dtype)
                                      if per_frame else basis, lights[start:stop], usable[start:stop], shading[:m],
                                      residual[:m])
            data += cauchy_energy(residual[:m], self.lam, kernels.log1p_square_sum)
        return data + (self.prior_energy(est.z) if prior is None else prior), usable

    def _led_energy(self, est: Estimate, points: np.ndarray, normals: np.ndarray, poses: np.ndarray,
                    lights: np.ndarray, light, prior: float | None) -> tuple[float, np.ndarray]:
        """:meth:`energy` on the host under the LED, a compiled pass over the pixels a frame
        (:func:`.kernels.led_energy_frame`: no frames x pixels arrays but the usable mask, a
        running product per pixel; 2 MP, 20 frames, one thread: 0.90 -> 0.73 CPU s); equal to the
        batched sums to ~1e-14 of them. The chunk count comes from ``frame_chunk``'s Python
        function: called through its dispatcher, that inline-only (uncached) function was compiled
        in every process (0.14 CPU s, on the critical path)."""
        n, N = self.n_frames, self.level.grid.size
        usable = np.empty((n, N), dtype=bool)
        products, parts = np.ones(N), np.zeros(-(-N // frame_chunk.py_func(N)))
        args = (contiguous(points, np.float64), contiguous(normals, np.float64),
                np.ascontiguousarray(poses, dtype=np.float64), self.device_K)
        rest = (self.visibility, contiguous(est.albedo, np.float64), contiguous(lights, np.float64),
                np.ascontiguousarray(light.positions(poses), dtype=np.float64), 1.0 / self.lam,
                self.residual_dtype == np.float32)
        for i in range(n):
            led_energy_frame(*args, self.level.images[i], *rest, i, usable, products, parts)
        data = log_products_sum(products, parts)
        return 0.5 * self.lam * self.lam * data + (self.prior_energy(est.z) if prior is None else prior), usable

    def evaluate_samples(self, est: Estimate, color: np.ndarray, usable: np.ndarray, normals: np.ndarray,
                         dA: np.ndarray, *, scored: bool = True) -> Evaluation:
        """The evaluation of ``est`` from its warped colours (n, N, 3), usable (n, N) and normals
        (scored: as :meth:`evaluate`'s).

        Steps that leave z and the poses alone (albedo, lighting) or that sampled the frames
        already (poses) reuse the samples instead of warping every frame again.
        """
        return self._evaluation(est, color, usable, normals, dA, self.bases(est, normals), scored=scored)

    def _evaluation(self, est, color, usable, normals, dA, basis, reuse: Evaluation | None = None,
                    prior: float | None = None, scored: bool = True) -> Evaluation:
        """The evaluation from the samples; ``prior``: the prior energy of ``est.z`` where the caller
        has it (None: computed); scored: as :meth:`evaluate`'s."""
        n, N = usable.shape
        xp, kernels = array_module(color), kernels_for(color)
        if reuse is None:
            shading, residual = xp.empty((n, N), self.residual_dtype), xp.empty((n, N, 3), self.residual_dtype)
        else:
            shading, residual = reuse.shading, reuse.residual
        if xp is not np:  # residuals, data and prior energy in one launch (and one copy)
            lights = self._device_poses_lights(est)[1]
            sums = self._device_sums(est.z, (color, est.albedo, basis, lights, usable, shading, residual), prior)
            return Evaluation(residual, usable, color, shading, normals, dA, basis, sums, sums)
        kernels.shading_residuals(color, est.albedo, basis, like(est.lights, color, dtype=np.float64), usable, shading,
                                  residual)
        data = cauchy_energy(residual, self.lam, kernels.log1p_square_sum) if scored else Unscored()
        return Evaluation(residual, usable, color, shading, normals, dA, basis, data,
                          self.prior_energy(est.z) if prior is None else prior)

    def albedo_reevaluation(self, est: Estimate, ev: Evaluation, *, scored: bool = True) -> Evaluation:
        """``est.albedo`` set to its closed form from ``ev``'s IRLS weights
        (:func:`.reflectance.update_albedo`) and the evaluation at it written into ``ev``'s arrays
        (:meth:`reevaluate` with overwrite; ``ev`` is given up). On a GPU in one launch
        (:func:`.kernels.albedo_evaluation_partials`), its energy read when first used; on the host
        in one compiled pass (:func:`.kernels.albedo_refit_residuals`: the same albedo and residuals
        bit for bit as the two steps, the energy to ~1e-14; it was three passes over the frames'
        arrays: the albedo's sums, the residuals, their logarithms). ``scored`` False: on the host
        without its data energy (:class:`Unscored`), for a caller that refits the lights next and
        reads the energy of that (a GPU's is read only when used anyway)."""
        xp = array_module(ev.residual)
        if xp is np:
            return self._host_albedo_reevaluation(est, ev, scored)
        num, den, albedo = (xp.empty_like(est.albedo) for _ in range(3))
        lights = self._device_poses_lights(est)[1]
        given = PendingSums.known_prior(ev.pending("prior"))
        partial = xp.empty((energy_blocks(ev.usable.size + self.level.prior.rows), 2))
        kernels_for(est.z).albedo_evaluation_partials(ev.residual, ev.usable, ev.color, ev.shading, 1.0 / self.lam,
                                                      contiguous(est.albedo), num, den, albedo, ev.basis, lights,
                                                      *self._prior_arrays(given is None), est.z, partial)
        est.albedo = albedo
        sums = PendingSums(partial, 0.5 * self.lam * self.lam, given)
        return Evaluation(ev.residual, ev.usable, ev.color, ev.shading, ev.normals, ev.dA, ev.basis, sums, sums)

    def _host_albedo_reevaluation(self, est: Estimate, ev: Evaluation, scored: bool = True) -> Evaluation:
        """:meth:`albedo_reevaluation` on the host."""
        N = ev.usable.shape[1]
        num, den, albedo = (np.empty((N, 3)) for _ in range(3))
        products, parts = np.ones(N), np.zeros(-(-N // FRAME_CHUNK))
        albedo_refit_residuals(ev.residual, ev.usable, ev.color, ev.shading, 1.0 / self.lam,
                               contiguous(est.albedo, np.float64), ev.basis,
                               like(est.lights, ev.color, dtype=np.float64), num, den, albedo, products, parts,
                               scored)
        est.albedo = albedo
        prior = ev.pending("prior")
        return Evaluation(ev.residual, ev.usable, ev.color, ev.shading, ev.normals, ev.dA, ev.basis,
                          0.5 * self.lam * self.lam * float(parts.sum()) if scored else Unscored(),
                          self.prior_energy(est.z) if prior is None else prior)

    def relit(self, est: Estimate, ev: Evaluation) -> Evaluation:
        """The evaluation of ``est``, whose z and poses are those ``ev`` was computed at but whose
        light model may differ (a moved LED offset), written into ``ev``'s residuals and shading
        (``ev`` is given up; its basis is dropped before the new one is made)."""
        ev.basis = None
        return self._evaluation(est, ev.color, ev.usable, ev.normals, ev.dA, self.bases(est, ev.normals), ev)

    def reevaluate(self, est: Estimate, ev: Evaluation, *, overwrite: bool = False) -> Evaluation:
        """Evaluation of ``est`` whose z, poses and light model are those ``ev`` was computed at.

        overwrite: write the new shading and residuals into ``ev``'s arrays (for a caller that
        gives ``ev`` up: no second frames x pixels x 3 array while the new one is computed). The
        prior energy is ``ev``'s (the same z)."""
        return self._evaluation(est, ev.color, ev.usable, ev.normals, ev.dA, ev.basis, ev if overwrite else None,
                                ev.pending("prior"))
