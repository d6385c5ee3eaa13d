"""The RGB-D sensor's grids and units: the super-resolution factor and the depth-unit check.

Colour is (H, W), depth (h, w); the super-resolution factor SF relates them
(``H = SF h``, ``W = SF w`` when the depth is registered on the colour camera's grid).
"""

from __future__ import annotations

import numpy as np

from ..errors import CaptureError

#: Plausible median depth of a capture in metres; outside it the depth unit is almost surely wrong.
DEPTH_RANGE_M = (0.05, 20.0)


def choose_scale_factor(colour_size: tuple[int, int], depth_size: tuple[int, int], requested: int | None = None, *,
                 exact: bool = False) -> int:
    """The super-resolution factor SF for colour (H, W) and depth (h, w) sizes.

    ``requested`` wins when given; otherwise SF is the nearest integer to W / w, lowered until
    it divides both colour sides (1280x720 colour with 848x480 depth gives 2). SF must divide
    the colour size. With ``exact`` the depth must already lie on the SF grid, (H/SF, W/SF),
    or at colour resolution (to be block-averaged by the caller); otherwise it is resampled
    onto that grid by the caller (registration).

    Raises
    ------
    CaptureError
        A requested SF that is not a positive integer or does not divide the colour size, or
        (``exact``) depth that is not on the SF grid.
    """
    (H, W), (h, w) = (tuple(int(s) for s in colour_size), tuple(int(s) for s in depth_size))
    if h < 1 or w < 1:
        raise CaptureError(f"depth is {w}x{h} (WxH): it has no pixels; give non-empty depth frames")
    if requested is not None:
        if isinstance(requested, bool) or int(requested) != requested or requested < 1:
            raise CaptureError(f"scale_factor {requested!r} must be an integer >= 1 (2, 4 or 8)")
        sf = int(requested)
        if H % sf or W % sf:
            raise CaptureError(f"colour {W}x{H} is not divisible by scale_factor {sf}; crop the frames to a multiple")
    else:
        sf = max(1, int(round(W / w)))
        while sf > 1 and (H % sf or W % sf):
            sf -= 1
    if exact and (h, w) not in ((H // sf, W // sf), (H, W)):
        raise CaptureError(
            f"depth is {w}x{h} but colour is {W}x{H} (WxH): colour must be an integer multiple SF >= 1 of depth in "
            f"both directions (W = SF*w, H = SF*h; SF {sf} {'was asked for' if requested is not None else 'is the nearest'}). Colour and depth from different cameras "
            "(or camera modes) must first be registered to the colour camera (o3d_mvps.depth_to_colour.register_depth), "
            "or crop or resample one of them"
        )
    return sf


def check_depth_unit(z: np.ndarray, what: str, fix: str) -> None:
    """Raise CaptureError when the median of the valid (> 0) depths z (metres) lies outside
    :data:`DEPTH_RANGE_M`; ``what`` names the frame, ``fix`` says what to change."""
    valid = np.asarray(z)[np.asarray(z) > 0]
    lo, hi = DEPTH_RANGE_M
    if valid.size and not lo <= float(np.median(valid)) <= hi:
        raise CaptureError(f"{what}: median depth {np.median(valid):.4g} m is outside {lo:g}-{hi:g} m, "
                           f"so the unit looks wrong: {fix}")
