"""Light models of the renderer: a point LED moving with the camera, an SH-exact directional light
fixed to the camera, and room light (ambient plus distant lights fixed in the scene)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import open3d as o3d

from ..model.shading import led_vectors
from .scene import apply_matrix

if TYPE_CHECKING:  # annotations only
    from .render import FrameRender
    from .scene import SyntheticScene

LIGHTS = ("led", "directional", "room")

LED_OFFSET = (0.03, -0.02, 0.0)  # metres, camera frame
LED_FRONTAL_IRRADIANCE = 0.85  # irradiance of a frontal surface at the object centre
LED_AMBIENT = 0.03
SHADOW_OFFSET = 1e-4  # metres along the normal

SH_AMBIENT = 0.5
SH_STRENGTH = 0.45  # < SH_AMBIENT: shading stays >= 0.05 for any normal
SH_DIRECTION = (0.35, -0.3, -1.0)  # toward the light, camera frame (normalised)

ROOM_AMBIENT = 0.3
# (strength, direction toward the light in the scene frame: x right, y down, z away from the reference camera)
ROOM_LIGHTS = ((0.4, (-0.5, -1.0, -0.7)),  # key light: above, left, in front
               (0.15, (0.9, -0.4, -0.2)),  # fill from the right
               (0.15, (0.2, -1.0, 0.6)))  # ceiling light behind the object
DISTANT = 100.0  # metres: how far a shadow ray toward a distant light is followed


def unoccluded(scene, origins: np.ndarray, directions: np.ndarray, reach: float) -> np.ndarray:
    """(N,) bool: the segments ``origins + t * directions``, t in [0, reach], hit nothing (scene frame)."""
    rays = o3d.core.Tensor(np.hstack([origins, directions]).astype(np.float32))
    return ~scene.raycaster.test_occlusions(rays, tnear=0.0, tfar=reach).numpy().astype(bool)


@dataclass(frozen=True)
class PointLight:
    """Point light at ``offset`` (3,) metres in the camera frame, moving with the camera.

    ``I = albedo * (ambient + intensity * V * max(0, n.l) / r^2)``; ``intensity`` in
    irradiance x m^2; V the shadow-ray visibility.
    """

    offset: tuple = LED_OFFSET
    intensity: float = LED_FRONTAL_IRRADIANCE * 0.6**2
    ambient: float = LED_AMBIENT
    shadows: bool = True

    def shading(self, scene: SyntheticScene, pose: np.ndarray, frame: "FrameRender") -> np.ndarray:
        """Shading (N,) of the frame's hit pixels (N = frame.hit.sum())."""
        X = frame.points[frame.hit]  # camera frame
        n = frame.normals[frame.hit]
        irradiance = np.maximum(0.0, np.einsum("ij,ij->i", n, led_vectors(X, np.asarray(self.offset))))
        if self.shadows:
            irradiance *= self._visible(scene, pose, X, n, np.asarray(self.offset) - X, irradiance > 0)
        return self.ambient + self.intensity * irradiance

    @staticmethod
    def _visible(scene, pose, X, n, to_light, lit) -> np.ndarray:
        """1.0 where a shadow ray from X + SHADOW_OFFSET n reaches the light, else 0 (N,)."""
        visible = np.zeros(len(X))
        if not lit.any():
            return visible
        R_c2r, C = pose[:3, :3].T, -pose[:3, :3].T @ pose[:3, 3]
        origin = apply_matrix(R_c2r, X[lit] + SHADOW_OFFSET * n[lit]) + C
        direction = apply_matrix(R_c2r, to_light[lit] - SHADOW_OFFSET * n[lit])  # reaches the light at t = 1
        visible[lit] = unoccluded(scene, origin, direction, 1.0)
        return visible

    def parameters(self, poses: np.ndarray, scene_to_reference: np.ndarray | None = None) -> dict:
        """JSON-serialisable parameters; ``positions`` (n, 3) light centres in reference coordinates
        (from ``poses``, reference -> frame; a light fixed to the camera needs no ``scene_to_reference``)."""
        inv = np.linalg.inv(poses)
        positions = inv[:, :3, :3] @ np.asarray(self.offset) + inv[:, :3, 3]
        return {
            "model": "led",
            "offset": [float(v) for v in self.offset],
            "intensity": float(self.intensity),
            "ambient": float(self.ambient),
            "falloff": "inverse-square",
            "shadows": bool(self.shadows),
            "positions": positions.tolist(),
            "formula": "albedo * (ambient + intensity * visible * max(0, n.l) / r^2), camera frame",
        }


@dataclass(frozen=True)
class DirectionalLight:
    """SH-exact light fixed in the camera frame: shading ``ambient + strength * d . n_cam``.

    ``direction`` (3,) toward the light (normalised on use), camera frame. With
    ``strength < ambient`` the shading is positive for every normal; no clamping, no shadows.
    """

    direction: tuple = SH_DIRECTION
    ambient: float = SH_AMBIENT
    strength: float = SH_STRENGTH

    def sh_camera(self) -> np.ndarray:
        """(4,) SH vector [ambient, strength * d] in camera coordinates."""
        d = np.asarray(self.direction, dtype=np.float64)
        return np.concatenate([[self.ambient], self.strength * d / np.linalg.norm(d)])

    def sh_reference(self, pose: np.ndarray) -> np.ndarray:
        """(4,) SH vector of the frame with ``pose`` (reference -> frame) in reference coordinates."""
        l = self.sh_camera()
        return np.concatenate([l[:1], pose[:3, :3].T @ l[1:]])

    def shading(self, scene: SyntheticScene, pose: np.ndarray, frame: "FrameRender") -> np.ndarray:
        """Shading (N,) of the frame's hit pixels: ``<l_cam, [1, n_cam]>``."""
        l = self.sh_camera()
        return l[0] + apply_matrix(l[None, 1:], frame.normals[frame.hit])[:, 0]

    def parameters(self, poses: np.ndarray, scene_to_reference: np.ndarray | None = None) -> dict:
        """JSON-serialisable parameters; ``sh`` (n, 4) per-frame SH vectors in reference coordinates
        (from ``poses``, reference -> frame; a light fixed to the camera needs no ``scene_to_reference``)."""
        return {
            "model": "directional",
            "direction": [float(v) for v in self.sh_camera()[1:] / self.strength],
            "ambient": float(self.ambient),
            "strength": float(self.strength),
            "sh": [self.sh_reference(T).tolist() for T in poses],
            "formula": "albedo * <sh[i], [1, n_x, n_y, n_z]>, n unit normal in reference coordinates",
        }


@dataclass(frozen=True)
class RoomLight:
    """Room light fixed in the scene: ambient plus distant lights, with shadows.

    ``I = albedo * (ambient + sum_k strength_k * V_k * max(0, n . d_k))``, n the unit normal and
    d_k the unit direction toward light k, both in the scene frame; V_k the shadow-ray visibility.
    Every frame sees the same light: the frames differ in shading only through the viewpoint,
    which is what makes room-lit captures hard for photometric methods. Smooth enough for the
    first-order SH model ("sh") to fit it closely.
    """

    ambient: float = ROOM_AMBIENT
    lights: tuple = ROOM_LIGHTS
    shadows: bool = True

    def directions(self) -> np.ndarray:
        """(K, 3) unit directions toward the lights, scene frame."""
        d = np.array([direction for _, direction in self.lights], dtype=np.float64)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def shading(self, scene: SyntheticScene, pose: np.ndarray, frame: "FrameRender") -> np.ndarray:
        """Shading (N,) of the frame's hit pixels (N = frame.hit.sum())."""
        R_c2r, C = pose[:3, :3].T, -pose[:3, :3].T @ pose[:3, 3]
        n = apply_matrix(R_c2r, frame.normals[frame.hit])
        X = apply_matrix(R_c2r, frame.points[frame.hit]) + C
        shading = np.full(len(n), self.ambient)
        for (strength, _), d in zip(self.lights, self.directions()):
            irradiance = np.maximum(0.0, n @ d)
            lit = irradiance > 0
            if self.shadows and lit.any():
                irradiance[lit] *= unoccluded(scene, X[lit] + SHADOW_OFFSET * n[lit], np.broadcast_to(d, n[lit].shape),
                                              DISTANT)
            shading += strength * irradiance
        return shading

    def parameters(self, poses: np.ndarray, scene_to_reference: np.ndarray | None = None) -> dict:
        """JSON-serialisable parameters; ``directions`` in the capture's reference frame, which
        ``scene_to_reference`` (4, 4; default identity) maps the scene frame to."""
        R = np.eye(3) if scene_to_reference is None else np.asarray(scene_to_reference)[:3, :3]
        return {
            "model": "room",
            "ambient": float(self.ambient),
            "strengths": [float(s) for s, _ in self.lights],
            "directions": (self.directions() @ R.T).tolist(),
            "shadows": bool(self.shadows),
            "formula": "albedo * (ambient + sum_k strengths[k] * visible_k * max(0, n.directions[k])), "
                       "reference frame",
        }


#: Hand-held light of the static-camera renders: its distance (m) from the camera's optical axis.
HANDHELD_RADIUS = (0.3, 0.5)
GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def handheld_offsets(frames: int, radius=HANDHELD_RADIUS) -> np.ndarray:
    """(frames, 3) positions (m, camera frame) of a light moved by hand around a fixed camera.

    In the camera's plane (z = 0), at azimuths a golden angle (137.5 deg) apart, so any first k
    frames spread around the camera; the distance from the optical axis runs from ``radius[0]``
    to ``radius[1]`` and back (one cycle every 5 frames).
    """
    i = np.arange(int(frames))
    r = radius[0] + (radius[1] - radius[0]) * 0.5 * (1.0 - np.cos(2 * np.pi * i / 5))
    angle = GOLDEN_ANGLE * i
    return np.stack([r * np.cos(angle), r * np.sin(angle), np.zeros_like(r)], axis=1)


def handheld_lights(frames: int, distance: float = 0.6, radius=HANDHELD_RADIUS, shadows: bool = True) -> list:
    """One :class:`PointLight` per frame at :func:`handheld_offsets` (fixed camera: camera frame =
    reference frame), with cast shadows (unless ``shadows`` is False) and the LED's ambient; one
    intensity for all, giving a frontal surface at the object centre the LED's irradiance from the
    middle radius."""
    middle = 0.5 * (radius[0] + radius[1])
    intensity = LED_FRONTAL_IRRADIANCE * (distance**2 + middle**2)
    offsets = handheld_offsets(frames, radius)
    return [PointLight(offset=tuple(float(v) for v in p), intensity=intensity, shadows=bool(shadows)) for p in offsets]


def handheld_parameters(lights: list) -> dict:
    """JSON-serialisable parameters of :func:`handheld_lights` (``positions`` (n, 3) m, reference frame)."""
    return {
        "model": "point",
        "positions": [list(light.offset) for light in lights],
        "intensity": float(lights[0].intensity),
        "ambient": float(lights[0].ambient),
        "falloff": "inverse-square",
        "shadows": bool(lights[0].shadows),
        "formula": "albedo * (ambient + intensity * visible * max(0, n.l) / r^2), l toward positions[i]",
    }


def make_light(light: str, distance: float = 0.6):
    """The light model named ``light`` ("led", "directional" or "room"), LED scaled for ``distance`` m."""
    if light == "led":
        return PointLight(intensity=LED_FRONTAL_IRRADIANCE * distance**2)
    if light == "directional":
        return DirectionalLight()
    if light == "room":
        return RoomLight()
    raise ValueError(f"unknown light {light!r}; choose one of {list(LIGHTS)}")
