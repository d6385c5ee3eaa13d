"""Frame selection: sharpness, overlap with the reference, and an even spread of the kept frames."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def grey_thumbnail(rgb: np.ndarray, width: int = 320) -> np.ndarray:
    """(h', width) float32 grey image in [0, 1] of an (H, W, 3) uint8 frame, area-downsampled."""
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    if grey.shape[1] > width:
        height = max(1, round(grey.shape[0] * width / grey.shape[1]))
        grey = cv2.resize(grey, (width, height), interpolation=cv2.INTER_AREA)
    return grey


def sharpness(grey: np.ndarray) -> float:
    """Variance of the Laplacian of an (h, w) grey image: low for blurred frames."""
    return float(cv2.Laplacian(np.asarray(grey, dtype=np.float32), cv2.CV_32F, ksize=3).var())


def image_overlap(reference: np.ndarray, grey: np.ndarray, width: int = 160, min_correlation: float = 0.5) -> float:
    """Estimated fraction (0..1) of the reference view still seen in another grey image.

    Cheap and approximate: the translation between the two (h, w) images is found by phase
    correlation of thumbnails at most ``width`` pixels wide. Phase correlation is circular, so
    a shift d and d - w (d - h vertically) are both tried; the one whose overlapping parts correlate
    best (normalised cross-correlation) wins. The overlap is the area of the reference covered
    by the shifted image, or 0 when even the best candidate correlates below
    ``min_correlation`` (the views share too little to be registered). Rotation and scale
    changes are not modelled; a frame must roughly look at the same scene as the reference.
    """
    def small(img):  # noqa: E306  (downsample only: upsampled thumbnails confuse phaseCorrelate)
        img = np.asarray(img, dtype=np.float32)
        if img.shape[1] > width:
            size = (width, max(8, round(img.shape[0] * width / img.shape[1])))
            img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        return img.astype(np.float64) - img.mean()

    a, b = small(reference), small(grey)
    h, w = a.shape
    (dx, dy), _ = cv2.phaseCorrelate(a, b)  # b(x, y) ~ a(x - dx, y - dy)
    best_ncc, best_area = -1.0, 0.0
    for sx in {int(round(dx)), int(round(dx - np.copysign(w, dx)))}:
        for sy in {int(round(dy)), int(round(dy - np.copysign(h, dy)))}:
            area = max(0.0, 1 - abs(sx) / w) * max(0.0, 1 - abs(sy) / h)
            if area < 0.05:
                continue
            xa, ya = slice(max(0, -sx), min(w, w - sx)), slice(max(0, -sy), min(h, h - sy))
            xb, yb = slice(xa.start + sx, xa.stop + sx), slice(ya.start + sy, ya.stop + sy)
            pa, pb = a[ya, xa] - a[ya, xa].mean(), b[yb, xb] - b[yb, xb].mean()
            ncc = float((pa * pb).sum() / (np.sqrt((pa * pa).sum() * (pb * pb).sum()) + 1e-12))
            if ncc > best_ncc:
                best_ncc, best_area = ncc, area
    return best_area if best_ncc >= min_correlation else 0.0


@dataclass
class FrameSelection:
    """Result of :func:`select_frames`: chosen indices (reference first) and per-candidate scores."""

    indices: list
    sharpness: list
    overlap: list
    blurred: list
    low_overlap: list


def select_frames(
    greys: list[np.ndarray], count: int, blur_fraction: float = 0.5, min_overlap: float = 0.5
) -> FrameSelection:
    """Choose up to ``count`` sharp, overlapping frames, spread evenly, from candidate greys.

    Parameters
    ----------
    greys : list of (h, w) float32
        Grey thumbnails of the candidate frames in recording order.
    count : int
        Number of frames wanted (fewer are returned when fewer qualify).
    blur_fraction : float
        A frame is blurred when its :func:`sharpness` < ``blur_fraction`` x the median.
    min_overlap : float
        A frame is dropped when its :func:`image_overlap` with the reference < ``min_overlap``.

    Returns
    -------
    FrameSelection
        ``indices`` into ``greys``, the first one the reference (the first sharp frame).
    """
    if count < 1:
        raise ValueError(f"frames must be at least 1, got {count}")
    if not greys:
        return FrameSelection([], [], [], [], [])
    scores = np.array([sharpness(g) for g in greys])
    sharp = scores >= blur_fraction * np.median(scores)
    ref = int(np.argmax(sharp))
    overlap = np.array([image_overlap(greys[ref], g) if sharp[i] else 0.0 for i, g in enumerate(greys)])
    good = np.flatnonzero(sharp & (overlap >= min_overlap))  # starts with ref (overlap 1)
    if len(good) > count:
        good = good[np.round(np.linspace(0, len(good) - 1, count)).astype(int)]
    return FrameSelection(
        indices=[int(i) for i in good], sharpness=scores.tolist(), overlap=overlap.tolist(),
        blurred=np.flatnonzero(~sharp).tolist(), low_overlap=np.flatnonzero(sharp & (overlap < min_overlap)).tolist(),
    )  # fmt: skip
