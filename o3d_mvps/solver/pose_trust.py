"""What a frame's pose answers to besides its photometric energy (issue #32, item 1).

The photometric energy of one frame is a poor judge of its pose on its own: its minimum is
biased by everything the model does not explain (shadows, a light model that does not fit the
scene, silhouette pixels, a depth still blurred on a coarse level), and a pose walks along the
valley where a rotation about the object trades off against a translation. On a render with
exact given poses the pose step moved frames 1-4 mm / 0.1-0.45 deg away from them (320x240,
6 frames, the true depth held fixed). Two checks that the photometric energy cannot talk
round:

- the frame's **own sensor depth**: the reference surface moved into frame i must agree with
  the depth frame i measured there, ``d(p) = Z_i(p) - D_i(pi(X_i(p)))`` (metres, bilinear
  sample of the (h, w) sensor depth), robust Cauchy with scale ``depth_scale``;
- a **prior towards given poses** with the trust the user states (``trust`` (metres, radians):
  ``E = prior_weight / 2 (|dt|^2 / s_t^2 + |dw|^2 / s_r^2)`` with ``(dt, dw)`` the twist from the
  given pose).

A pose update is accepted only if the frame's photometric energy plus these terms
(:meth:`PoseAnchors.frame_energy`) does not rise; :class:`PoseLog` counts what was rejected and
why. Both terms are in the photometric energy's units: a depth residual of one ``depth_scale``
costs what a colour pixel at one Cauchy scale does (three channels), and a move of one standard
deviation of the prior costs :data:`PRIOR_SHARE` of what the frame's own images charge for it
(their Gauss-Newton curvature along the six twist axes at the trust radius, averaged): a prior
in proportion to the evidence, which holds the directions the images barely see (a rotation
about the object with the matching translation) and yields along those they do. The prior also
enters the pose step's and the joint step's Gauss-Newton systems, so neither proposes a slide
along the weak directions that the acceptance would then refuse whole. A depth pixel counts once however many
colour pixels sample it (on the 640x480 bunny, counted at every colour pixel, the depth check held
odometry poses 3.5 mm from the truth, mean, where the images alone take them to 0.64 mm).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model import se3
from ..model.robust import cauchy, robust_scale
from ..model.warping import sample_bilinear
from .device import to_host

#: how far given poses are trusted by default (metres, radians): a registration of the same
#: capture that lands within 2 mm and 0.15 deg of good given poses is typical (issue #32)
DEFAULT_POSE_TRUST = (0.002, float(np.radians(0.2)))
#: the smallest Cauchy scale of the depth residuals (metres): 1 mm sensor quantisation
MIN_DEPTH_SCALE = 0.001
#: a one-sigma move of a given pose costs this share of what the frame's images charge for it
#: (their curvature along the six twist axes, averaged at the trust radius)
PRIOR_SHARE = 0.1


@dataclass
class PoseAnchors:
    """The frames' sensor depths (n, h, w) metres (0: none) with their intrinsics (3, 3), and,
    for given poses, the poses (n, 4, 4) and their trust (metres, radians); scale_factor: colour
    pixels per depth pixel along a side; per level,
    :meth:`calibrate` sets the weights (``depth_weight`` per pixel, ``prior_weight``)."""

    sensor_depths: np.ndarray
    depth_K: np.ndarray
    given: np.ndarray | None = None
    trust: tuple[float, float] | None = None
    scale_factor: int = 1
    depth_scale: float = MIN_DEPTH_SCALE
    depth_weight: float = 0.0
    prior_weight: float | np.ndarray = 0.0

    def __post_init__(self):
        self.sensor_depths = np.asarray(self.sensor_depths, dtype=np.float32)
        self._measured = (self.sensor_depths > 0).astype(np.float32)

    def depth_residuals(self, i: int, pose: np.ndarray, points_ref: np.ndarray, usable: np.ndarray) -> np.ndarray:
        """d (M,) metres at the usable reference points (N, 3) moved by ``pose`` into frame i,
        where frame i measured a depth (bilinear samples whose four neighbours all measured)."""
        P = to_host(points_ref)[to_host(usable)]
        X = P @ pose[:3, :3].T + pose[:3, 3]
        Z = X[:, 2]
        K, depth = self.depth_K, self.sensor_depths[i]
        h, w = depth.shape
        with np.errstate(divide="ignore", invalid="ignore"):
            su = K[0, 0] * X[:, 0] / Z + K[0, 2]
            sv = K[1, 1] * X[:, 1] / Z + K[1, 2]
        inside = (Z > 0) & (su >= 0) & (su <= w - 1) & (sv >= 0) & (sv <= h - 1)
        su, sv = su[inside], sv[inside]
        d = sample_bilinear(depth[..., None], su, sv)[:, 0]
        measured = sample_bilinear(self._measured[i][..., None], su, sv)[:, 0] > 0.999
        return (Z[inside] - d)[measured]

    def depth_energy(self, i: int, pose: np.ndarray, points_ref: np.ndarray, usable: np.ndarray) -> float:
        """The frame's geometric energy: ``depth_weight`` x the Cauchy energy of its depth residuals."""
        if self.depth_weight == 0.0:
            return 0.0
        d = self.depth_residuals(i, pose, points_ref, usable)
        return self.depth_weight * float(cauchy(d, self.depth_scale).sum())  # NumPy: small arrays

    def twist_from_given(self, i: int, pose: np.ndarray) -> np.ndarray:
        """(6,) the twist xi = (v, w) with ``pose = exp(xi) given_i``."""
        return se3.log(pose @ np.linalg.inv(self.given[i]))

    def trust_radius(self) -> np.ndarray:
        """(6,) the trust along the twist axes (metres x 3, radians x 3)."""
        s_t, s_r = self.trust
        return np.array([s_t] * 3 + [s_r] * 3)

    def prior_precision(self, i: int) -> np.ndarray:
        """(6,) frame i's prior's diagonal curvature in energy units (0 without given poses)."""
        weight = float(np.asarray(self.prior_weight)[i] if np.ndim(self.prior_weight) else self.prior_weight)
        if self.given is None or self.trust is None or weight == 0.0:
            return np.zeros(6)
        return weight / self.trust_radius() ** 2

    def prior_energy(self, i: int, pose: np.ndarray) -> float:
        """The prior's energy of frame i at ``pose`` (0 without given poses)."""
        precision = self.prior_precision(i)
        if not precision.any() or i == 0:
            return 0.0
        xi = self.twist_from_given(i, pose)
        return 0.5 * float(xi @ (precision * xi))

    def prior_system(self, i: int, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(H (6, 6), g (6,)): the prior's Gauss-Newton terms for a left update exp(xi) pose, or None."""
        precision = self.prior_precision(i)
        if not precision.any() or i == 0:
            return None
        return np.diag(precision), precision * self.twist_from_given(i, pose)

    def frame_energy(self, i: int, pose: np.ndarray, points_ref: np.ndarray, usable: np.ndarray) -> float:
        """Geometric plus prior energy of frame i at ``pose`` (add its photometric energy to judge a pose)."""
        return self.depth_energy(i, pose, points_ref, usable) + self.prior_energy(i, pose)

    def calibrate(self, photometric_scale: float, poses: np.ndarray, points_ref: np.ndarray,
                  usable: np.ndarray, information: np.ndarray, footprint: float = 1.0) -> None:
        """Set the level's weights: the depth residuals' scale from those of the current ``poses``
        (n, 4, 4) (1.4826 MAD over frames 1.., at least :data:`MIN_DEPTH_SCALE`), a depth
        measurement at that scale weighing like a colour pixel (3 channels) at
        ``photometric_scale`` -- spread over the ``footprint`` level pixels that sample one depth
        pixel ((SF / 2^level)^2, at least 1) -- and, per frame, the prior's one-sigma cost
        :data:`PRIOR_SHARE` x what the frame's images charge for a move of one trust radius,
        averaged over the six twist axes: ``information`` (n, 6), their curvature along the
        axes (:func:`o3d_mvps.solver.pose.pose_information`). usable (n, N)."""
        residuals = [self.depth_residuals(i, poses[i], points_ref, usable[i]) for i in range(1, len(poses))]
        r = np.concatenate(residuals) if residuals else np.zeros(0)
        self.depth_scale = max(MIN_DEPTH_SCALE, robust_scale(r[None, :, None], np.ones((1, r.size), bool))
                               if r.size else MIN_DEPTH_SCALE)
        self.depth_weight = 3.0 * photometric_scale**2 / self.depth_scale**2 / max(1.0, footprint)
        if self.trust is not None:
            self.prior_weight = PRIOR_SHARE * (np.asarray(information) * self.trust_radius() ** 2).mean(axis=1)


@dataclass
class PoseLog:
    """Per frame, the pose updates rejected and why (a count per reason)."""

    rejected: list = field(default_factory=list)

    def reject(self, i: int, reason: str) -> None:
        while len(self.rejected) <= i:
            self.rejected.append({})
        self.rejected[i][reason] = self.rejected[i].get(reason, 0) + 1

    def report(self, start: np.ndarray, final: np.ndarray, trust: tuple | None, frames: list) -> list[dict]:
        """info["pose_updates"]: per frame 1.. (``frames``: the capture's index of each) how far
        its camera moved from ``start`` (n, 4, 4) to ``final`` (:func:`~o3d_mvps.model.se3.camera_movement`), how many updates were rejected,
        and a note saying why; trust: the given poses' (metres, radians), None for poses refined
        freely (registered)."""
        rows = []
        kind = ("registered pose, refined freely" if trust is None else
                f"given pose, trusted to {1e3 * trust[0]:g} mm and {np.degrees(trust[1]):g} deg")
        for i in range(1, len(final)):
            degrees, metres = se3.camera_movement(start[i], final[i])
            reasons = self.rejected[i] if i < len(self.rejected) else {}
            note = kind + (
                "; rejected: " + ", ".join(f"{n} x {r}" for r, n in sorted(reasons.items())) if reasons else "")
            rows.append({"frame": int(frames[i]), "moved_mm": round(1e3 * metres, 3), "moved_deg": round(degrees, 4),
                         "rejected_updates": int(sum(reasons.values())), "note": note})
        return rows
