"""The static-camera, moving-light setting (Peng et al. 2017): a camera fixed on a tripod, a light
moved by hand between frames. Such a capture needs no registration (every pose is the identity).

:func:`camera_setting` decides whether a capture is one: capture.json's ``"camera"`` when it says,
else the depth (:func:`static_depth_agreement`): a fixed camera sees the same surface in every
frame, so on a coarse grid every frame's depth matches the reference's within the sensor noise
over nearly the same pixels. A slow orbit (a degree or two) passes that too, so a capture that
passes is confirmed by ICP of a few frames onto the reference (:func:`static_frame_motion`):
moving when they move the surface by several times the depth noise and over a depth pixel.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass

import numpy as np

from ..model.camera import project, transform
from ..model.resampling import blend_into_mean, resample_valid
from ..model.robust import nan_median
from ..model.se3 import rotation_angle_deg
from ..odometry import ICP_VOXELS, MAX_CLOUD_POINTS, cloud_pyramid, depth_cloud, frame_region, register
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
#: Fewer coarse pixels valid in both frames than this: too little depth to call a camera static.
MIN_COARSE_PIXELS = 50
#: A camera the depth agreement finds static is confirmed by ICP (:func:`static_frame_motion`) of
#: CONFIRM_FRAMES frames onto the reference (the last frame and the worst-agreeing ones). A frame
#: moved when ICP moves the reference's points (MOTION_PERCENTILE th percentile) by more than
#: STATIC_NOISE_MULTIPLE times the depth noise left after the alignment and by more than
#: STATIC_MIN_MOTION_PX of their depth-pixel footprints (z / fx): both scale-free. Measured on
#: D415-like renders (SF 2): static bunny and quilt at 320x240 and 640x480, 0.25-0.6 m, 4 x 19 frames:
#: at most 3.1 x the noise (and 1.65 px); slow orbits at 320x240: 0.5 deg a frame at 0.25 m
#: 15 x / 2.5 px at frame 4, 0.75 deg a frame at 0.6 m 5.2 x / 1.34 px at frame 4; the first 6 frames
#: of a 2 MP bunny render (0.79 deg a frame, 0.25 m, 427x284 depth) 10.7 x / 11.8 px at frame 5.
CONFIRM_FRAMES = 4
STATIC_NOISE_MULTIPLE = 4.0
STATIC_MIN_MOTION_PX = 1.0
MOTION_PERCENTILE = 95
#: the ICP check's clouds read every k-th depth pixel of every k-th row, k the largest that leaves
#: at least this many times the clouds' MAX_CLOUD_POINTS pixels (a 640x480 depth: every 2nd)
ICP_PIXELS_PER_POINT = 2


#: Given poses that move a frame by more than this (m, or radians) are a moving camera.
MOVED_M = 1e-3
MOVED_RAD = np.radians(0.1)


def _poses_move(poses: np.ndarray) -> bool:
    """Whether any pose (n, 4, 4; frame 0 -> frame i) moves by more than MOVED_M or turns by more than MOVED_RAD."""
    relative = poses @ np.linalg.inv(poses[0])
    cos = np.clip((np.trace(relative[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return bool(np.any(np.linalg.norm(relative[:, :3, 3], axis=1) > MOVED_M) or np.any(np.arccos(cos) > MOVED_RAD))


@dataclass(frozen=True)
class CameraSetting:
    """Whether a capture is treated as static-camera, and why (JSON-ready via :meth:`to_dict`).

    static: treated as static (no registration, identity poses, no pose refinement).
    declared: capture.json's "camera" ("static", "moving" or None). detected: what the depth
    says (None when not checked: a capture that declares "moving", or a single frame).
    agreement, overlap: the worst frame's figures (:func:`static_depth_agreement`); worst_frame
    its index. motion_frame, motion_mm, motion_noise, motion_px: the ICP check of a capture
    (undeclared, or declared static) whose depth agrees (:func:`_confirm_static`): the frame, how far its points moved (mm),
    that over the depth noise, and in depth pixels (None when not checked or ICP failed). detail: in words.
    """

    static: bool
    declared: str | None
    detected: bool | None
    agreement: float | None = None
    overlap: float | None = None
    worst_frame: int | None = None
    detail: str = ""
    motion_frame: int | None = None
    motion_mm: float | None = None
    motion_noise: float | None = None
    motion_px: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    def check(self) -> dict:
        """The row of ``info["inputs"]["checks"]`` (name "camera"): a warning where capture.json
        declares a static camera that the depth (agreement, or ICP of the frames that agree)
        finds moving, else ok; detail: :attr:`detail`."""
        contradicted = self.declared == "static" and self.detected is False
        return {"name": "camera", "status": "warning" if contradicted else "ok", "detail": self.detail}


def static_depth_agreement(depths: np.ndarray, coarse_width: int = COARSE_WIDTH) -> list[tuple[float, float, int]]:
    """(agreement, overlap, pixels) of every frame i >= 1 with frame 0, on a coarse grid.

    depths (n, h, w) metres, 0 = none. Each frame is area-averaged to about ``coarse_width``
    pixels across. agreement: the fraction of the coarse pixels fully valid in both frames (no
    hole, no silhouette) whose depths differ by at most ``max(5 mm, 1 % z)``; overlap: the
    coarse pixels at least half valid in both over those in either (1 when none is valid anywhere);
    pixels: how many coarse pixels the agreement counts.
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
        out.append((agree, float((h & half[0]).sum() / either.sum()) if either.any() else 1.0, int(both.sum())))
    return out


def static_frame_motion(capture: Capture, frames) -> list[tuple[float, float, float, float, float, str | None]]:
    """(pixels, shift_mm, noise_mm, mm, deg, failure) of each of ``frames`` registered onto frame 0.

    Point-to-plane ICP from the identity (:func:`o3d_mvps.odometry.register`, the clouds of
    :func:`~o3d_mvps.odometry.depth_cloud` inside the object masks when there are any) gives T
    (reference -> frame i). pixels: the :data:`MOTION_PERCENTILE` th percentile over the reference
    cloud's points p of ``|T p - p| / (z_p / fx)``, how far T moves the surface in units of its
    depth-pixel footprint; shift_mm: that percentile of ``|T p - p|`` (both inf when ICP fails);
    noise_mm: the depth noise once aligned (:func:`_residual_spread` of T p in frame i's depth);
    mm, deg: T's translation and rotation; failure: why ICP failed (None when it did not).
    """
    K = np.asarray(capture.depth_K(), dtype=np.float64)
    h, w = capture.depth_size
    # every k-th pixel where the depth image holds over ICP_PIXELS_PER_POINT x MAX_CLOUD_POINTS
    stride = max(1, int(np.sqrt(h * w / (ICP_PIXELS_PER_POINT * MAX_CLOUD_POINTS))))
    clouds = {i: cloud_pyramid(depth_cloud(capture.depth_array(i), K, region=frame_region(capture, i),
                                           voxel=ICP_VOXELS[-1], pixel_stride=stride))
              for i in [0, *frames]}
    points = np.asarray(clouds[0][-1].points)
    out = []
    for i in frames:
        attempt = register(clouds[0], clouds[i], np.eye(4), f"ICP of frame {i} onto frame 0")
        T = attempt.T
        aligned = transform(T, points)
        moved = np.linalg.norm(aligned - points, axis=1)
        ok = attempt.failure is None and len(moved)
        pixels = float(np.percentile(moved * K[0, 0] / points[:, 2], MOTION_PERCENTILE)) if ok else np.inf
        shift = float(np.percentile(moved, MOTION_PERCENTILE)) if ok else np.inf
        noise = _residual_spread(aligned, capture.depth_array(i), K)
        out.append((pixels, shift * 1000, noise * 1000, float(np.linalg.norm(T[:3, 3]) * 1000),
                    rotation_angle_deg(T[:3, :3]), attempt.failure))
    return out


def _residual_spread(points: np.ndarray, depth: np.ndarray, K: np.ndarray) -> float:
    """Robust spread (m, 1.4826 MAD) of ``depth`` (h, w) at the nearest pixels the ``points`` (m, 3,
    camera frame) project to minus their z (inf when none): once the frames are aligned, the
    sensor's depth noise, plus what the cloud's smoothing and the pixel rounding on slopes leave
    (0.49 mm on a noiseless bunny at 0.6 m, 320x240, SF 2)."""
    z = np.asarray(depth, dtype=np.float64).reshape(np.shape(depth)[:2])
    u, v, zp = project(points, K)
    u, v = np.rint(u).astype(int), np.rint(v).astype(int)
    inside = (zp > 0) & (u >= 0) & (u < z.shape[1]) & (v >= 0) & (v < z.shape[0])
    r = z[v[inside], u[inside]] - points[inside, 2]
    r = r[z[v[inside], u[inside]] > 0]
    return float(1.4826 * np.median(np.abs(r - np.median(r)))) if len(r) else np.inf


def _confirm_static(capture: Capture, scores: list) -> tuple[dict, str, bool]:
    """(figures, in words, moved) of :func:`static_frame_motion` on the last frame and the
    worst-agreeing ones (``scores`` of frames 1..n-1, lower is worse), :data:`CONFIRM_FRAMES` in
    all: of the frame nearest to (or farthest past) both bounds. figures: motion_frame,
    motion_mm, motion_noise (times the depth noise), motion_px. moved: by more than
    :data:`STATIC_NOISE_MULTIPLE` times the noise and :data:`STATIC_MIN_MOTION_PX`, or ICP failed
    (no motion can be ruled out: registration is the safe default)."""
    n = capture.n_frames
    frames = list(dict.fromkeys([n - 1, *(int(i) + 1 for i in np.argsort(scores))]))[:CONFIRM_FRAMES]
    motions = static_frame_motion(capture, frames)
    times = [shift / noise if noise > 0 else (np.inf if shift > 0 else 0.0) for _, shift, noise, *_ in motions]
    k = int(np.argmax([min(t / STATIC_NOISE_MULTIPLE, m[0] / STATIC_MIN_MOTION_PX) for t, m in zip(times, motions)]))
    pixels, shift, noise, mm, deg, failure = motions[k]
    figures = {"motion_frame": frames[k], "motion_mm": None if failure else round(shift, 3),
               "motion_noise": None if failure else round(float(times[k]), 2),
               "motion_px": None if failure else round(pixels, 3)}
    if failure is not None:
        return figures, (f"ICP of frame {frames[k]} onto the reference failed ({failure}), so a small camera motion "
                         "cannot be ruled out"), True
    said = (f"ICP of frame {frames[k]} onto the reference moves its points by {shift:.2f} mm ({MOTION_PERCENTILE}th "
            f"percentile), {times[k]:.1f} times the depth noise left ({noise:.2f} mm) and {pixels:.2f} depth pixels "
            f"(the camera {mm:.1f} mm, {deg:.2f} deg; the most of the {len(frames)} frames checked; a camera moved "
            f"when over {STATIC_NOISE_MULTIPLE:g} times the noise and {STATIC_MIN_MOTION_PX:g} pixel)")
    return figures, said, bool(times[k] > STATIC_NOISE_MULTIPLE and pixels > STATIC_MIN_MOTION_PX)


def camera_setting(capture: Capture, poses=None, warn: bool = True) -> CameraSetting:
    """Whether ``capture`` is a static-camera capture: declared in capture.json, or detected from
    the depth (:func:`static_depth_agreement`; every frame must agree, then ICP of a few frames,
    :func:`_confirm_static`). Warns (when ``warn``) if the depth finds a static camera the capture
    does not declare, or contradicts a declared one (the depth disagrees, or ICP finds a frame
    moved; :meth:`CameraSetting.check` is then a warning); a declared "camera" always wins. Given ``poses`` (n, 4, 4) that move a frame by more than
    :data:`MOVED_M` or :data:`MOVED_RAD` settle an undeclared capture as moving (no check)."""
    declared = capture.camera
    if declared == "moving" or capture.n_frames < 2:
        return CameraSetting(static=declared == "static", declared=declared, detected=None,
                             detail="declared moving in capture.json" if declared == "moving" else "a single frame")
    poses = None if poses is None else np.asarray(poses, dtype=np.float64)
    if declared is None and poses is not None and poses.shape == (capture.n_frames, 4, 4) and _poses_move(poses):
        return CameraSetting(static=False, declared=None, detected=None, detail="the given poses move the camera")
    depths = np.stack([capture.depth_array(i) for i in range(capture.n_frames)])
    figures = static_depth_agreement(depths)
    scores = [min(a / MIN_AGREEMENT, o / MIN_OVERLAP, p / MIN_COARSE_PIXELS) for a, o, p in figures]
    worst = int(np.argmin(scores))
    agreement, overlap, _ = figures[worst]
    detected = all(a >= MIN_AGREEMENT and o >= MIN_OVERLAP and p >= MIN_COARSE_PIXELS for a, o, p in figures)
    pixels = figures[worst][2]
    figures_text = (f"the depth of frame {worst + 1} agrees with the reference's on {agreement:.0%} of the pixels "
                    f"both see, which overlap {overlap:.0%}" + (f" (only {pixels} coarse pixels: too little depth "
                                                                f"to tell)" if pixels < MIN_COARSE_PIXELS else ""))
    motion, moved = {}, False
    if detected:  # the depth agrees: confirm that no frame moved by a pixel or two (declared static too)
        motion, motion_text, moved = _confirm_static(capture, scores)
        detected = not moved
    static = declared == "static" or detected
    if declared == "static":
        contradiction = (f"every frame's depth agrees with the reference's (the worst: {figures_text}), but "
                         f"{motion_text}" if moved else
                         f"{figures_text} (a static camera gives at least {MIN_AGREEMENT:.0%} and {MIN_OVERLAP:.0%})")
        detail = "declared static in capture.json" + ("" if detected else f", although {contradiction}")
        if warn and not detected:
            warnings.warn(f"capture.json says \"camera\": \"static\", but {contradiction}: treating it as static as "
                          "declared; if the camera moved, write \"camera\": \"moving\"", stacklevel=3)
    elif detected:
        detail = (f"detected from the depth (every frame agrees with the reference; the worst: {figures_text}; "
                  f"{motion_text})")
        if warn:
            warnings.warn("every frame's depth agrees with the reference's (no camera motion): treating the capture "
                          "as static-camera, moving-light (no registration, identity poses, no pose refinement). "
                          "Write \"camera\": \"static\" into capture.json to say so, or \"camera\": \"moving\" if "
                          "the camera did move", stacklevel=3)
    elif motion:
        detail = (f"not static: every frame's depth agrees with the reference's (the worst: {figures_text}), but "
                  f"{motion_text}: treated as moving (registration finds near-identity poses for a static camera; "
                  f"write \"camera\": \"static\" into capture.json if it did not move)")
    else:
        detail = f"not static: {figures_text}"
    return CameraSetting(static=static, declared=declared, detected=detected, agreement=agreement, overlap=overlap,
                         worst_frame=worst + 1, detail=detail, **motion)


#: Pixels whose linear value is below this in any channel, or above :data:`BALANCE_SATURATED`,
#: are left out of :func:`frame_white_balance` (8-bit sRGB, shot noise: their channel ratios are noisy or clipped).
BALANCE_DARKEST = 0.02
BALANCE_SATURATED = 0.98
#: Fewer pixels usable in a frame and the reference than this: the frame's balance is left at 1.
BALANCE_MIN_PIXELS = 100
#: :func:`frame_white_balance` reads every k-th pixel of every k-th row, k the least that leaves
#: at most this many pixels per frame (a 1280x960 frame: every 2nd; 20 frames in 0.3 s, not 1.3 s;
#: every 2nd of a 640x480 frame took the bunny's error from 0.1 to 0.2 %)
BALANCE_MAX_PIXELS = 400_000


def frame_white_balance(colors, masks=None) -> np.ndarray:
    """Each frame's white balance relative to the frames' mean, (n, 3), green 1, from the images alone.

    A static camera sees each surface point at the same pixel in every frame; with a light whose
    colour is the same in every frame (a Lambertian surface, any lamp position, intensity and
    exposure), frame i's pixel is ``rho_c L_i w_ic``, so its log ratio of channel c to green
    minus the reference frame's is ``log(w_ic / w_ig) - log(w_0c / w_0g)`` at every pixel. Its
    median over the pixels usable in both frames (at most :data:`BALANCE_MAX_PIXELS`, evenly
    spread; every channel in
    [:data:`BALANCE_DARKEST`, :data:`BALANCE_SATURATED`], inside both masks where given), centred
    so that each channel's log balance averages 0 over the frames, is returned. Dividing frame i's
    channel c by it leaves the colour of the mean balance in the albedo (an albedo is known up to
    the light's colour) and a per-frame gain to the frame's light (the light models have one
    intensity per frame, not one per channel).

    Parameters
    ----------
    colors : sequence of n (H, W, 3) float arrays
        Linear RGB frames of a static camera.
    masks : sequence of n (H, W) bool arrays or None, optional
        Object masks (None: every pixel).

    Returns
    -------
    np.ndarray
        (n, 3) float64 balance factors, column 1 (green) all 1; rows of frames with fewer than
        :data:`BALANCE_MIN_PIXELS` usable pixels in common with the reference (or the reference
        itself when it has none) are left out of the centring and set to the mean balance (1).
    """
    n = len(colors)
    H, W = np.shape(colors[0])[:2]
    k = max(1, int(np.ceil(np.sqrt(H * W / BALANCE_MAX_PIXELS))))
    logs, usable = [], []
    for i in range(n):
        c = np.asarray(colors[i], dtype=np.float32)[::k, ::k]
        ok = np.ones(c.shape[:2], dtype=bool)  # channel by channel: NumPy's all(axis=2) over 3 is 6x slower
        for channel in range(3):
            ok &= (c[..., channel] >= BALANCE_DARKEST) & (c[..., channel] <= BALANCE_SATURATED)
        if masks is not None and masks[i] is not None:
            ok &= np.asarray(masks[i], dtype=bool)[::k, ::k]
        with np.errstate(divide="ignore", invalid="ignore"):
            logs.append(np.log(np.maximum(c[..., [0, 2]], 1e-6)) - np.log(np.maximum(c[..., 1:2], 1e-6)))
        usable.append(ok)
    relative = np.zeros((n, 2))
    found = np.zeros(n, dtype=bool)
    found[0] = usable[0].sum() >= BALANCE_MIN_PIXELS
    for i in range(1, n):
        both = usable[i] & usable[0]
        if both.sum() >= BALANCE_MIN_PIXELS:
            relative[i] = np.median((logs[i] - logs[0])[both], axis=0)
            found[i] = True
    balance = np.ones((n, 3))
    if found[0] and found.sum() >= 2:
        centred = relative - relative[found].mean(axis=0)
        balance[np.ix_(found, [0, 2])] = np.exp(centred[found])
    return balance


#: A reference depth pixel is a flying pixel when it is farther than max(STATIC_TOLERANCE_M,
#: STATIC_TOLERANCE_REL z) from the median of the frames' depths there, measured by at least this many frames.
MIN_FRAMES_FOR_MEDIAN = 3
#: A depth pixel is unsteady (:func:`unsteady_depth`) where fewer than this fraction of the frames
#: that measure it lie within that tolerance of their median. A surface measures alike in every
#: frame (D415-like at 0.55 m: about 1 mm); a depth pixel that straddles a silhouette is a mixture
#: of the near and far depth drawn anew in every frame (within 6 mm of the median: about one in five)
MIN_AGREEING_FRACTION = 0.5


def _frames_median(depths: np.ndarray) -> tuple:
    """(valid (n, h, w) bool, counts (h, w) int, median (h, w) m, 0 where no frame measures) of
    the frames' depths (n, h, w) metres, 0 = none."""
    depths = np.asarray(depths, dtype=np.float64)
    valid = depths > 0
    counts = valid.sum(axis=0)
    median = np.where(counts > 0, nan_median(np.where(valid, depths, np.nan)), 0.0)
    return valid, counts, median


def _frames_agreement(depths: np.ndarray) -> tuple:
    """(counts (h, w) int, median (h, w) m, agree (n, h, w) bool) of the frames' depths (n, h, w)
    metres, 0 = none: :func:`_frames_median`'s counts and median, and which frames measure within
    ``max(STATIC_TOLERANCE_M, STATIC_TOLERANCE_REL * median)`` of it."""
    valid, counts, median = _frames_median(depths)
    tolerance = np.maximum(STATIC_TOLERANCE_M, STATIC_TOLERANCE_REL * median)
    return counts, median, valid & (np.abs(np.asarray(depths, np.float64) - median) <= tolerance)


def reference_depth_outliers(depths: np.ndarray) -> np.ndarray:
    """(h, w) bool: the reference frame's depth pixels that disagree with the other frames of a
    static camera (flying pixels, mismatches).

    A fixed camera measures the same surface at the same depth pixel in every frame; a sensor's
    flying pixels along silhouettes and depth edges (a mixture of the near and far depth, up to
    centimetres off) fall anew in every frame. A pixel of frame 0 is flagged where at least
    :data:`MIN_FRAMES_FOR_MEDIAN` frames measure it and frame 0's depth is farther than
    ``max(STATIC_TOLERANCE_M, STATIC_TOLERANCE_REL * z)`` from their median (the depth noise is
    well inside: D415-like at 0.6 m, about 1 mm).

    depths (n, h, w) metres, 0 = none.
    """
    counts, _, agree = _frames_agreement(depths)
    return (np.asarray(depths[0]) > 0) & (counts >= MIN_FRAMES_FOR_MEDIAN) & ~agree[0]


def unsteady_depth(depths: np.ndarray) -> np.ndarray:
    """(h, w) bool: depth pixels that at least :data:`MIN_FRAMES_FOR_MEDIAN` frames of a static
    camera measure but fewer than :data:`MIN_AGREEING_FRACTION` of them alike (within
    ``max(STATIC_TOLERANCE_M, STATIC_TOLERANCE_REL * z)`` of their median): where a pixel flies in
    most frames, their median flies too, and :func:`reference_depth_outliers` keeps frame 0's
    flying depth. Without masks ``refine`` leaves their colour pixels out of its output: on the
    640x480 D415-like quilt 129 output pixels lay over 10 mm off the sheet (2x2 islands and a
    fringe 1-2 px past its edge, 52-90 mm behind it), 7 without them. Left in the solve:
    dropping them there moved the quilt's point lights from 9 to 30 mm off their truth at 320x240
    (docs/static-camera.md, "Flying pixels that fly in most frames").

    depths (n, h, w) metres, 0 = none.
    """
    counts, _, agree = _frames_agreement(depths)
    return (counts >= MIN_FRAMES_FOR_MEDIAN) & (agree.sum(axis=0) < MIN_AGREEING_FRACTION * counts)


#: a pixel is averaged (:func:`reference_depth_mean`) where at least this fraction of the frames
#: measures it alike: a sensor's speckle holes (D415-like: 3 % of the pixels, new in every frame)
#: are measured by nearly every other frame; past a silhouette, where a frame's flying pixels fall
#: about every other frame (D415-like: 50 %), the pixel is not averaged (nor filled)
FILL_MIN_FRACTION = 0.75
#: the Gaussian (depth pixels) over which frame 0's offset from the frames' mean is carried into
#: the pixels the frames do not average
FILL_OFFSET_SIGMA_PX = 4.0


def reference_depth_mean(depths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference depth of a static camera from all its frames: (depth (h, w) metres, 0 =
    none; filled (h, w) bool, the pixels frame 0 does not measure that the mean gives).

    A fixed camera measures the same surface at the same depth pixel in every frame, so the
    frames' depth noise averages out (D415-like: white disparity noise, terraces and a
    low-frequency error of about 1 mm at 0.6 m, new in every frame; on the 640x480 quilt, 20
    frames, the refined normals 0.92 -> 0.45 deg, the lamps 24 -> 11 mm off, the albedo error
    1.60 -> 1.02 %). A pixel takes the mean of the frames that measure it within
    ``max(STATIC_TOLERANCE_M, STATIC_TOLERANCE_REL * z)`` of their median where at least
    :data:`FILL_MIN_FRACTION` of the frames (and :data:`MIN_FRAMES_FOR_MEDIAN`) do, frame 0's
    holes included (without masks they were cut out of the output as blocks). Elsewhere (near a
    silhouette, where the frames' flying pixels disagree) frame 0's own depth stays, less its
    offset from the mean nearby (a Gaussian of :data:`FILL_OFFSET_SIGMA_PX` depth pixels), so
    that no step forms where the mean ends. A depth map copied into every frame is its own mean.

    depths (n, h, w) metres, 0 = none; frame 0's flying pixels
    (:func:`reference_depth_outliers`) best set to 0 first.
    """
    counts, median, agree = _frames_agreement(depths)
    n = agree.shape[0]
    depths = np.asarray(depths, np.float64)
    k = agree.sum(axis=0)
    use = k >= max(MIN_FRAMES_FOR_MEDIAN, FILL_MIN_FRACTION * n)
    mean = np.where(use, (depths * agree).sum(axis=0) / np.maximum(k, 1), 0.0)
    return blend_into_mean(depths[0], mean, use, FILL_OFFSET_SIGMA_PX), use & ~(depths[0] > 0)
