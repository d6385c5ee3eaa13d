"""Cross-checks of a capture's inputs before the solve: intrinsics, depth scale, frame quality, poses.

Each check is cheap (coarse grids, a few statistics per frame) and either passes, warns, or
raises :class:`~o3d_mvps.errors.CaptureError` naming the file or value and the fix, so that a
mix-up does not end in a confident wrong result. :func:`check_inputs` runs them all and
returns an :class:`InputReport` (``info["inputs"]`` and ``info["frames_report"]`` of a
refinement). The pose checks' geometry is :mod:`.pose_checks`.

=====================  ===========================================================  ==========
check                  what is compared                                             outcome
=====================  ===========================================================  ==========
intrinsics             K not transposed; principal point inside the image (and      error
                       not the centre of another resolution); fx / fy near 1; the
                       field of view plausible (the sensor's, when capture.json
                       names a D415)
depth scale            median depth within :data:`SENSOR_RANGE_M`; names the        error
                       ``depth_scale`` that would fit
frame quality          black, saturated or blurred frames (against the others);     warning, frame dropped
                       a frame that repeats an earlier one exactly                  (error for the reference);
                       frames over-exposed in part (:data:`OVEREXPOSED`)            kept, with a warning
frame count            at least :data:`MIN_FRAMES` usable frames (unless fewer      error
                       were asked for on purpose, ``RefineOptions.frames``)
colour/depth           depth discontinuities line up with colour edges (coarse      warning
alignment              cross-correlation over small shifts)
poses                  each frame's depth, moved by its pose, on the reference's;   error naming the
                       the usual mix-ups tried (:mod:`.pose_checks`)                mix-up and its fix;
                                                                                    a few frames placed
                                                                                    by no pose: warning,
                                                                                    dropped
=====================  ===========================================================  ==========
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import CaptureError
from ..model.resampling import resize
from .pose_checks import check_poses
from .types import default_depth_intrinsic

#: Plausible median scene depth in metres for an RGB-D camera (a D415 measures 0.16-10 m).
SENSOR_RANGE_M = (0.1, 10.0)
#: depth_scale values that tools write (units per metre): metres, 0.1 mm, mm, TUM's 5000, ...
COMMON_DEPTH_SCALES = (1.0, 10.0, 100.0, 1000.0, 4000.0, 5000.0, 10000.0, 100000.0)
#: Plausible horizontal field of view of a colour camera (degrees); and a D415's colour camera's.
FOV_RANGE_DEG = (20.0, 110.0)
D415_FOV_DEG = (50.0, 80.0)  # 69 at 1280x720, 55 in the 640x480 mode
#: Largest accepted fx / fy deviation from 1 (RGB-D cameras have square pixels).
ASPECT_TOLERANCE = 0.2
#: A principal point farther than this share of the size from the centre is suspicious.
CENTRE_TOLERANCE = 0.2
#: Frame quality: mean linear intensity below BLACK is black; more than SATURATED of the
#: pixels at >= 0.99 is saturated; a blur (:func:`blur_effect`, 0 sharp .. 1 flat) above the
#: frames' median by more than BLURRED is blurred (renders: sharp 0.26-0.42; a Gaussian blur of
#: 2 px per 320 px of width: 0.52-0.92).
BLACK, SATURATED, BLURRED = 0.01, 0.3, 0.15
#: A frame kept with more than this share of its pixels at >= 0.99 is over-exposed, with a
#: warning: a clipped pixel reads dimmer than its light (renders: 0-0.3 % as lit; the bunny at
#: 0.25 m under the LED: 5-9 %, and on a 2 MP render with 15 % of the object clipped the normals
#: came out 1.38 deg against 1.13 unclipped).
OVEREXPOSED = 0.02
#: Frames uncalibrated photometric stereo needs: the reference and two more
#: (:data:`o3d_mvps.covisibility.MIN_OTHER_FRAMES`).
MIN_FRAMES = 3
#: Widest grid the image statistics are taken on (pixels).
STATS_WIDTH = 640


@dataclass
class InputReport:
    """What the checks found. checks: rows {"name", "status" ("ok"|"warning"|"error"),
    "detail"}; conventions: the pose conventions found (JSON-ready); frames: rows {"index",
    "file", "used", "reason"}, one per frame checked; usable: indices (into the checked capture)
    of the frames to refine with, the reference first."""

    checks: list = field(default_factory=list)
    conventions: dict = field(default_factory=dict)
    frames: list = field(default_factory=list)
    usable: list = field(default_factory=list)

    def add(self, name: str, status: str, detail: str) -> None:
        self.checks.append({"name": name, "status": status, "detail": detail})
        if status == "warning":
            warnings.warn(f"{name}: {detail}", stacklevel=4)

    def to_dict(self) -> dict:
        """``info["inputs"]``: {"checks", "conventions"}."""
        return {"checks": self.checks, "conventions": self.conventions}


def check_inputs(capture, given_poses=None, *, frames: list | None = None, frames_asked: bool = False,
                 where: str | None = None, pose_trust: tuple | None = (0.0, 0.0)) -> InputReport:
    """Run every check on a capture (its frames ``frames`` of the original capture, the reference first).

    Parameters
    ----------
    capture : Capture
        The frames to refine with (already picked), frame 0 the reference.
    given_poses : GivenPoses or None
        Initial poses as given, one per frame of the original capture (checked against depth).
    frames : list of int or None
        Original indices of ``capture``'s frames (default 0..n-1), for messages and reports.
    frames_asked : bool
        The user asked for this many frames (``RefineOptions.frames``): fewer than
        :data:`MIN_FRAMES` is then allowed (the single-frame baseline).
    where : str or None
        The capture folder, for messages (default: ``capture.folder``).
    pose_trust : (metres, radians) or None
        How far the refinement may move ``given_poses`` (None: freely); see :func:`check_poses`.

    Returns
    -------
    InputReport

    Raises
    ------
    CaptureError
        A check failed; the message names the file or value and the fix.
    """
    n = capture.n_frames
    frames = list(range(n)) if frames is None else [int(i) for i in frames]
    names = capture.frame_names or [None] * n
    ids = frames if capture.frame_ids is None else [capture.frame_id(k) for k in range(n)]  # as the user knows it
    labels = [f"frame {ids[k]}" + (f" ({names[k]})" if names[k] else "") for k in range(n)]
    report = InputReport(frames=[{"index": frames[k], "file": names[k], "used": True, "reason": None}
                                 for k in range(n)])
    where = where or capture.folder
    folder = f"{where}/" if where else ""
    check_intrinsics(capture.color_K(), capture.color_size, f"{folder}intrinsic.json (colour intrinsics)",
                     capture.sensor)
    check_intrinsics(capture.depth_K(), capture.depth_size, f"{folder}depth_intrinsic.json (or the colour "
                                                            "intrinsics scaled to depth)", None, fov=False)
    report.add("intrinsics", "ok", "K upright, principal point near the centre, square pixels, plausible field of "
                                   f"view ({field_of_view_deg(capture.color_K(), capture.color_size):.0f} degrees)")
    registered = default_depth_intrinsic(capture.color_K(), capture.scale_factor)
    off = np.abs(capture.depth_K()[:2] - registered[:2]).max()
    if off > 0.02 * capture.depth_size[1]:
        report.add("depth intrinsics", "warning",
                   f"{folder}depth_intrinsic.json differs from the colour intrinsics scaled by 1/{capture.scale_factor} "
                   f"by up to {off:.3g} px ({np.round(capture.depth_K(), 2).tolist()} against "
                   f"{np.round(registered, 2).tolist()}): depth registered to the colour camera shares its "
                   "intrinsics; remove depth_intrinsic.json, or register the depth first "
                   "(o3d_mvps.depth_to_colour.register_depth)")
    median = check_depth_scale(capture, folder)
    report.add("depth scale", "ok", f"median depth {median:.3g} m")
    usable = check_frame_quality(capture, labels, report)
    if len(usable) < MIN_FRAMES and not frames_asked:
        raise CaptureError(
            f"{where + ': ' if where else ''}only {len(usable)} usable frame(s) "
            f"({', '.join(labels[k] for k in usable)}); uncalibrated "
            f"photometric stereo needs at least {MIN_FRAMES} (the reference and {MIN_FRAMES - 1} more, from "
            "different viewpoints): capture more frames. To refine fewer on purpose (the single-frame baseline), "
            "ask for them: --frames 1 (RefineOptions(frames=1))")
    alignment(capture, report)
    if given_poses is not None:
        picked = [frames[k] for k in usable]
        pose = check_poses([capture.depth_array(k) for k in usable], capture.depth_K(), given_poses, picked,
                           [labels[k] for k in usable], 1 if frames_asked else MIN_FRAMES, pose_trust)
        report.add("poses", pose.status, pose.detail)
        report.conventions["poses"] = {**pose.conventions,
                                       "frame_agreement": {str(i): a for i, a in zip(picked, pose.agreement)}}
        for j, why in pose.dropped.items():  # j indexes usable
            report.frames[usable[j]].update(used=False, reason=why)
        usable = [k for j, k in enumerate(usable) if j not in pose.dropped]
    report.usable = usable
    return report


def field_of_view_deg(K: np.ndarray, size) -> float:
    """Horizontal field of view (degrees) of intrinsics K (3, 3) on an (H, W) image."""
    return float(np.degrees(2 * np.arctan(size[1] / (2 * K[0, 0]))))


def check_intrinsics(K: np.ndarray, size, what: str, sensor: str | None = None, *, fov: bool = True) -> None:
    """CaptureError unless K (3, 3) is upright, its principal point near the centre of an (H, W)
    image, its pixels square and (``fov``) its field of view plausible; ``what`` names the file."""
    H, W = size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if np.any(K[2, :2] != 0) or K[2, 2] != 1 or K[1, 0] != 0:
        hint = (" It looks transposed (cx, cy in the bottom row): Open3D's intrinsic.json stores the matrix "
                "column-major, [fx, 0, 0, 0, fy, 0, cx, cy, 1]; write it with o3d.io.write_pinhole_camera_intrinsic"
                if np.allclose(K[:2, 2], 0) else " The last row must be 0 0 1")
        raise CaptureError(f"{what}: intrinsic matrix {np.round(K, 3).tolist()} is not [[fx, 0, cx], [0, fy, cy], "
                           f"[0, 0, 1]].{hint}")
    if not (0 <= cx <= W - 1 and 0 <= cy <= H - 1) or (abs(cx - (W - 1) / 2) > CENTRE_TOLERANCE * W
                                                      or abs(cy - (H - 1) / 2) > CENTRE_TOLERANCE * H):
        other = (int(round(2 * cx + 1)), int(round(2 * cy + 1)))
        inside = 0 <= cx <= W - 1 and 0 <= cy <= H - 1
        same_shape = other[0] > 0 and other[1] > 0 and abs(other[0] / other[1] - W / H) < 0.03 * W / H
        hint = (f" The principal point is the centre of {other[0]}x{other[1]} images: these intrinsics belong to "
                f"that resolution; for {W}x{H} frames scale them by {W / other[0]:.4g} "
                "(o3d_mvps.model.camera.scale_intrinsics) or use the intrinsics of the mode the frames were "
                "recorded in" if same_shape else
                " Use the intrinsics of the camera mode the frames were recorded in (cx near W/2, cy near H/2)")
        raise CaptureError(f"{what}: principal point cx={cx:g}, cy={cy:g} is "
                           f"{'far from the centre of' if inside else 'outside'} the {W}x{H} image.{hint}")
    if abs(fx / fy - 1) > ASPECT_TOLERANCE:
        raise CaptureError(f"{what}: fx={fx:g} and fy={fy:g} differ by a factor {fx / fy:.3g}; RGB-D cameras have "
                           "square pixels (fx = fy within a few %): one of them is wrong (halved or doubled?); use "
                           "the calibrated intrinsics of the mode the frames were recorded in")
    if not fov:
        return
    angle = field_of_view_deg(K, size)
    d415 = bool(sensor) and "d415" in sensor.lower()
    low, high = D415_FOV_DEG if d415 else FOV_RANGE_DEG
    if not low <= angle <= high:
        sensor_note = " (a D415 colour camera: 69)" if d415 else ""
        raise CaptureError(f"{what}: fx={fx:g} gives a horizontal field of view of {angle:.0f} degrees on {W}-pixel-"
                           f"wide frames, outside {low:g}-{high:g} degrees{sensor_note}; the focal length is wrong "
                           f"(scaled for another resolution?): fx near {W / (2 * np.tan(np.radians(69 / 2))):.0f} px "
                           "gives 69 degrees")


def check_depth_scale(capture, folder: str = "") -> float:
    """The reference's median depth (m); CaptureError naming ``depth_scale`` and the value that
    would fit when it lies outside :data:`SENSOR_RANGE_M`."""
    z = capture.depth_array(0)
    median = float(np.median(z[z > 0]))
    lo, hi = SENSOR_RANGE_M
    if lo <= median <= hi:
        return median
    raw = median * capture.depth_scale  # the stored units
    fits = min(COMMON_DEPTH_SCALES, key=lambda s: abs(np.log(raw / s)))  # nearest to 1 m
    fix = (f"depth_scale {capture.depth_scale:g} in {folder or ''}capture.json is probably wrong: with depth_scale "
           f"{fits:g} the median would be {raw / fits:.3g} m" if lo <= raw / fits <= hi else
           f"check depth_scale ({capture.depth_scale:g}) in capture.json and the depth files' unit")
    raise CaptureError(f"{folder}depth: the median depth of the reference is {median:.3g} m, implausible for an "
                       f"RGB-D camera ({lo:g}-{hi:g} m): {fix}")


def frame_statistics(color: np.ndarray) -> tuple[float, float, float]:
    """(mean, saturated fraction, :func:`blur_effect`) of an (H, W, 3) linear RGB frame, on a grid
    at most :data:`STATS_WIDTH` wide."""
    H, W = color.shape[:2]
    if W > STATS_WIDTH:
        color = cv2.resize(color, (STATS_WIDTH, H * STATS_WIDTH // W), interpolation=cv2.INTER_AREA)
    r, g, b = cv2.split(np.asarray(color, dtype=np.float32))
    grey = (r + g + b) / 3
    brightest = cv2.max(cv2.max(r, g), b)
    return float(grey.mean()), float(np.count_nonzero(brightest >= 0.99)) / brightest.size, blur_effect(grey)


def blur_effect(grey: np.ndarray, size: int = 9) -> float:
    """Blur of a grey image, 0 (sharp) .. 1 (blurred or flat): the share of its differences
    between neighbours that survive a further ``size``-pixel box blur, the larger of the two
    directions (Crete-Roffet et al. 2007, "The blur effect"); independent of brightness and
    of how much texture a frame sees."""
    out = []
    for axis, kernel in ((0, (1, size)), (1, (size, 1))):
        reblurred = cv2.blur(grey, kernel)
        d = np.abs(np.diff(grey, axis=axis))
        lost = np.maximum(0.0, d - np.abs(np.diff(reblurred, axis=axis)))
        out.append(float((d.sum() - lost.sum()) / max(d.sum(), 1e-12)))
    return max(out)


def check_frame_quality(capture, labels: list, report: InputReport) -> list:
    """Indices of the frames fit to use; black, saturated and blurred ones are dropped with a
    warning (their rows in ``report.frames`` say why); a bad reference is a CaptureError."""
    stats = np.array([frame_statistics(capture.color_array(k)) for k in range(capture.n_frames)])
    typical = float(np.median(stats[:, 2]))
    copies = duplicate_frames(capture, stats)
    usable, dropped = [], []
    for k, (mean, saturated, blur) in enumerate(stats):
        why = None
        if k in copies:
            why = (f"a copy of {labels[copies[k]]} (the same colour and depth, so no new view nor light): remove the "
                   "copy from the capture")
        elif mean < BLACK:
            why = f"black (mean intensity {mean:.2%})"
        elif saturated > SATURATED:
            why = f"saturated ({saturated:.0%} of the pixels clipped)"
        elif capture.n_frames >= 3 and blur > typical + BLURRED:
            why = f"blurred (blur {blur:.2f}, the frames' median {typical:.2f})"
        if why is None:
            usable.append(k)
            continue
        if k == 0:
            raise CaptureError(f"the reference {labels[0]} is {why}: the refinement is computed in the reference "
                               "view, so it must be a good frame. Retake it, or remove it so that the next frame "
                               "becomes the reference")
        dropped.append(f"{labels[k]}: {why}")
        report.frames[k].update(used=False, reason=why)
    bright = [k for k in usable if stats[k, 1] > OVEREXPOSED]
    exposure = ""
    if bright:
        worst = max(bright, key=lambda k: stats[k, 1])
        which = (f"{labels[worst]} kept over-exposed ({stats[worst, 1]:.0%} of its pixels clipped)" if len(bright) == 1
                 else f"{len(bright)} frames kept over-exposed ({stats[bright, 1].min():.0%}-{stats[worst, 1]:.0%} of "
                      f"their pixels clipped, the most in {labels[worst]})")
        exposure = (f"{which}: a clipped pixel reads dimmer than its light, which biases the light, the poses and the "
                    "normals; retake with a shorter exposure or a dimmer LED")
    if dropped:
        report.add("frame quality", "warning", f"dropped {len(dropped)} frame(s): {'; '.join(dropped)}"
                   + (f"; {exposure}" if exposure else ""))
    elif exposure:
        report.add("frame quality", "warning", exposure)
    else:
        report.add("frame quality", "ok", f"{capture.n_frames} frames, none black, saturated, over-exposed or blurred")
    return usable


def duplicate_frames(capture, stats: np.ndarray) -> dict:
    """{k: j} for each frame k whose colour and depth equal an earlier frame j's, exactly (a frame
    written twice). Only frames with the same :func:`frame_statistics` (``stats``, (n, 3)) are
    compared pixel for pixel."""
    copies = {}
    for k in range(1, len(stats)):
        for j in range(k):
            if j not in copies and np.array_equal(stats[j], stats[k]) and np.array_equal(
                    capture.color_array(j), capture.color_array(k)) and np.array_equal(
                    capture.depth_array(j), capture.depth_array(k)):
                copies[k] = j
                break
    return copies


def alignment(capture, report: InputReport, shift: int = 3) -> None:
    """Warn when the reference's colour edges line up with its depth discontinuities better at a
    shift of a few depth pixels than at none (depth not registered to the colour camera)."""
    z = capture.depth_array(0).astype(np.float64)
    valid = z > 0
    h, w = z.shape
    grey = resize(capture.color_array(0).mean(axis=2), (h, w)).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        logz = np.where(valid, np.log(np.where(valid, z, 1.0)), 0.0)
    gz = np.hypot(*np.gradient(logz))
    gz[~valid] = 0
    gz = np.minimum(gz, 0.2)  # a jump to no depth counts like a large jump
    gc = np.hypot(*np.gradient(grey / max(grey.mean(), 1e-6)))
    inner = (slice(shift, h - shift), slice(shift, w - shift))
    a = gz[inner] - gz[inner].mean()
    scores = {}
    for dy in range(-shift, shift + 1):
        for dx in range(-shift, shift + 1):
            b = gc[shift + dy:h - shift + dy, shift + dx:w - shift + dx]
            b = b - b.mean()
            scores[(dx, dy)] = float((a * b).sum() / max(np.sqrt((a * a).sum() * (b * b).sum()), 1e-12))
    best = max(scores, key=scores.get)
    zero = scores[(0, 0)]
    if best != (0, 0) and max(abs(best[0]), abs(best[1])) >= 2 and scores[best] > 0.2 and scores[best] > 1.5 * zero:
        report.add("colour/depth alignment", "warning",
                   f"the reference's colour edges match its depth edges best {best[0]:+d}, {best[1]:+d} depth "
                   f"pixels away (correlation {scores[best]:.2f}, {zero:.2f} in place): is depth registered to the "
                   "colour camera? (o3d_mvps.depth_to_colour.register_depth)")
    else:
        report.add("colour/depth alignment", "ok", f"colour and depth edges line up (correlation {zero:.2f})")


def check_given_poses(capture, given) -> dict:
    """:func:`.pose_checks.check_poses` of all of a capture's frames against its frame 0 (e.g. a
    ring before it is split into references); the conventions found (CaptureError on a mix-up; a
    warning naming the few frames the poses do not place, which the views' own checks then drop)."""
    n = capture.n_frames
    labels = [capture.frame_label(k) for k in range(n)]
    found = check_poses([capture.depth_array(k) for k in range(n)], capture.depth_K(), given, list(range(n)),
                        labels, MIN_FRAMES)
    if found.dropped:
        warnings.warn(f"poses: {found.detail}", stacklevel=2)
    return found.conventions
