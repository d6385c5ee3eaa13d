"""The static-camera, moving-light setting (Peng et al. 2017): a camera fixed on a tripod, a light
moved by hand between frames. Such a capture needs no registration (every pose is the identity).

:func:`camera_setting` decides whether a capture is one: capture.json's ``"camera"`` when it says,
else the depth (:func:`static_depth_agreement`): a fixed camera sees the same surface in every
frame, so on a coarse grid every frame's depth matches the reference's within the sensor noise
over nearly the same pixels; a camera moved by even a degree shifts the silhouette and tilts the
surface by more.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass

import numpy as np

from ..model.resampling import resample_valid
from .types import Capture

#: Coarse grid of the check: about this many pixels across.
COARSE_WIDTH = 80
#: Depth agreement tolerance: max(STATIC_TOLERANCE_M, STATIC_TOLERANCE_REL * z) on the coarse grid.
STATIC_TOLERANCE_M = 0.005
STATIC_TOLERANCE_REL = 0.01
#: A frame agrees when this fraction of the coarse pixels fully valid in both agree, and the
#: pixels valid in both are this fraction of those valid in either (holes and flying pixels at the
#: silhouette change a static D415-like capture's by 5-10 %; rendered 320x240 bunny, SF 2).
MIN_AGREEMENT = 0.8
MIN_OVERLAP = 0.75


@dataclass(frozen=True)
class CameraSetting:
    """Whether a capture is treated as static-camera, and why (JSON-ready via :meth:`to_dict`).

    static: treated as static (no registration, identity poses, no pose refinement).
    declared: capture.json's "camera" ("static", "moving" or None). detected: what the depth
    says (None when not checked: a capture that declares "moving", or a single frame).
    agreement, overlap: the worst frame's figures (:func:`static_depth_agreement`); worst_frame
    its index. detail: in words.
    """

    static: bool
    declared: str | None
    detected: bool | None
    agreement: float | None = None
    overlap: float | None = None
    worst_frame: int | None = None
    detail: str = ""

    def to_dict(self) -> dict:
        return asdict(self)


def static_depth_agreement(depths: np.ndarray, coarse_width: int = COARSE_WIDTH) -> list[tuple[float, float]]:
    """(agreement, overlap) of every frame i >= 1 with frame 0, on a coarse grid.

    depths (n, h, w) metres, 0 = none. Each frame is area-averaged to about ``coarse_width``
    pixels across. agreement: the fraction of the coarse pixels fully valid in both frames (no
    hole, no silhouette) whose depths differ by at most ``max(5 mm, 1 % z)``; overlap: the
    coarse pixels at least half valid in both over those in either (1 when none is valid anywhere).
    """
    depths = np.asarray(depths, dtype=np.float64)
    n, h, w = depths.shape
    k = max(1, int(round(w / coarse_width)))
    size = (max(1, h // k), max(1, w // k))
    full = [resample_valid(d, d > 0, size, min_valid_fraction=1.0) for d in depths]
    half = [resample_valid(d, d > 0, size, min_valid_fraction=0.5)[1] for d in depths]
    z0, v0 = full[0]
    out = []
    for (z, v), h in zip(full[1:], half[1:]):
        both = v & v0
        tolerance = np.maximum(STATIC_TOLERANCE_M, STATIC_TOLERANCE_REL * z0)
        agree = float(np.mean(np.abs(z - z0)[both] <= tolerance[both])) if both.any() else 0.0
        either = h | half[0]
        out.append((agree, float((h & half[0]).sum() / either.sum()) if either.any() else 1.0))
    return out


def camera_setting(capture: Capture, warn: bool = True) -> CameraSetting:
    """Whether ``capture`` is a static-camera capture: declared in capture.json, or detected from
    the depth (:func:`static_depth_agreement`; every frame must agree). Warns (when ``warn``) if
    the depth finds a static camera the capture does not declare, or contradicts a declared one;
    a declared "camera" always wins."""
    declared = capture.camera
    if declared == "moving" or capture.n_frames < 2:
        return CameraSetting(static=declared == "static", declared=declared, detected=None,
                             detail="declared moving in capture.json" if declared == "moving" else "a single frame")
    depths = np.stack([capture.depth_array(i) for i in range(capture.n_frames)])
    figures = static_depth_agreement(depths)
    scores = [min(a / MIN_AGREEMENT, o / MIN_OVERLAP) for a, o in figures]
    worst = int(np.argmin(scores))
    agreement, overlap = figures[worst]
    detected = all(a >= MIN_AGREEMENT and o >= MIN_OVERLAP for a, o in figures)
    figures_text = (f"the depth of frame {worst + 1} agrees with the reference's on {agreement:.0%} of the pixels "
                    f"both see, which overlap {overlap:.0%}")
    static = declared == "static" or detected
    if declared == "static":
        detail = "declared static in capture.json" + ("" if detected else f", although {figures_text}")
        if warn and not detected:
            warnings.warn(f"capture.json says \"camera\": \"static\", but {figures_text} (a static camera gives "
                          f"at least {MIN_AGREEMENT:.0%} and {MIN_OVERLAP:.0%}): treating it as static as declared; "
                          "if the camera moved, write \"camera\": \"moving\"", stacklevel=3)
    elif detected:
        detail = f"detected from the depth (every frame agrees with the reference; the worst: {figures_text})"
        if warn:
            warnings.warn("every frame's depth agrees with the reference's (no camera motion): treating the capture "
                          "as static-camera, moving-light (no registration, identity poses, no pose refinement). "
                          "Write \"camera\": \"static\" into capture.json to say so, or \"camera\": \"moving\" if "
                          "the camera did move", stacklevel=3)
    else:
        detail = f"the camera moved: {figures_text}"
    return CameraSetting(static=static, declared=declared, detected=detected, agreement=agreement, overlap=overlap,
                         worst_frame=worst + 1, detail=detail)
