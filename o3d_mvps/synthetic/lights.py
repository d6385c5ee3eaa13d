"""Light models of the renderer: a point LED moving with the camera, and an SH-exact directional light."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from ..model.shading import led_vectors
from .scene import apply_matrix

LIGHTS = ("led", "directional")

LED_OFFSET = (0.03, -0.02, 0.0)  # metres, camera frame
LED_FRONTAL_IRRADIANCE = 0.85  # irradiance of a frontal surface at the object centre
LED_AMBIENT = 0.03
SHADOW_OFFSET = 1e-4  # metres along the normal

SH_AMBIENT = 0.5
SH_STRENGTH = 0.45  # < SH_AMBIENT: shading stays >= 0.05 for any normal
SH_DIRECTION = (0.35, -0.3, -1.0)  # toward the light, camera frame (normalised)


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
        """Shading (N,) of the frame's hit pixels (N = frame.mask.sum())."""
        X = frame.points[frame.mask]  # camera frame
        n = frame.normals[frame.mask]
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
        rays = o3d.core.Tensor(np.hstack([origin, direction]).astype(np.float32))
        occluded = scene.raycaster.test_occlusions(rays, tnear=0.0, tfar=1.0).numpy()
        visible[lit] = ~occluded.astype(bool)
        return visible

    def parameters(self, poses: np.ndarray) -> dict:
        """JSON-serialisable parameters; ``positions`` (n, 3) light centres in reference coordinates."""
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
        return l[0] + apply_matrix(l[None, 1:], frame.normals[frame.mask])[:, 0]

    def parameters(self, poses: np.ndarray) -> dict:
        """JSON-serialisable parameters; ``sh`` (n, 4) per-frame SH vectors in reference coordinates."""
        return {
            "model": "directional",
            "direction": [float(v) for v in self.sh_camera()[1:] / self.strength],
            "ambient": float(self.ambient),
            "strength": float(self.strength),
            "sh": [self.sh_reference(T).tolist() for T in poses],
            "formula": "albedo * <sh[i], [1, n_x, n_y, n_z]>, n unit normal in reference coordinates",
        }


def make_light(light: str, distance: float = 0.6):
    """The light model named ``light`` ("led" or "directional"), LED scaled for ``distance`` m."""
    if light == "led":
        return PointLight(intensity=LED_FRONTAL_IRRADIANCE * distance**2)
    if light == "directional":
        return DirectionalLight()
    raise ValueError(f"unknown light {light!r}; choose one of {list(LIGHTS)}")
