"""Resampling images between grids: area resizing, block averages, nearest-valid and harmonic
fill, normalised Gaussian filtering over valid pixels.

Pixel centres sit at integer coordinates (:mod:`o3d_mvps.model.camera`); a grid downsampled
by an integer factor k keeps the centre of block j at fine coordinate ``k j + (k - 1) / 2``,
which is what both :func:`resize` (OpenCV's area interpolation) and :func:`block_average` do.
"""

from __future__ import annotations

import cv2
import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp
import scipy.sparse.linalg as spla


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
    # relative slack: at a ratio that is not a whole number, cv2 weighs the areas in float32, so a
    # full block's weights sum to 1 - 4e-8 (a 284x427 depth to 47x71 lost all but 2 % of its pixels)
    ok = weight >= min_valid_fraction * (1.0 - 1e-6)
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


def masked_gaussian(values: np.ndarray, valid: np.ndarray, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Normalised Gaussian filter (std ``sigma`` pixels) of ``values`` (H, W) over ``valid`` (H, W)
    bool: (smoothed (H, W), weight (H, W), the filtered share of valid pixels; the smoothed value
    is meaningless where the weight is near 0)."""
    valid = np.asarray(valid, dtype=bool)
    weight = ndi.gaussian_filter(valid.astype(np.float64), sigma, mode="constant")
    total = ndi.gaussian_filter(np.where(valid, values, 0.0).astype(np.float64), sigma, mode="constant")
    return total / np.maximum(weight, 1e-12), weight


def blend_into_mean(z0: np.ndarray, mean: np.ndarray, use: np.ndarray, sigma: float) -> np.ndarray:
    """(h, w) metres: ``mean`` (h, w) where ``use`` (h, w) bool, elsewhere the valid (> 0) pixels
    of ``z0`` (h, w) less their offset from the mean nearby (``z0 - mean`` over the pixels both
    have, a :func:`masked_gaussian` of ``sigma`` pixels), so that no step forms where the mean
    ends; 0 where neither. The reference depth a capture's frames average (a static camera's,
    :func:`o3d_mvps.capture.static.reference_depth_mean`; a moving one's,
    :func:`o3d_mvps.covisibility.reference_depth_mean`)."""
    valid = z0 > 0
    offset, weight = masked_gaussian(z0 - mean, valid & use, sigma)
    kept = valid & ~use
    return np.where(use, mean, np.where(kept, z0 - np.where(weight > 1e-3, offset, 0.0), 0.0))


#: weight of each unknown pixel's pull toward its nearest known value in :func:`harmonic_fill`
#: (against 1 per neighbour difference): it settles regions no known pixel borders
HARMONIC_ANCHOR = 1e-6


def harmonic_fill(image: np.ndarray, known: np.ndarray, unknown: np.ndarray) -> np.ndarray:
    """Copy (H, W) float64 of ``image`` (H, W) with the ``unknown`` (H, W) bool pixels set to the
    harmonic (membrane) interpolation of the ``known`` (H, W) bool ones: the least squares of the
    differences between 4-neighbours in ``known | unknown``, one of them unknown (a plane is
    filled exactly), with a pull of :data:`HARMONIC_ANCHOR` toward the nearest known value (a
    region no known pixel borders takes it)."""
    known = np.asarray(known, dtype=bool)
    unknown = np.asarray(unknown, dtype=bool) & ~known
    out = np.asarray(image, dtype=np.float64).copy()
    if not unknown.any() or not known.any():
        return out
    H, W = out.shape
    m = int(unknown.sum())
    index = np.full(H * W, -1)
    index[unknown.ravel()] = np.arange(m)
    domain = (known | unknown).ravel()
    flat = np.arange(H * W).reshape(H, W)
    pairs = np.concatenate([np.stack([flat[:, :-1].ravel(), flat[:, 1:].ravel()], axis=1),
                            np.stack([flat[:-1, :].ravel(), flat[1:, :].ravel()], axis=1)])
    pairs = pairs[domain[pairs].all(axis=1) & (index[pairs] >= 0).any(axis=1)]
    cols = index[pairs]  # (k, 2), -1 for a known pixel
    signs = np.broadcast_to(np.array([1.0, -1.0]), cols.shape)
    free = cols >= 0
    rows = np.broadcast_to(np.arange(len(pairs))[:, None], cols.shape)
    A = sp.csr_matrix((signs[free], (rows[free], cols[free])), shape=(len(pairs), m))
    b = -np.where(free, 0.0, signs * out.ravel()[pairs]).sum(axis=1)  # the known ends moved over
    anchor = fill_nearest_valid(out, known)[unknown]
    normal = (A.T @ A + HARMONIC_ANCHOR * sp.identity(m)).tocsc()
    out[unknown] = spla.spsolve(normal, A.T @ b + HARMONIC_ANCHOR * anchor)
    return out
