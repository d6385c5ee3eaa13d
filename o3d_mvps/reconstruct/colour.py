"""Surface colours from the reference views' albedos: each point a blend of the views that see it.

A view sees a point when its depth there is within 1 % of the point's; its score is the facing
cosine times the silhouette ramp of :func:`~.fusion.pixel_weights`, and the views blend with
weights score**BLEND_POWER, so the best view dominates and seams between views fade where two
see the point about equally well. Each refinement fixes its albedo only up to a factor: the
views are first brought to a common scale (:func:`albedo_gains`), and every colour shares one
white level (a high percentile of the mesh vertices' colours) before sRGB encoding.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..colour import linear_to_srgb
from ..model.camera import project, transform
from ..model.warping import sample_bilinear
from .fusion import pixel_weights

#: Relative depth margin within which a view's depth confirms that it sees a point.
VISIBILITY_TOLERANCE = 0.01
#: Exponent of the view scores in the blend (seams fade over the band of comparable scores).
BLEND_POWER = 4.0
#: Percentile of the vertices' linear colours mapped to white.
WHITE_PERCENTILE = 99.5
#: Points coloured at once (bounds the (views, points, 3) sample arrays).
POINTS_PER_CHUNK = 1 << 17


def albedo_gains(samples: np.ndarray, weights: np.ndarray, rounds: int = 3) -> np.ndarray:
    """Gains (k,) that bring k views' albedo samples (k, n, 3) to a common scale: the median ratio
    of the weighted blend to each view's luminance over points several views see (weights (k, n))."""
    k = len(samples)
    gains = np.ones(k)
    luminance = samples.mean(axis=2)
    for _ in range(rounds):  # blend, rescale each view to the blend, repeat
        blend = (weights * gains[:, None] * luminance).sum(0) / np.maximum(weights.sum(0), 1e-30)
        for j in range(k):
            shared = (weights[j] > 0) & ((weights > 0).sum(0) > 1) & (luminance[j] > 1e-4)
            if shared.sum() >= 10:
                gains[j] = np.median(blend[shared] / luminance[j][shared])
    return gains


class ViewColours:
    """Colours of surface points from a reconstruction's views (:class:`~.views.ViewResult`).

    The views' gains and the white level are fixed on the mesh vertices ``positions``,
    ``normals`` (n, 3) world frame; :meth:`colours` then colours any surface points alike.
    """

    def __init__(self, views: list, edge_px: float, positions: np.ndarray, normals: np.ndarray):
        self.views = views
        self.ramps = [pixel_weights(v.depth, v.mask, v.K, 1.0, edge_px) for v in views]
        samples, weights = self._samples(positions, normals)
        self.gains = albedo_gains(samples, weights)
        self.white = 1.0
        linear, seen = self._blend(samples, weights)
        if seen.any():
            self.white = max(float(np.percentile(linear[seen], WHITE_PERCENTILE)), 1e-6)

    def colours(self, positions: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """sRGB colours (n, 3) in [0, 1] of surface points (n, 3) with normals (n, 3), and which
        points (n,) some view sees (the others are 0)."""
        srgb, seen = np.zeros((len(positions), 3)), np.zeros(len(positions), dtype=bool)
        for start in range(0, len(positions), POINTS_PER_CHUNK):
            chunk = slice(start, start + POINTS_PER_CHUNK)
            linear, seen[chunk] = self._blend(*self._samples(positions[chunk], normals[chunk]))
            srgb[chunk] = linear_to_srgb(np.clip(linear / self.white, 0.0, 1.0))
        return srgb, seen

    def vertex_colours(self, positions: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """sRGB colours (n, 3) of mesh vertices; vertices no view sees take their nearest seen neighbour's."""
        srgb, seen = self.colours(positions, normals)
        if seen.any() and not seen.all():
            _, nearest = cKDTree(positions[seen]).query(positions[~seen])
            srgb[~seen] = srgb[seen][nearest]
        return srgb

    def _samples(self, positions: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Albedo samples (k, n, 3) linear RGB and blend weights (k, n) (0 where a view does not see a point)."""
        k, n = len(self.views), len(positions)
        samples, weights = np.zeros((k, n, 3), dtype=np.float32), np.zeros((k, n))
        for j, (view, ramp) in enumerate(zip(self.views, self.ramps)):
            q = transform(view.world_to_camera, positions)
            u, v, z = project(q, view.K)
            H, W = view.depth.shape
            with np.errstate(invalid="ignore"):
                inside = (z > 0) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
            iu, iv = np.rint(np.where(inside, u, 0)).astype(int), np.rint(np.where(inside, v, 0)).astype(int)
            seen = inside & view.mask[iv, iu] & (np.abs(view.depth[iv, iu] - z) < VISIBILITY_TOLERANCE * z)
            facing = -np.einsum("ij,ij->i", normals @ view.world_to_camera[:3, :3].T, q) / np.linalg.norm(q, axis=1)
            weights[j] = np.where(seen, np.clip(facing, 0, 1) * ramp[iv, iu], 0.0) ** BLEND_POWER
            samples[j] = sample_bilinear(view.albedo, np.where(inside, u, 0), np.where(inside, v, 0))
        return samples, weights

    def _blend(self, samples: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Weighted blend (n, 3) linear RGB of the gain-corrected samples, and which points (n,) some view sees."""
        total = weights.sum(axis=0)
        blend = np.einsum("kn,knc->nc", weights * self.gains[:, None], samples) / np.maximum(total, 1e-30)[:, None]
        return blend, total > 0
