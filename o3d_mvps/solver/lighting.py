"""The solver's light models: the paper's first-order SH and a near-field LED.

Frame i's shading of a reference pixel is linear in that frame's light parameters l_i (k,):
``s_i(p) = <B_i(p), l_i>``. Every method takes the reference surface, unit normals (N, 3) and
points (N, 3) in reference coordinates (metres), and frame i's pose (4, 4) reference -> frame i.

- :class:`SHLight` (k = 4, the paper): ``B = [1, n]``; l_i = (ambient, 3 directional terms) in
  reference coordinates, so the shading does not depend on the pose.
- :class:`RoomLight` (k = 4): the SH basis with one light fixed in the room for every frame,
  ``l_i = g_i l`` (g_i: the frame's exposure gain, g_0 = 1). Room light does not move with the
  camera, so every frame sees the same shading: once the albedo is free per pixel, the shading
  says nothing about the normals and the depth learns only from the warp's parallax. Fitted per
  frame (SH), the light's model error differs between frames and pulled the normals (a bunny on
  a table, 640x480: 11.8 deg inside the silhouette with the warp frozen, 6.6 with one light).
- :class:`LEDLight` (k = 2, the paper's future work): a point light at ``offset`` (3,) metres in
  the camera frame, moving with the camera, plus ambient light:
  ``B_i = [1, max(0, <n, v_i>)]``, ``v_i = (s_i - X) / |s_i - X|^3`` (1/m^2) with
  ``s_i = R_i^T (o - t_i)`` the LED in reference coordinates; l_i = (ambient, intensity in
  irradiance x m^2). The shading of frame i depends on its pose, and the offset can be estimated
  with the rest (:func:`update_led_offset`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..model.arrays import array_module, contiguous, like
from ..model.shading import (INITIAL_LIGHT, led_bases_into, led_fields_into, led_irradiances, led_positions_into,
                             sh_basis)
from .device import DeviceCopies, kernels_for, to_host
from .line_search import backtrack
from .linear import ridge_solve


class FrameFields:
    """One frame's light field and shading Jacobian, from the light model's batched ``fields``
    and ``shading_jacobians`` of m frames (lights (m, k), poses (m, 4, 4))."""

    def frames(self, selection: slice) -> "FrameFields":
        """The model for the frames ``selection`` picks (a batch of frames, with their poses
        ``poses[selection]``): the same model, unless it holds something per frame."""
        return self

    def field(self, light: np.ndarray, normals: np.ndarray, points: np.ndarray, pose: np.ndarray):
        """(c, L): frame's shading ``c + <L, n>`` for light (k,) and pose (4, 4) (:meth:`fields`)."""
        c, L = self.fields(light[None], normals, points, pose[None])
        return c[0], L[0]

    def shading_jacobian(self, light: np.ndarray, normals: np.ndarray, points: np.ndarray, pose: np.ndarray):
        """d(shading)/d(xi) (N, 6) of one frame, or None (:meth:`shading_jacobians`)."""
        J = self.shading_jacobians(light[None], normals, points, pose[None])
        return None if J is None else J[0]


@dataclass
class SHLight(FrameFields):
    """First-order spherical harmonics per frame (paper section 3); ``initial`` (4,)."""

    initial: tuple = INITIAL_LIGHT
    name = "sh"
    size = 4
    #: one light for every frame, fixed in the world: the shading is the same in every frame
    fixed_in_world = False

    def initial_lights(self, n_frames: int, mean_depth: float) -> np.ndarray:
        """(n, 4) starting lights."""
        return np.tile(np.asarray(self.initial, dtype=np.float64), (n_frames, 1))

    def basis(self, normals: np.ndarray, points: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """(N, 4) ``[1, n]``."""
        return sh_basis(normals)

    def bases(self, normals: np.ndarray, points: np.ndarray, poses: np.ndarray, dtype=np.float64) -> np.ndarray:
        """(1, N, 4): the one basis every frame shares (in ``dtype``)."""
        return sh_basis(normals)[None].astype(dtype, copy=False)

    def fields(self, lights: np.ndarray, normals: np.ndarray, points: np.ndarray, poses: np.ndarray, out=None):
        """(c, L): frame i's shading is ``c_i + <L_i, n>`` with n in reference coordinates; here
        c (m,) and L (m, 3) of lights (m, 4), the same for every pixel (``out`` is not used)."""
        return lights[:, 0], lights[:, 1:]

    def shading_jacobians(self, lights, normals, points, poses, out=None) -> None:
        """d(shading)/d(xi): zero, the SH light lives in reference coordinates."""
        return None

    def fit(self, gram: np.ndarray, rhs: np.ndarray, lights: np.ndarray) -> np.ndarray:
        """Lights (n, 4) minimising ``sum_i l_i^T gram_i l_i - 2 rhs_i . l_i``: each frame its own
        (:func:`fit_per_frame`). gram (n, 4, 4), rhs (n, 4); ``lights`` (n, 4) are kept for
        frames whose gram is zero or singular."""
        return fit_per_frame(gram, rhs, lights)

    def describe(self) -> dict:
        return {"model": "sh", "formula": "shading = l . [1, n_x, n_y, n_z], n in reference coordinates",
                "parameters": ["ambient", "l_x", "l_y", "l_z"]}


@dataclass
class RoomLight(SHLight):
    """One first-order SH light fixed in the room, times a per-frame exposure gain: the lights
    (n, 4) are ``g_i l`` with g_0 = 1 (rank one)."""

    name = "room"
    fixed_in_world = True

    def fit(self, gram: np.ndarray, rhs: np.ndarray, lights: np.ndarray, rounds: int = 100,
            rtol: float = 1e-12) -> np.ndarray:
        """Lights ``g_i l`` (n, 4) minimising ``sum_i g_i^2 l^T gram_i l - 2 g_i rhs_i . l``:
        alternations of l (one 4x4 solve over all frames) and the gains (one ratio per frame),
        from the gains of ``lights`` (n, 4) (each frame's projection on frame 0's light), until
        the gains change by less than ``rtol`` (at most ``rounds``; each is a few 4x4 products).
        A frame without pixels keeps its gain; ``lights`` are returned unchanged when the frames
        together do not determine the light."""
        reference = lights[0]
        gains = lights @ reference / max(float(reference @ reference), 1e-300)
        gains[0] = 1.0
        light = None
        for _ in range(rounds):
            solved = ridge_solve(np.einsum("i,ijk->jk", gains**2, gram), gains @ rhs, ridge=1e-12)
            if solved is None:
                break
            light = solved
            curvature = np.einsum("j,ijk,k->i", light, gram, light)
            seen = curvature > 1e-12 * max(float(curvature.max()), 1e-300)
            seen[0] = False  # frame 0's gain stays 1: the light's scale
            previous, gains = gains, np.where(seen, rhs @ light / np.where(seen, curvature, 1.0), gains)
            if np.max(np.abs(gains - previous)) <= rtol * np.max(np.abs(gains)):
                break
        return lights.copy() if light is None else gains[:, None] * light[None, :]

    def describe(self) -> dict:
        return {"model": "room", "formula": "shading = g_i l . [1, n_x, n_y, n_z], n in reference coordinates, "
                "one light l for all frames, g_i the frame's exposure gain (g_0 = 1)",
                "parameters": ["g_i l_ambient", "g_i l_x", "g_i l_y", "g_i l_z"]}


@dataclass
class LEDLight(FrameFields):
    """Near-field point light at ``offset`` (3,) metres in the camera frame, plus ambient."""

    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    name = "led"
    size = 2
    fixed_in_world = False

    def __post_init__(self):
        self.offset = np.asarray(self.offset, dtype=np.float64).reshape(3)

    def at(self, offset: np.ndarray) -> "LEDLight":
        """The same model with the LED at ``offset`` (3,) metres."""
        return LEDLight(offset)

    def initial_lights(self, n_frames: int, mean_depth: float) -> np.ndarray:
        """(n, 2) starting lights: ambient 0.2 and an intensity lighting a frontal surface with 1."""
        return np.tile([0.2, mean_depth**2], (n_frames, 1))

    def position(self, pose: np.ndarray) -> np.ndarray:
        """The LED (3,) in reference coordinates for the frame with ``pose``: R^T (o - t)."""
        return self.positions(pose[None])[0]

    def positions(self, poses: np.ndarray) -> np.ndarray:
        """:meth:`position` (m, 3) of the frames with ``poses`` (m, 4, 4)."""
        out = np.empty((len(poses), 3))
        led_positions_into(np.ascontiguousarray(poses, dtype=np.float64), self.offset, out)
        return out

    def irradiance(self, normals: np.ndarray, points: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """<n, v_i> (N,) per unit intensity, unclamped (negative where the point faces away)."""
        return self.irradiances(normals, points, pose[None])[0]

    def irradiances(self, normals: np.ndarray, points: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """:meth:`irradiance` (m, N) for the frames with ``poses`` (m, 4, 4), computed together."""
        return led_irradiances(normals, points, self.positions(poses), kernels_for(points).led_irradiances_into)

    def basis(self, normals: np.ndarray, points: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """(N, 2) ``[1, max(0, <n, v_i>)]``."""
        return self.bases(normals, points, pose[None])[0]

    def bases(self, normals: np.ndarray, points: np.ndarray, poses: np.ndarray, dtype=np.float64) -> np.ndarray:
        """(m, N, 2) :meth:`basis` of the frames with ``poses`` (m, 4, 4), in ``dtype`` (the
        solver's evaluations keep it in their residuals' float32: 150 MB instead of 300 at 2 MP
        and 20 frames). On the host one compiled pass (:func:`~o3d_mvps.model.shading.led_bases_into`:
        no (m, N) float64 temporary, no pass filling ones)."""
        if array_module(points) is np:
            out = np.empty((len(poses), len(points), 2), dtype=dtype)
            led_bases_into(contiguous(normals, np.float64), contiguous(points, np.float64),
                           np.ascontiguousarray(self.positions(poses), dtype=np.float64), out)
            return out
        g = self.irradiances(normals, points, poses)
        out = array_module(g).ones(g.shape + (2,), dtype=dtype)
        np.maximum(g, 0.0, out=out[..., 1])
        return out

    def fields(self, lights: np.ndarray, normals: np.ndarray, points: np.ndarray, poses: np.ndarray, out=None):
        """(c, L): frame i's shading is ``c_i + <L_i, n>``; c (m,) the ambients of lights (m, 2),
        L (m, N, 3) the intensity times v_i, zero where the point faces away (on the host one
        compiled pass, :func:`~o3d_mvps.model.shading.led_fields_into`, written into ``out``
        (m, N, 3) C-contiguous float64 where given; on a GPU its CUDA twin, one launch and one
        copy of the intensities and positions)."""
        if array_module(points) is np:
            L = np.empty((len(lights), len(points), 3)) if out is None else out
            led_fields_into(_intensities(lights, points), contiguous(normals, np.float64),
                            contiguous(points, np.float64), np.ascontiguousarray(self.positions(poses)), L)
            return lights[:, 0], L
        state = device_light_state(self, lights, poses, points)
        L = array_module(points).empty((len(state.positions), len(points), 3))
        kernels_for(points).led_fields_into(state.intensities, contiguous(normals, np.float64),
                                            contiguous(points, np.float64), state.positions, L)
        return lights[:, 0], L

    def _camera_gradients(self, lights, normals, points, poses):
        """d(shading)/d(point) (m, N, 3) in each frame's camera coordinates, zero where unlit."""
        J = lit_point_gradients(lights, normals, points, self.positions(poses))
        return np.matmul(J, like(poses[:, :3, :3].transpose(0, 2, 1), points))

    def shading_jacobians(self, lights: np.ndarray, normals: np.ndarray, points: np.ndarray,
                          poses: np.ndarray, out=None) -> np.ndarray:
        """d(shading)/d(xi) (m, N, 6) for a left update exp(xi) T of each frame, xi = (v, w),
        written into ``out`` (m, N, 6) C-contiguous float64 where given (the joint step's
        assembly reuses one buffer for its blocks: no fresh pages per block).

        Moving the camera moves the LED with it: s_i = T^-1 o, so with G the shading's gradient
        with respect to the point in camera coordinates, ``d/dv = G`` and ``d/dw = o x G``.
        """
        if out is None:
            out = array_module(points).empty((len(poses), len(points), 6))
        if array_module(points) is not np:  # one kernel on a GPU (the light state's copy shared: device_light_state)
            state = device_light_state(self, lights, poses, points)
            kernels_for(points).led_shading_jacobians_into(
                state.intensities, contiguous(normals, np.float64), contiguous(points, np.float64), state.positions,
                state.rotations, state.offset, out)
            return out
        # the same compiled pass on the host, in parallel over pixels (were a point-gradient pass,
        # a NumPy product with the rotations and a pass for [G, o x G]: 4.1 -> 0.9 ms a D415
        # assembly block of 4096 pixels and 20 frames; the same to round-off, 1e-16)
        kernels_for(points).led_shading_jacobians_into(
            _intensities(lights, points), contiguous(normals, np.float64), contiguous(points, np.float64),
            np.ascontiguousarray(self.positions(poses)), np.ascontiguousarray(poses[:, :3, :3], dtype=np.float64),
            self.offset, out)
        return out

    def offset_jacobian(self, light: np.ndarray, normals: np.ndarray, points: np.ndarray,
                        pose: np.ndarray) -> np.ndarray:
        """d(shading)/d(offset) (N, 3) of one frame."""
        return self.offset_jacobians(light[None], normals, points, pose[None])[0]

    def offset_jacobians(self, lights: np.ndarray, normals: np.ndarray, points: np.ndarray,
                         poses: np.ndarray) -> np.ndarray:
        """d(shading)/d(offset) (m, N, 3) of the frames with lights (m, 2) and poses (m, 4, 4)."""
        return -self._camera_gradients(lights, normals, points, poses)

    def fit(self, gram: np.ndarray, rhs: np.ndarray, lights: np.ndarray) -> np.ndarray:
        """Per-frame lights (n, 2): :func:`fit_per_frame` with the basis scaled, for its columns
        carry different units (1 and the irradiance, m^-2)."""
        return fit_per_frame(gram, rhs, lights, scaled=True)

    def describe(self) -> dict:
        return {"model": "led",
                "formula": "shading = ambient + intensity * max(0, n . (o - X)) / |o - X|^3, camera frame",
                "parameters": ["ambient", "intensity"], "offset_m": self.offset.tolist()}


def _intensities(lights: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The intensities ``lights[:, 1]`` (m,) in float64 as the array formulas use them: rounded
    to the points' dtype first."""
    return lights[:, 1].astype(points.dtype).astype(np.float64)


def _light_arrays(lights: np.ndarray, points: np.ndarray, positions: np.ndarray) -> tuple:
    """:func:`_intensities` (m,) and the positions (m, 3) float64 where the points are: on a GPU
    in one copy (views of one array; positions may carry further rows of three, which come along)."""
    intensities = _intensities(to_host(lights), points)
    positions = np.asarray(to_host(positions), dtype=np.float64).reshape(-1, 3)
    if array_module(points) is np:
        return intensities, np.ascontiguousarray(positions)
    packed = _LIGHT_COPIES.copy(np.concatenate([intensities, positions.reshape(-1)]), points)
    m = len(intensities)
    return packed[:m], packed[m:].reshape(-1, 3)


#: device copies of :func:`_light_arrays`' recent light states: a sweep's several calls with one
#: state copy it once (gpu3)
_LIGHT_COPIES = DeviceCopies(kept=4)


@dataclass
class DeviceLightState:
    """The small arrays the GPU's kernels read of one light state, float64 views of one device
    array (:func:`device_light_state`): poses (n, 4, 4), lights (n, k), and for the LED and
    point lights the offset (3,) (point lights: (n, 3)), the intensities ``lights[:, 1]`` (n,)
    (:func:`_intensities`), the light positions (n, 3) in reference coordinates and the poses'
    rotations (n, 3, 3); those three empty for other models."""

    poses: np.ndarray
    lights: np.ndarray
    offset: np.ndarray
    intensities: np.ndarray
    positions: np.ndarray
    rotations: np.ndarray


def device_light_state(light, lights: np.ndarray, poses: np.ndarray, reference) -> DeviceLightState:
    """The :class:`DeviceLightState` of the light model ``light`` with lights (n, k) and poses
    (n, 4, 4) on ``reference``'s device (the intensities rounded to its dtype: the points'),
    in one copy, or none where the same state was copied lately (:data:`_STATE_COPIES`): an
    evaluation, the joint step's Jacobians and fields, the LED offset's system and line search
    of one state share one copy (gpueval2)."""
    parts = _state_parts(light, lights, poses, reference)
    return _state_views(light, parts, _STATE_COPIES.copy(np.concatenate(parts), reference))


def preload_light_states(states: list, reference, extra: tuple = ()) -> list:
    """Copy the light states ``states`` [(light, lights, poses)] that :func:`device_light_state`
    will be asked for (an extrapolation's trials) in one copy, those not kept already, with the
    host arrays ``extra`` (1-d); returns the device copies of ``extra``."""
    return _STATE_COPIES.copy_many([np.concatenate(_state_parts(*state, reference)) for state in states], reference,
                                   extra)[1]


def _state_parts(light, lights, poses, reference) -> tuple:
    """The host arrays (1-d, float64) of :func:`device_light_state`: poses, lights, offset,
    intensities, positions, rotations."""
    host_poses = np.ascontiguousarray(to_host(poses), dtype=np.float64)
    host_lights = np.ascontiguousarray(to_host(lights), dtype=np.float64)
    if isinstance(light, LEDLight):
        offset = light.offset.reshape(-1)
        positions, intensities = light.positions(host_poses).reshape(-1), _intensities(host_lights, reference)
        rotations = host_poses[:, :3, :3].reshape(-1)
    else:
        offset = positions = intensities = rotations = np.zeros(0)
    return host_poses.reshape(-1), host_lights.reshape(-1), offset, intensities, positions, rotations


def _state_views(light, parts: tuple, packed) -> DeviceLightState:
    """The :class:`DeviceLightState` views of ``packed``, the device copy of ``parts``' concatenation."""
    ends = np.cumsum([0] + [len(part) for part in parts])
    views = [packed[a:b] for a, b in zip(ends[:-1], ends[1:])]
    n = len(parts[0]) // 16
    return DeviceLightState(views[0].reshape(n, 4, 4), views[1].reshape(n, -1),
                            views[2].reshape(light.offset.shape) if len(parts[2]) else views[2], views[3],
                            views[4].reshape(-1, 3), views[5].reshape(-1, 3, 3))


#: device copies of :func:`device_light_state`'s recent states (an extrapolation's trials and
#: the state it started from)
_STATE_COPIES = DeviceCopies(kept=6)


def lit_point_gradients(lights: np.ndarray, normals: np.ndarray, points: np.ndarray,
                        positions: np.ndarray) -> np.ndarray:
    """d(shading)/d(point) (m, N, 3) of m point lights at ``positions`` (m, 3) with intensities
    ``lights[:, 1]`` (m,) on unit normals and points (N, 3), all in one frame (metres): the
    intensity times :func:`~o3d_mvps.model.shading.led_vector_jacobian`, zero where the point
    faces away. The derivative with respect to the light's position is its negative. One
    compiled pass (:func:`~o3d_mvps.model.shading.led_point_gradients_into`, equal bit for bit
    to the array formulas; on a GPU its CUDA twin, one launch)."""
    J = array_module(points).empty((len(positions), len(points), 3))
    intensities, positions = _light_arrays(lights, points, positions)
    kernels_for(points).led_point_gradients_into(intensities, contiguous(normals, np.float64),
                                                 contiguous(points, np.float64), positions, J)
    return J


@dataclass
class PointLight(LEDLight):
    """A free point light per frame (a lamp moved by hand around a static camera, Peng et al.
    2017), plus ambient: frame i's light sits at ``positions[i]`` (3,) metres in reference
    coordinates (a static camera's own frame) and shades like the LED,
    ``B_i = [1, max(0, <n, v_i>)]``, ``v_i = (p_i - X) / |p_i - X|^3``; l_i = (ambient,
    intensity in irradiance x m^2). The positions are unknowns (:mod:`.point_light`),
    carried in the estimate's ``led_offset`` (n, 3); the shading does not depend on the poses
    (the light does not move with the camera), so the poses are not refined with this model."""

    offset: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    name = "point"
    size = 2
    fixed_in_world = False

    def __post_init__(self):
        self.offset = np.asarray(self.offset, dtype=np.float64).reshape(-1, 3)

    def at(self, offset: np.ndarray) -> "PointLight":
        """The same model with the lights at ``offset`` (n, 3) metres."""
        return PointLight(offset)

    def frames(self, selection: slice) -> "PointLight":
        """The model of the frames ``selection`` picks: their own lights."""
        return PointLight(self.offset[selection])

    def positions(self, poses: np.ndarray) -> np.ndarray:
        """The frames' light positions (n, 3) in reference coordinates; poses (n, 4, 4) of all n
        frames of the model (a single frame's pose cannot say which light is its own: take
        :meth:`frames` first)."""
        if len(poses) != len(self.offset):
            raise ValueError(f"the point light model has {len(self.offset)} light positions, one per frame, "
                             f"but was asked for {len(poses)} frames: it shades all frames together (a static "
                             f"camera, no pose refinement)")
        return self.offset

    def shading_jacobians(self, lights, normals, points, poses, out=None) -> None:
        """d(shading)/d(xi): zero, the lights live in reference coordinates."""
        return None

    def position_jacobians(self, lights: np.ndarray, normals: np.ndarray, points: np.ndarray) -> np.ndarray:
        """d(shading)/d(position) (n, N, 3) of every frame's light (:func:`lit_point_gradients`)."""
        return -lit_point_gradients(lights, normals, points, self.offset)

    def initial_positions(self, sh_lights: np.ndarray, centre: np.ndarray, distance: float) -> tuple:
        """Lights (n, 2) and positions (n, 3) from per-frame SH lights (n, 4): each light at
        ``distance`` metres from ``centre`` (3,) (the object's centroid) along its SH light's
        direction, its intensity giving a surface facing it the SH light's directional strength,
        its ambient the SH ambient."""
        direction = sh_lights[:, 1:]
        strength = np.linalg.norm(direction, axis=1)
        unit = np.where(strength[:, None] > 0, direction / np.maximum(strength, 1e-12)[:, None], [0.0, 0.0, -1.0])
        return (np.stack([sh_lights[:, 0], strength * distance**2], axis=1), centre + distance * unit)

    def describe(self) -> dict:
        return {"model": "point",
                "formula": "shading = ambient_i + intensity_i * max(0, n . (p_i - X)) / |p_i - X|^3, "
                           "reference camera frame",
                "parameters": ["ambient", "intensity"], "positions_m": self.offset.tolist()}


#: the least eigenvalue of a frame's light gram, relative to its largest, whose direction the
#: lighting step moves (:func:`fit_per_frame`)
LIGHT_MIN_EIGENVALUE = 1e-3


def fit_per_frame(gram: np.ndarray, rhs: np.ndarray, lights: np.ndarray, scaled: bool = False) -> np.ndarray:
    """Each frame's light (n, k): the least-squares solution of ``gram_i l_i = rhs_i`` in the
    directions the pixels determine (eigenvalues of gram_i above :data:`LIGHT_MIN_EIGENVALUE`
    times its largest), the current light ``lights_i`` kept in the others. On a coarse level of a
    nearly flat object the normals hardly vary, so ambient and directional light trade off
    freely: solved in full, a static-camera quilt's SH lights turned 140-160 degrees away on
    the 1/16 level, the finer levels kept that basin and the normals came out 8.0 degrees off
    (with 3 levels instead of 5: 2.6). gram (n, k, k), rhs (n, k); ``lights`` (n, k) kept for a
    frame whose gram is zero or not finite.

    ``scaled``: the directions are judged with the basis columns scaled to a unit diagonal of
    gram_i, for a basis whose columns carry different units (the LED's 1 and irradiance in
    m^-2): unscaled, the threshold depends on the units. At 0.25 m (irradiance ~16 m^-2) the
    ambient's direction fell under it: the ambient stayed at its start, 2-3.6x the truth's share,
    and the poses and the LED offset took up the difference (2 MP bunny: normals 2.46 deg,
    poses 0.17 deg and the offset 12 mm from the truth; scaled: 1.13 deg, 0.03 deg, 2 mm).
    """
    out = lights.copy()
    for i in range(len(out)):
        G, r, light = gram[i], rhs[i], lights[i]
        if not (np.trace(G) > 0 and np.isfinite(G).all() and np.isfinite(r).all()):
            continue
        d = np.ones(len(light))
        if scaled:  # G = D G' D with D = diag(d): solved for D l in G's unit-free form G'
            diagonal = np.diag(G)
            d = np.where(diagonal > 0, np.sqrt(np.where(diagonal > 0, diagonal, 1.0)), 1.0)
            G, r, light = G / np.outer(d, d), r / d, light * d
        values, vectors = np.linalg.eigh(G)
        keep = values > LIGHT_MIN_EIGENVALUE * values[-1]
        V = vectors[:, keep]
        out[i] = (light + V @ ((V.T @ (r - G @ light)) / values[keep])) / d
    return out


LIGHT_MODELS = ("led", "sh", "room", "point")


def make_light_model(name: str, *, initial_sh=INITIAL_LIGHT, led_offset=None):
    """The light model ``name`` ("led", "sh", "room" or "point": its positions, one per frame, are
    set by :func:`.point_light.initial_point_lights`)."""
    if name == "sh":
        return SHLight(tuple(initial_sh))
    if name == "room":
        return RoomLight(tuple(initial_sh))
    if name == "led":
        return LEDLight(np.zeros(3) if led_offset is None else led_offset)
    if name == "point":
        return PointLight()
    raise ValueError(f"light_model must be one of {LIGHT_MODELS}, got {name!r}")


def update_led_offset(problem, est, ev, *, max_halvings: int = 3, max_pixels: int = 4000, min_decrease: float = 0.0,
                      relative: bool = False):
    """One IRLS Gauss-Newton step on the LED offset (all frames): returns (offset (3,), evaluation).

    The step is computed from at most ``max_pixels`` evenly spread pixels per frame (three
    unknowns need few), the line search on the full energy (on a GPU every frame's system summed,
    solved and every trial scored on the device, one read: :func:`_device_offset_search`, the
    system in one launch: :func:`.kernels.led_offset_system`); the
    offset is ``est``'s (or the
    light model's) unchanged, with ``ev``, when no step lowers the energy, or when the
    Gauss-Newton model predicts a decrease below ``min_decrease`` (energy units, or with
    ``relative`` times ``ev``'s energy; each line search trial costs an energy, and near
    convergence they nearly all fail). On a GPU ``ev``'s data energy, where not read yet, comes
    with the trials' read (their sums at the current offset). The trials are
    scored by :meth:`.LevelProblem.energy` from ``ev``'s samples (no frames x pixels arrays
    but a few frames'); the kept offset's evaluation is written into ``ev``'s arrays
    (:meth:`.LevelProblem.relit`), so ``ev`` is given up when the offset moves.
    """
    light = problem.light_model(est)
    stride = max(1, ev.usable.shape[1] // max_pixels)
    P = problem.points(est.z)
    xp = array_module(P)
    # every frame's system at once from every stride-th pixel, unusable pixels weighted 0: one launch
    # on a GPU, one compiled pass on the host (was a NumPy loop over the frames: 0.49 of a D415
    # refine's CPU s in 33 calls; the same sums in another order)
    if xp is not np:
        state = device_light_state(light, est.lights, est.poses, P)  # the evaluation's copy: none made here
        intensities, positions, rotations = state.intensities, state.positions, state.rotations
    else:
        intensities, positions = _intensities(est.lights, P), np.ascontiguousarray(light.positions(est.poses))
        rotations = np.ascontiguousarray(est.poses[:, :3, :3], dtype=np.float64)
    H, g = xp.empty((1, 3, 3)), xp.empty((1, 3, 1))
    kernels_for(P).led_offset_system(intensities, contiguous(ev.normals, np.float64), contiguous(P, np.float64),
                                     positions, rotations, ev.residual, ev.usable,
                                     contiguous(est.albedo, np.float64), 1.0 / problem.lam, stride, H, g)
    if xp is not np:
        return _device_offset_search(problem, est, ev, light, H, g, stride, max_halvings, min_decrease, relative)
    min_decrease = min_decrease * ev.energy if relative else min_decrease
    H, g = H[0], g[0, :, 0]
    start = light.offset
    step = ridge_solve(H, -g) if np.trace(H) > 0 else None
    # the IRLS model's decrease -g.step / 2 on the spread pixels, scaled to all of them
    if step is None or -0.5 * float(g @ step) * stride < min_decrease:
        return start, ev

    def trial(t: float):
        moved = dataclasses.replace(est, led_offset=start + t * step)
        # scored a few frames at a time from ev's samples; only the kept offset is evaluated
        return moved, problem.energy(moved, (ev.color, ev.usable), ev.normals, prior=ev.prior)[0]

    found = backtrack(trial, ev.energy, max_halvings)
    if found is None:
        return start, ev
    moved = found[1]
    return moved.led_offset, problem.relit(moved, ev)


def _device_offset_search(problem, est, ev, light, H, g, stride, max_halvings, min_decrease, relative):
    """:func:`update_led_offset`'s step and line search on a GPU from its system H (1, 3, 3), g
    (1, 3, 1) on the device: the step solved and every trial length 1, 1/2, ..., 2^-max_halvings scored
    in one launch (:func:`.kernels.led_trial_sums`: the step by the host's ridge_solve formula,
    the data energy of :meth:`.LevelProblem.energy` from ``ev``'s samples, plus ``ev``'s prior),
    the light state's copy shared with ``ev``'s evaluation (:func:`device_light_state`) and one
    read (the trials' sums, the step, g),
    where the host's line search reads a system and then an energy per trial; then the longest
    trial whose energy is not above ``ev``'s, as :func:`.line_search.backtrack` takes it."""
    xp, P = array_module(ev.residual), problem.points(est.z)
    start, K = light.offset, max_halvings + 1
    state = device_light_state(light, est.lights, est.poses, P)  # the evaluation's copy: none made here
    kernels = kernels_for(P)
    # the trials' sums, the current offset's (ev's data energy: not read apart; current=True, the
    # last argument), then x, solved, g
    out = xp.empty((K + 2, kernels.trial_blocks(*ev.usable.shape)))
    kernels.led_trial_sums(ev.color, ev.usable, contiguous(est.albedo, np.float64), contiguous(ev.normals, np.float64),
                           contiguous(P, np.float64), state.poses, state.offset, H, g, state.lights,
                           1.0 / problem.lam, problem.residual_dtype == np.float32, out, True)
    out = to_host(out)
    if not isinstance(ev.pending("data"), float):  # ev's data energy from this read, as the trials'
        ev.data = 0.5 * problem.lam ** 2 * float(out[K].sum())
    min_decrease = min_decrease * ev.energy if relative else min_decrease
    sums, step, solved, g = out[:K], -out[K + 1, :3], out[K + 1, 3:4], out[K + 1, 4:7]
    # the IRLS model's decrease -g.step / 2 on the spread pixels, scaled to all of them
    if not solved[0] or -0.5 * float(g @ step) * stride < min_decrease:
        return start, ev
    energies = 0.5 * problem.lam ** 2 * sums.sum(axis=1) + ev.prior
    for k, energy in enumerate(energies):
        if energy <= ev.energy:
            moved = dataclasses.replace(est, led_offset=start + 0.5 ** k * step)
            return moved.led_offset, problem.relit(moved, ev)
    return start, ev
