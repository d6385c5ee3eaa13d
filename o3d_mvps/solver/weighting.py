"""How the solver balances the photometric evidence against the sensor depth.

Two pieces, both set from the data (README/docs "Fidelity"):

- :func:`tie_low_frequencies`: the depth's low frequencies are the sensor's. Shading informs the
  normals, and integrating a normal field turns a small bias (a light model that does not fit a
  near light's falloff, a camera response that is not quite linear) into a bend that grows with
  the object's width (a bowl): the photometric data are weak on the low frequencies where the
  sensor, averaged over many pixels, is strong (Nehab et al. 2005, "Efficiently combining
  positions and normals for precise 3D geometry", take the low frequencies from positions and the
  high ones from normals for the same reason).
- :func:`evidence_weights`: per pixel, how well the frames' shading pins the normal down (the
  conditioning of the stacked shading system against the image noise); the smoothness leans in
  where it is weak (dark albedo, few frames, little light diversity), so colour texture and noise
  do not become relief; with the LED, :func:`albedo_step_weights` also counts the albedo's
  steps (:func:`albedo_step_factor`), whose pixels each warped frame mixes.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..model.arrays import array_module, contiguous, fused
from ..model.resampling import fill_nearest_valid
from .device import kernels_for
from .lighting import LEDLight, device_light_state
from .smoothness import sensor_roughness

#: the least width (Gaussian sigma, depth pixels) of the low-pass that ties the depth to the
#: sensor: at 4 the tie leaves features narrower than ~16 depth pixels to the photometric terms
LOWPASS_MIN_SIGMA = 4.0
#: the sensor noise the tie may pass on, relative to the depth (per mille): the low-pass is
#: widened until the sensor's noise, averaged by it, falls below this
LOWPASS_NOISE_PER_MILLE = 0.1


def lowpass_sigma(z0: np.ndarray, mask: np.ndarray, scale_factor: int) -> float:
    """Gaussian sigma (depth pixels) of the sensor tie: the least width at which the sensor depth
    z0 (h, w) metres, averaged, is as quiet as :data:`LOWPASS_NOISE_PER_MILLE` of its depth,
    not below :data:`LOWPASS_MIN_SIGMA`. A Gaussian of sigma s averages white noise of standard
    deviation sigma_n down to sigma_n / (2 sqrt(pi) s); sigma_n is the sensor's roughness
    (:func:`.smoothness.sensor_roughness`); mask (H, W) bool the colour-resolution object mask."""
    noise = sensor_roughness(z0, mask, scale_factor)
    depth = float(np.median(z0[z0 > 0])) if (z0 > 0).any() else 1.0
    needed = noise / (2.0 * np.sqrt(np.pi) * LOWPASS_NOISE_PER_MILLE * 1e-3 * depth)
    return max(LOWPASS_MIN_SIGMA, float(needed))


def _masked_blur(values: np.ndarray, weights: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised Gaussian blur (H, W) of ``values`` over the pixels' ``weights`` (H, W) >= 0."""
    num = cv2.GaussianBlur(values * weights, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    den = cv2.GaussianBlur(weights, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
    return num / np.maximum(den, 1e-12)


#: relative depth range over a depth pixel's 3 x 3 neighbourhood above which the sensor depth is
#: taken to step there (an occluding edge), and its pixels are left out of the tie's average
EDGE_STEP = 0.02
#: differences from the sensor beyond this many robust standard deviations (1.4826 MAD) are left
#: out of the tie's average (edges the sensor and the refinement place a pixel apart)
OUTLIER_SIGMAS = 4.0


def tie_low_frequencies(z: np.ndarray, mask: np.ndarray, z0: np.ndarray, sigma: float) -> np.ndarray:
    """z (H, W) metres with its low frequencies replaced by the sensor's: ``z - G * (z - z0')``,
    applied twice (one pass leaves a curved bowl's sigma^2 curvature offset), over the mask
    (H, W) bool; G a Gaussian of ``sigma`` depth pixels, normalised over the pixels it averages;
    z0' the sensor depth z0 (h, w) metres (0 = missing) bilinearly resampled to z's grid. The
    average leaves out pixels without sensor depth, next to a step of the sensor depth (range
    over 3 x 3 depth pixels above :data:`EDGE_STEP` of the depth) and differences beyond
    :data:`OUTLIER_SIGMAS` robust standard deviations: across an occluding edge the difference
    is the edge's misplacement, not a bend, and blurred it moved the surfaces on both sides (a
    room scene's RMSE 3.5 -> 8.8 mm). Outside the mask z is returned unchanged."""
    H, W = z.shape
    valid = z0 > 0
    filled = fill_nearest_valid(z0.astype(np.float64), valid)
    kernel = np.ones((3, 3), np.uint8)
    flat = valid & (cv2.dilate(filled, kernel) - cv2.erode(filled, kernel) <= EDGE_STEP * filled)
    z0_level = cv2.resize(filled, (W, H), interpolation=cv2.INTER_LINEAR)
    flat_level = cv2.resize(flat.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST).astype(bool)
    use = mask & flat_level
    if not use.any():
        return z
    difference = z - z0_level
    centre = float(np.median(difference[use]))
    spread = 1.4826 * float(np.median(np.abs(difference[use] - centre)))
    use &= np.abs(difference - centre) <= OUTLIER_SIGMAS * spread + 1e-6 * z0_level
    weights = use.astype(np.float64)
    sigma_level = max(0.5, sigma * W / z0.shape[1])
    tied = z
    for _ in range(2):  # twice: removes G (2 - G) of the difference, 1 - O(f^4) at low frequencies f
        tied = tied - _masked_blur(np.where(use, tied - z0_level, 0.0), weights, sigma_level)
    return np.where(mask, tied, z)


#: the most :func:`evidence_weights` multiplies a pixel's smoothness by
EVIDENCE_MAX_WEIGHT = 100.0


def normal_evidence(light_model, est, ev, points: np.ndarray) -> np.ndarray:
    """How well the frames' shading determines each pixel's normal: (N,) the smaller eigenvalue
    (intensity^2 per radian^2) of the shading system's information on the normal's two tangent
    directions, the albedo projected out.

    Frame i shades pixel p with ``rho_c (c_i + <L_i, n>)`` (the light model's frozen field
    :meth:`~.lighting.FrameFields.fields`, L_i (3,) or per pixel); over the frames that see p,
    ``G = sum_i sum_c rho_c^2 L_i L_i^T`` less its part along the albedo's direction
    ``v v^T / d`` (v = sum rho^2 s_i L_i, d = sum rho^2 s_i^2), restricted to the plane normal to
    n. Small where the albedo is dark, few frames see p, or their lights hardly differ; the image
    noise sigma makes the normal's standard deviation about ``sigma / sqrt(evidence)`` radians.
    est: the :class:`~.problem.Estimate`; ev its :class:`~.problem.Evaluation`; points (N, 3)."""
    xp = array_module(ev.normals)
    normals = ev.normals
    N = normals.shape[0]
    if isinstance(light_model, LEDLight):  # one compiled pass (a launch on a GPU), the fields formed per pixel
        state = device_light_state(light_model, est.lights, est.poses, points)
        G6, v, d = xp.empty((6, N)), xp.empty((3, N)), xp.empty(N)
        kernels_for(points).led_evidence_sums(ev.usable, contiguous(est.albedo, np.float64), ev.shading,
                                              state.intensities, contiguous(normals, np.float64),
                                              contiguous(points, np.float64), state.positions, G6, v, d)
        return _tangent_min_eigenvalue(normals[:, 0], normals[:, 1], normals[:, 2], *G6, *v, d)
    # SH and room light: one field per frame, L (n, 3); the sums over the frames as products with
    # (n, 9) and (n, 3)
    _, L = light_model.fields(est.lights, normals, points, est.poses)
    L = xp.asarray(L, dtype=np.float64)
    u = ev.usable * (est.albedo ** 2).sum(axis=1)  # (n, N)
    us = u * ev.shading
    G = (u.T.astype(np.float64) @ (L[:, :, None] * L[:, None, :]).reshape(-1, 9)).reshape(N, 3, 3)
    v = us.T.astype(np.float64) @ L
    d = (us * ev.shading).sum(axis=0)
    return _tangent_min_eigenvalue(normals[:, 0], normals[:, 1], normals[:, 2], G[:, 0, 0], G[:, 0, 1], G[:, 0, 2],
                                   G[:, 1, 1], G[:, 1, 2], G[:, 2, 2], v[:, 0], v[:, 1], v[:, 2], d)


@fused
def _tangent_min_eigenvalue(nx, ny, nz, g00, g01, g02, g11, g12, g22, v0, v1, v2, d):
    """The smaller eigenvalue (N,) of ``G - v v^T / d`` (G symmetric, its six entries gjk; v and d
    as in :func:`normal_evidence`; each (N,)) restricted to the plane normal to the unit normal
    (nx, ny, nz), in closed form: tangents t1 = n x a (a the x axis, or the y axis where n is
    near the x axis) and t2 = n x t1. Elementwise: one kernel on a GPU."""
    xp = array_module(nx)
    d = xp.maximum(d, 1e-30)
    g00, g01, g02 = g00 - v0 * v0 / d, g01 - v0 * v1 / d, g02 - v0 * v2 / d
    g11, g12, g22 = g11 - v1 * v1 / d, g12 - v1 * v2 / d, g22 - v2 * v2 / d
    near_x = xp.abs(nx) >= 0.9  # n x (1, 0, 0) = (0, nz, -ny); n x (0, 1, 0) = (-nz, 0, nx)
    t1x, t1y, t1z = xp.where(near_x, -nz, 0.0), xp.where(near_x, 0.0, nz), xp.where(near_x, nx, -ny)
    norm = xp.sqrt(t1x * t1x + t1y * t1y + t1z * t1z)
    t1x, t1y, t1z = t1x / norm, t1y / norm, t1z / norm
    t2x, t2y, t2z = ny * t1z - nz * t1y, nz * t1x - nx * t1z, nx * t1y - ny * t1x
    a = (g00 * t1x * t1x + g11 * t1y * t1y + g22 * t1z * t1z
         + 2.0 * (g01 * t1x * t1y + g02 * t1x * t1z + g12 * t1y * t1z))
    c = (g00 * t2x * t2x + g11 * t2y * t2y + g22 * t2z * t2z
         + 2.0 * (g01 * t2x * t2y + g02 * t2x * t2z + g12 * t2y * t2z))
    b = (g00 * t1x * t2x + g11 * t1y * t2y + g22 * t1z * t2z + g01 * (t1x * t2y + t1y * t2x)
         + g02 * (t1x * t2z + t1z * t2x) + g12 * (t1y * t2z + t1z * t2y))
    return xp.maximum(0.5 * (a + c) - xp.sqrt(0.25 * (a - c) * (a - c) + b * b), 0.0)


def evidence_weights(evidence: np.ndarray) -> np.ndarray:
    """Per-pixel smoothness weights (N,) >= 1 from :func:`normal_evidence` (N,): the median
    evidence over the pixel's own, in [1, :data:`EVIDENCE_MAX_WEIGHT`]. A pixel whose shading
    says k times less about its normal than the typical pixel gets k times the smoothness, so
    the smoothing's balance against the image noise is the typical pixel's everywhere; pixels at
    or above the median keep the plain weight."""
    xp = array_module(evidence)
    reference = float(xp.median(evidence))
    if not reference > 0:
        return xp.ones_like(evidence)
    return xp.clip(reference / xp.maximum(evidence, reference / EVIDENCE_MAX_WEIGHT), 1.0, EVIDENCE_MAX_WEIGHT)


#: the normal precision (degrees) below which the shading is trusted over the smoothness by
#: :func:`absolute_evidence_weights`: a photometric normal's standard deviation
#: ``noise / sqrt(evidence)`` above it makes the pixel lean on the smoothness. On a speckled
#: LED-lit bunny with the D415-like sensor the dark speckles' shading gives 10-20 degrees and the
#: pale stone's 3-4; on the accuracy benchmark's LED bunny (Gaussian noise) the median pixel's 1,
#: the 1st percentile's 4. 1.5 measured: the speckles' normals 13.1 deg off (1: 12.6, 2: 13.9),
#: the 640x480 bunny 2.30 deg / 0.897 mm (1: 2.33 / 0.919; without weights 2.32 / 0.895)
NORMAL_PRECISION_DEG = 1.5


def absolute_evidence_weights(evidence: np.ndarray, noise: float, ceiling: float,
                              precision_deg: float = NORMAL_PRECISION_DEG) -> np.ndarray:
    """Per-pixel smoothness weights (N,) in [1, ``ceiling``] from :func:`normal_evidence` (N,)
    against an absolute scale: ``(noise / precision)^2 / evidence``, the variance of the pixel's
    photometric normal (``noise`` the image residuals' standard deviation, intensity) over that
    of a normal known to ``precision_deg``. Pixels whose shading pins the normal down better keep
    the plain weight, whatever the others do (the LED's rule: unlike :func:`evidence_weights`,
    a capture whose pixels are all well lit is left alone, and a noisy one is smoothed
    throughout); ``ceiling``: the ratio of the sensor's own smoothness
    (:func:`.smoothness.auto_smoothness`) to the light model's, so a pixel without evidence
    is as smooth as the sensor's surface."""
    reference = (float(noise) / np.radians(precision_deg)) ** 2
    ceiling = max(1.0, float(ceiling))
    return _clipped_ratio(evidence, reference, ceiling)


@fused
def _clipped_ratio(evidence, reference, ceiling):
    """``clip(reference / max(evidence, reference / ceiling), 1, ceiling)`` elementwise (as
    ``np.clip``: a NaN stays NaN); one kernel on a GPU."""
    xp = array_module(evidence)
    return xp.minimum(xp.maximum(reference / xp.maximum(evidence, reference / ceiling), 1.0), ceiling)


#: the sub-pixel misplacement (pixels) of an albedo step between the frames that
#: :func:`albedo_step_factor` counts: each frame point-samples the surface at its own points, so
#: warped to the reference by bilinear sampling a step lands anywhere within a pixel (a uniform
#: offset in [0, 1) has mean 0.5). Measured on the speckled LED bunny (320x240, 10 frames): the
#: darkest quarter's normals 10.68 deg off at 0.3, 10.28 at 0.5, 11.07 at 1.0 (without: 13.13)
ALBEDO_STEP_PIXELS = 0.5


def albedo_step_factor(albedo, grid, shading, usable, noise: float, step_pixels: float = ALBEDO_STEP_PIXELS):
    """How much noisier (N,) >= 1 than the image noise each pixel's shading is next to a step of
    the albedo: ``1 + (k drho s / noise)^2``, drho the largest change of the mean albedo to the
    pixel's four neighbours (the grid's stencil), s its mean shading over the frames that see
    it, k = ``step_pixels``. A frame samples a step at other points than the reference does, so
    warped to the reference it mixes the step's two sides in its own proportion at the pixels
    beside it: an error of about ``k drho s`` in each frame that the shading system reads as
    relief (a speckled stone's speckle rims, 3-4 pixels wide: all rim). albedo (N, 3); grid:
    the level's :class:`~o3d_mvps.model.normals.MaskedGrid` (on the albedo's device); shading,
    usable (n, N); noise: the residuals' standard deviation (intensity)."""
    xp = array_module(albedo)
    rho = albedo.mean(axis=1)
    seen = usable.sum(axis=0)
    s = (shading * usable).sum(axis=0)
    return _step_factor(rho, rho[grid.fwd_u], rho[grid.bwd_u], rho[grid.fwd_v], rho[grid.bwd_v], grid.wf_u, grid.wb_u,
                        grid.wf_v, grid.wb_v, s, xp.maximum(seen, 1), step_pixels / max(float(noise), 1e-12))


@fused
def _step_factor(rho, fu, bu, fv, bv, wf_u, wb_u, wf_v, wb_v, shading_sum, seen, scale):
    """:func:`albedo_step_factor` elementwise (each (N,) but ``scale`` = k / noise): the largest
    change of rho to the neighbours fu, bu, fv, bv whose stencil weight is positive, times the
    mean shading ``shading_sum / seen``. One kernel on a GPU."""
    xp = array_module(rho)
    step = xp.maximum(xp.maximum(xp.where(wf_u > 0, xp.abs(fu - rho), 0.0), xp.where(wb_u > 0, xp.abs(rho - bu), 0.0)),
                      xp.maximum(xp.where(wf_v > 0, xp.abs(fv - rho), 0.0), xp.where(wb_v > 0, xp.abs(rho - bv), 0.0)))
    x = scale * step * shading_sum / seen
    return 1.0 + x * x


def leans_on_smoothness(weights) -> bool:
    """Whether the typical pixel leans on the smoothness: the median of :func:`absolute_evidence_weights`'s
    ``weights`` (N,) above 1 (the shading pins the median pixel's normal less well than
    :data:`NORMAL_PRECISION_DEG`). Only such captures count the albedo's steps
    (:func:`albedo_step_weights`)."""
    return float(array_module(weights).median(weights)) > 1.0


def albedo_step_weights(weights, evidence, steps, noise: float, ceiling: float):
    """The LED's smoothness weights (N,) with the albedo's steps counted, for a capture that
    :func:`leans_on_smoothness`: where a pixel's weight is above 1, the weight of its evidence
    (N,) divided by :func:`albedo_step_factor`'s ``steps`` (N,); elsewhere ``weights``
    unchanged. On the speckled LED bunny (320x240, 10 frames, D415-like sensor; the
    median weight 130) the darkest albedo quarter's normals 13.1 -> 10.3 deg; on the accuracy
    benchmark's LED bunny (640x480, SF 4, 20 frames, Gaussian noise; median weight 1, its
    patches' rims 10-15 % of the pixels) counting the steps cost 0.14 deg (2.30 -> 2.44) where
    the median was not asked. noise, ceiling: as for :func:`absolute_evidence_weights`."""
    xp = array_module(weights)
    return xp.where(weights > 1.0, absolute_evidence_weights(evidence / steps, noise, ceiling), weights)
