"""Sensor simulation: the 8-bit sRGB colour camera and the low-resolution, noisy, quantised depth
sensor, and the named sensor profiles (:data:`SENSORS`: the paper's Gaussian one, a D415-like one,
none) that the renderers take."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import scipy.ndimage as ndi

from ..colour import decode_table, linear_to_srgb
from ..model.resampling import resample_valid

COLOR_NOISE_SIGMA = 0.005
DEPTH_SCALE = 1000.0  # depth units per metre: 1 mm quantisation

SRGB8_TO_LINEAR = decode_table(8)  # (256,) float32: srgb_to_linear(k / 255)


def quantise_srgb8(
    linear: np.ndarray, rng: np.random.Generator | None = None, sigma: float = COLOR_NOISE_SIGMA
) -> np.ndarray:
    """8-bit sRGB camera: linear RGB (..., 3) -> float32 linear values exactly ``srgb_to_linear(k/255)``.

    Adds zero-mean Gaussian noise of std ``sigma`` (linear units) first when ``rng`` is given.
    """
    linear = np.asarray(linear, dtype=np.float64)
    if rng is not None:
        linear = linear + rng.normal(0.0, sigma, size=linear.shape)
    codes = np.rint(linear_to_srgb(np.clip(linear, 0.0, 1.0)).astype(np.float64) * 255.0).astype(np.uint8)
    return SRGB8_TO_LINEAR[codes]


def depth_noise_sigma(z: np.ndarray) -> np.ndarray:
    """Kinect-like depth noise std in metres of depth z in metres: ``1e-5 * z_mm^2`` mm."""
    z_mm = np.asarray(z, dtype=np.float64) * 1000.0
    return 1e-5 * z_mm**2 / 1000.0


def simulate_depth_sensor(
    depth: np.ndarray,
    scale_factor: int,
    rng: np.random.Generator | None = None,
    depth_scale: float | None = DEPTH_SCALE,
) -> np.ndarray:
    """Depth sensor: area-average (H, W) -> (h, w), Gaussian noise if ``rng``, quantise.

    Noise: ``depth_noise_sigma(z)`` on valid pixels. Quantisation: ``rint(z * depth_scale) /
    depth_scale`` (what a uint16 PNG at ``depth_scale`` units per metre stores); ``None``
    skips it. Returns float64 metres, 0 where invalid.
    """
    H, W = depth.shape
    # a block is valid only if every pixel in it hit the object (no mixed pixels)
    z, valid = resample_valid(depth, depth > 0, (H // scale_factor, W // scale_factor), min_valid_fraction=1.0)
    if rng is not None:
        z = z + valid * rng.normal(size=z.shape) * depth_noise_sigma(z)
    if depth_scale is not None:
        z = np.rint(z * depth_scale) / depth_scale
    return np.where(valid & (z > 0), z, 0.0)


# --------------------------------------------------------------------------------------
# Sensor profiles: what render_capture(sensor=...) and `o3d-mvps render --sensor` pick
# --------------------------------------------------------------------------------------
#: Names of the sensor profiles (:func:`make_sensor`).
SENSORS = ("gaussian", "d415", "none")

#: Depth discontinuity (m) within a 3x3 colour-pixel neighbourhood that makes a depth pixel an edge pixel.
EDGE_JUMP = 0.02


@dataclass(frozen=True)
class GaussianSensor:
    """The paper's protocol (Kinect-like, DESIGN.md section 5): depth area-averaged over SF x SF
    blocks (mixed blocks dropped), Gaussian noise ``sigma = 1e-5 z_mm^2`` mm, 1 mm steps; colour
    Gaussian noise of ``color_sigma`` (linear units), 8-bit sRGB. ``noise=False`` keeps the
    quantisation only (the "none" profile). ``color_samples`` 1: colour point-sampled at the
    pixel centres, as the paper's renders (:func:`~o3d_mvps.synthetic.render.render_frame`)."""

    noise: bool = True
    color_sigma: float = COLOR_NOISE_SIGMA
    color_samples: int = 1

    @property
    def name(self) -> str:
        return "gaussian" if self.noise else "none"

    def color(self, linear: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
        """(8-bit sRGB values linearised (H, W, 3) float32, per-frame parameters {})."""
        return quantise_srgb8(linear, rng if self.noise else None, self.color_sigma).astype(np.float32), {}

    def depth(self, depth: np.ndarray, scale_factor: int, rng: np.random.Generator) -> np.ndarray:
        """Low-resolution depth (H/SF, W/SF) float64 metres (0 = none) of depth (H, W) at colour resolution."""
        return simulate_depth_sensor(depth, scale_factor, rng if self.noise else None)

    def describe(self) -> dict:
        """JSON-ready parameters (written to capture.json's metadata.synthetic.sensor)."""
        if not self.noise:
            return {"name": "none", "depth": "area average, 1 mm steps", "color": "8-bit sRGB"}
        return {"name": "gaussian", "depth_sigma": "1e-5 * z_mm^2 mm", "color_sigma": self.color_sigma,
                "depth_scale": DEPTH_SCALE}


@dataclass(frozen=True)
class D415Sensor:
    """An active-stereo RGB-D camera like the Intel RealSense D415 (units in brackets).

    Depth, in this order (z from disparity ``d = f B / z``):

    1. area average over SF x SF colour pixels (as :class:`GaussianSensor`);
    2. flying pixels: a depth pixel whose footprint (grown by one colour pixel) straddles a jump
       of more than :data:`EDGE_JUMP` or the silhouette is, with probability ``flying_fraction``,
       a mixture ``z_fg + u (z_bg - z_fg)``, u ~ U(0, 1), of the nearest and farthest depth there
       (with nothing behind the silhouette: ``z_bg = z_fg + flying_reach``); else it is dropped
       when its block is not fully on a surface;
    3. disparity noise, white ``disparity_sigma`` plus a smooth field of RMS
       ``lowfreq_sigma`` (Gaussian-filtered white noise, filter sigma ``lowfreq_scale`` x the
       depth image width, a new field per frame): depth error ``z^2 sigma_d / (f B)``;
    4. speckle holes: ``hole_fraction`` of the valid pixels set to 0, in clusters (a smoothed
       random field, filter sigma ``hole_scale`` depth pixels, thresholded at that quantile);
    5. disparity quantisation to ``1 / subpixel_steps`` px: terraces ``z^2 / (f B steps)``
       (1.13 mm at 1 m, 0.41 mm at 0.6 m); then the capture's 1 mm uint16 units.

    Colour (a CMOS RGB camera): the radiance integrated over each pixel's area (``color_samples``
    x ``color_samples`` rays, a box filter: :func:`~o3d_mvps.synthetic.render.render_frame`),
    times the frame's exposure gain ``g`` (log-uniform in ``1 +- gain_drift``), shot noise
    (``full_well`` electrons at linear 1.0, Gaussian approximation of Poisson) and read noise
    (``read_noise`` electrons), white balance ``w_c`` on red and blue (log-uniform in
    ``1 +- white_balance_drift``, green 1), clipped, 8-bit sRGB.

    Sources: baseline 55 mm and depth HFOV 65 deg (D415 datasheet, Intel doc. 337029); f the
    640x360 depth mode's focal length ``320 / tan(32.5 deg)`` = 502 px; 1/32 px disparity
    steps (5 subpixel bits, Intel's D400 tuning guide) and RMS error ``z^2 subpixel / (f B)``
    with subpixel 0.08 at 1280x720 = 0.04 px here (Intel's depth-quality white paper: 1.45 mm
    at 1 m). Low-frequency error, flying pixels, holes and colour figures are typical values
    chosen to match what real captures show (DESIGN.md section 6: a few mm frame to frame,
    holes a few % of an object), not datasheet numbers.
    """

    baseline: float = 0.055  # m
    focal_px: float = 320.0 / np.tan(np.radians(32.5))  # px of the stereo matcher (640x360 mode)
    subpixel_steps: int = 32  # disparity steps per pixel
    disparity_sigma: float = 0.04  # px, white
    lowfreq_sigma: float = 0.08  # px RMS of the smooth field (2.9 mm at 1 m, 1.0 mm at 0.6 m)
    lowfreq_scale: float = 0.1  # filter sigma, fraction of the depth image width
    flying_fraction: float = 0.5  # of the edge pixels
    flying_reach: float = 0.1  # m behind the silhouette when nothing is behind it
    hole_fraction: float = 0.03  # of the valid depth pixels
    hole_scale: float = 1.0  # depth pixels
    full_well: float = 4000.0  # electrons at linear 1.0
    read_noise: float = 5.0  # electrons RMS
    gain_drift: float = 0.1  # exposure gain in [1/(1+x), 1+x]
    white_balance_drift: float = 0.04  # red/blue gains in [1/(1+x), 1+x]
    color_samples: int = 2  # subpixel rays per side over the pixel area (4x the point-sampled render)
    name = "d415"

    def depth_step(self, z) -> np.ndarray:
        """Terrace height (m) of the disparity quantisation at depth z (m): ``z^2 / (f B steps)``."""
        return np.asarray(z, dtype=np.float64) ** 2 / (self.focal_px * self.baseline * self.subpixel_steps)

    def depth_sigma(self, z) -> np.ndarray:
        """Std (m) of the white depth noise at depth z (m); the smooth field adds ``lowfreq/disparity`` times it."""
        return np.asarray(z, dtype=np.float64) ** 2 * self.disparity_sigma / (self.focal_px * self.baseline)

    def quantise_disparity(self, z: np.ndarray) -> np.ndarray:
        """Depth (m) on the disparity lattice: ``f B / (rint(f B / z * steps) / steps)``; 0 stays 0."""
        fb = self.focal_px * self.baseline
        z = np.asarray(z, dtype=np.float64)
        d = np.rint(fb / np.where(z > 0, z, np.inf) * self.subpixel_steps) / self.subpixel_steps
        return np.where((z > 0) & (d > 0), fb / np.where(d > 0, d, 1.0), 0.0)

    def edge_pixels(self, depth: np.ndarray, scale_factor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(edge, near, far) on the depth grid (h, w): pixels whose footprint, grown by one colour
        pixel, holds a miss or a jump > :data:`EDGE_JUMP`; the nearest and farthest depth there (m;
        ``near + flying_reach`` for a miss, 0 where nothing was hit)."""
        hit = depth > 0
        near = ndi.minimum_filter(np.where(hit, depth, np.inf), size=3, mode="nearest")
        far = ndi.maximum_filter(np.where(hit, depth, -np.inf), size=3, mode="nearest")
        miss = ndi.minimum_filter(hit.astype(np.uint8), size=3, mode="nearest") == 0
        far = np.where(miss & np.isfinite(near), np.maximum(far, near + self.flying_reach), far)
        edge = np.isfinite(near) & (far - near > EDGE_JUMP)
        k = int(scale_factor)
        h, w = depth.shape[0] // k, depth.shape[1] // k
        blocks = lambda a: a.reshape(h, k, w, k)  # noqa: E731
        near_lr = blocks(near).min(axis=(1, 3))
        far_lr = blocks(np.where(np.isfinite(far), far, -np.inf)).max(axis=(1, 3))
        edge_lr = blocks(edge).any(axis=(1, 3))
        ok = np.isfinite(near_lr) & np.isfinite(far_lr)
        return edge_lr & ok, np.where(ok, near_lr, 0.0), np.where(ok, far_lr, 0.0)

    def depth(self, depth: np.ndarray, scale_factor: int, rng: np.random.Generator) -> np.ndarray:
        """Low-resolution depth (H/SF, W/SF) float64 metres (0 = none) of depth (H, W) at colour
        resolution (0 where nothing was hit); steps 1-5 of the class docstring, before the 1 mm units."""
        z = simulate_depth_sensor(depth, scale_factor, None, depth_scale=None)
        edge, near, far = self.edge_pixels(depth, scale_factor)
        flying = edge & (rng.random(z.shape) < self.flying_fraction)
        z = np.where(flying, near + rng.random(z.shape) * (far - near), z)
        valid = z > 0
        fb = self.focal_px * self.baseline
        field = smooth_field(rng, z.shape, self.lowfreq_scale * z.shape[1])
        disparity = fb / np.where(valid, z, 1.0) + rng.normal(size=z.shape) * self.disparity_sigma \
            + field * self.lowfreq_sigma
        z = np.where(valid & (disparity > 0), fb / np.where(disparity > 0, disparity, 1.0), 0.0)
        holes = smooth_field(rng, z.shape, self.hole_scale)
        if valid.any():
            z = np.where(holes > np.quantile(holes[valid], 1.0 - self.hole_fraction), 0.0, z)
        return self.quantise_disparity(z)

    def frame_gains(self, rng: np.random.Generator) -> tuple[float, np.ndarray]:
        """(exposure gain, white balance (3,)) of one frame, drawn from ``rng``."""
        gain = float(np.exp(rng.uniform(-1.0, 1.0) * np.log1p(self.gain_drift)))
        red, blue = np.exp(rng.uniform(-1.0, 1.0, size=2) * np.log1p(self.white_balance_drift))
        return gain, np.array([red, 1.0, blue])

    def color(self, linear: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
        """(8-bit sRGB values linearised (H, W, 3) float32, {"gain", "white_balance"} of the frame)."""
        gain, balance = self.frame_gains(rng)
        electrons = self.full_well * gain * np.clip(np.asarray(linear, dtype=np.float64), 0.0, None)
        electrons = electrons + rng.normal(size=electrons.shape) * np.sqrt(electrons + self.read_noise**2)
        out = quantise_srgb8(electrons / self.full_well * balance).astype(np.float32)
        return out, {"gain": gain, "white_balance": balance.tolist()}

    def describe(self) -> dict:
        """JSON-ready parameters (written to capture.json's metadata.synthetic.sensor)."""
        return {"name": "d415", **{f.name: float(getattr(self, f.name)) for f in fields(self)},
                "depth_step_at_1m_mm": float(self.depth_step(1.0) * 1000),
                "depth_sigma_at_1m_mm": float(self.depth_sigma(1.0) * 1000), "depth_scale": DEPTH_SCALE}


def smooth_field(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Zero-mean, unit-RMS (h, w) random field: white noise Gaussian-filtered with ``sigma`` pixels."""
    field = ndi.gaussian_filter(rng.normal(size=shape), sigma, mode="wrap")
    return (field - field.mean()) / max(float(field.std()), 1e-12)


def make_sensor(name: str):
    """The sensor profile named ``name`` (:data:`SENSORS`): "gaussian", "d415" or "none"."""
    if name == "gaussian":
        return GaussianSensor()
    if name == "none":
        return GaussianSensor(noise=False)
    if name == "d415":
        return D415Sensor()
    raise ValueError(f"unknown sensor {name!r}; choose one of {list(SENSORS)}")


def resolve_sensor(sensor: str | None, noise: bool):
    """The profile of the renderers' ``sensor`` and ``noise`` arguments: ``sensor`` None means
    "gaussian" (``noise`` True, the paper's protocol) or "none"; ``noise=False`` with a noisy
    ``sensor`` is a contradiction (ValueError)."""
    if sensor is None:
        return make_sensor("gaussian" if noise else "none")
    if not noise and sensor != "none":
        raise ValueError(f"noise=False contradicts sensor={sensor!r}; pass sensor='none' (quantisation only) "
                         "or leave noise at True")
    return make_sensor(sensor)
