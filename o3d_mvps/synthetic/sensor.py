"""Sensor simulation: the 8-bit sRGB colour camera and the low-resolution, noisy, quantised depth sensor."""

from __future__ import annotations

import numpy as np

from ..colour import linear_to_srgb, srgb_to_linear
from ..model.resampling import resample_valid

COLOR_NOISE_SIGMA = 0.005
DEPTH_SCALE = 1000.0  # depth units per metre: 1 mm quantisation

SRGB8_TO_LINEAR = srgb_to_linear(np.arange(256) / 255.0)  # (256,) float32 decode table


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
