"""Resampling images between grids: area resizing, block averages, nearest-valid fill.

Pixel centres sit at integer coordinates (:mod:`o3d_mvps.model.camera`); a grid downsampled
by an integer factor k keeps the centre of block j at fine coordinate ``k j + (k - 1) / 2``,
which is what both :func:`resize` (OpenCV's area interpolation) and :func:`block_average` do.
"""

from __future__ import annotations

import cv2
import numpy as np
import scipy.ndimage as ndi


def resize(image: np.ndarray, size: tuple[int, int], interpolation=cv2.INTER_AREA) -> np.ndarray:
    """Resize an (H, W) or (H, W, C) float image to size (H', W') (pixel-centre aligned)."""
    if image.shape[:2] == tuple(size):
        return image.copy()
    out = cv2.resize(np.ascontiguousarray(image), (size[1], size[0]), interpolation=interpolation)
    return out.reshape(tuple(size) + image.shape[2:])


def block_average(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean (H/k, W/k, ...) float64 over k x k blocks of an (H, W, ...) array; H, W multiples of k."""
    k = int(factor)
    H, W = image.shape[:2]
    blocks = np.asarray(image, dtype=np.float64).reshape(H // k, k, W // k, k, *image.shape[2:])
    return blocks.mean(axis=(1, 3))


def resample_valid(values: np.ndarray, valid: np.ndarray, size: tuple[int, int],
                   min_valid_fraction: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Area-resample a sparse map (H, W) to ``size`` (H', W'), averaging valid pixels only.

    Returns (values' (H', W') float64, valid' (H', W') bool): valid' marks target pixels whose
    source area is at least ``min_valid_fraction`` valid (1.0: fully valid, like a depth sensor
    that drops mixed pixels; a tiny positive number: any valid pixel); values' is 0 elsewhere.
    """
    valid = np.asarray(valid, dtype=bool)
    weight = resize(valid.astype(np.float64), size)
    total = resize(np.where(valid, values, 0.0).astype(np.float64), size)
    ok = weight >= min_valid_fraction - 1e-9  # area weights of a full block sum to 1 up to rounding
    return np.where(ok, total / np.maximum(weight, 1e-12), 0.0), ok


def fill_nearest_valid(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Copy of ``image`` (H, W[, C]) with every pixel outside ``valid`` (H, W) bool set to the
    value of the nearest valid pixel (Euclidean distance); unchanged when none or all are valid."""
    valid = np.asarray(valid, dtype=bool)
    if valid.all() or not valid.any():
        return image.copy()
    _, (iv, iu) = ndi.distance_transform_edt(~valid, return_indices=True)
    return image[iv, iu]


def repeat_pixels(image: np.ndarray, factor: int) -> np.ndarray:
    """(h, w) image -> (factor h, factor w): each pixel repeated over a factor x factor block
    (a depth-grid mask onto the colour grid)."""
    return np.repeat(np.repeat(image, factor, axis=0), factor, axis=1)
