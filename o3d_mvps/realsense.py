"""Intel RealSense (D415) captures: live recording and reading recordings, native depth kept.

Two ways to a :class:`~o3d_mvps.capture.Capture`:

- :func:`record_capture` streams colour and depth from a connected camera and keeps one sharp
  frame every ``interval`` seconds (or at each key press);
- :func:`read_recording` plays back a recording made with the RealSense Viewer or the SDK.
  pyrealsense2 plays back ROS1 ``.bag`` files (RealSense Viewer, SDKs before 2.59) and ROS2
  ``.db3`` files (the 2.59+ recorder, which refuses ``.bag`` names).

Depth is read raw (z16 times the depth sensor's depth units) in the depth camera and
registered to the colour camera with :func:`o3d_mvps.registration.register_depth` on the grid
colour resolution / SF, never upsampled (DESIGN section 6: ``o3d.t.io.RSBagReader`` aligns at
colour resolution and loses the native low-resolution depth).

Frame selection (:func:`select_frames`): a frame is *blurred* when the variance of the
Laplacian of its grey image is below ``blur_fraction`` times the median over the candidates;
its *overlap* with the reference is estimated from the image translation between the two
(phase correlation of grey thumbnails, checked by normalised cross-correlation):
the fraction of the reference image still covered by the shifted frame, 0 when the views do not
correlate. Frames below ``min_overlap`` are dropped. The first sharp
frame is the reference; the kept frames are spread evenly over the recording.
"""

from __future__ import annotations

import collections
import queue
import sys
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pyrealsense2 as rs

from .capture import Capture, default_depth_intrinsic, image_from_array
from .colour import srgb_to_linear
from .errors import RecordingError
from .registration import register_depth

PLAYBACK_FORMATS = (
    "pyrealsense2 plays back ROS1 .bag recordings (RealSense Viewer, SDKs before 2.59) and "
    "ROS2 .db3 recordings (pyrealsense2 2.59+ recorder)"
)
USB2_BANDWIDTH = 35e6
"""Bytes per second a USB 2 link sustains in practice (480 Mbit/s nominal)."""

_COLOR_BYTES = {rs.format.rgb8: 3, rs.format.bgr8: 3, rs.format.rgba8: 4, rs.format.bgra8: 4, rs.format.yuyv: 2}


# --------------------------------------------------------------------------------------------
# Stream description
# --------------------------------------------------------------------------------------------
@dataclass
class StreamInfo:
    """Colour and depth streams of a device or recording, in numpy form.

    color_K, depth_K: (3, 3) float64 intrinsics in pixels at the native stream resolutions.
    color_size, depth_size: native (width, height). depth_to_color: (4, 4) float64 rigid
    transform from depth-camera to colour-camera coordinates (metres). depth_units: metres per
    z16 unit. sensor: device name and serial. metadata: JSON-serialisable stream details.
    """

    color_K: np.ndarray
    depth_K: np.ndarray
    color_size: tuple[int, int]
    depth_size: tuple[int, int]
    depth_to_color: np.ndarray
    depth_units: float
    sensor: str = "Intel RealSense"
    metadata: dict = field(default_factory=dict)


def _intrinsics_to_numpy(intr) -> tuple[np.ndarray, dict]:
    K = np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]])
    info = {
        "width": int(intr.width), "height": int(intr.height), "fx": float(intr.fx), "fy": float(intr.fy),
        "ppx": float(intr.ppx), "ppy": float(intr.ppy), "model": str(intr.model).split(".")[-1],
        "coeffs": [float(c) for c in intr.coeffs],
    }  # fmt: skip
    return K, info


def extrinsics_to_matrix(extrinsics) -> np.ndarray:
    """4x4 float64 matrix of an ``rs.extrinsics`` (its rotation is stored column-major)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(extrinsics.rotation, dtype=np.float64).reshape(3, 3).T
    T[:3, 3] = np.asarray(extrinsics.translation, dtype=np.float64)
    return T


def _device_info(device) -> dict:
    info = {}
    for key, name in [("name", "name"), ("serial", "serial_number"), ("firmware", "firmware_version"),
                      ("usb", "usb_type_descriptor"), ("product_line", "product_line")]:  # fmt: skip
        which = getattr(rs.camera_info, name)
        try:
            if device.supports(which):
                info[key] = device.get_info(which)
        except RuntimeError:
            pass
    return info


def _sensor_name(dev_info: dict) -> str:
    name = dev_info.get("name", "Intel RealSense")
    return f"{name} (serial {dev_info['serial']})" if dev_info.get("serial") else name


def stream_info(profiles, device, what: str = "recording") -> StreamInfo:
    """Describe the colour and depth streams among ``profiles`` (``rs.stream_profile`` list) of a device.

    Raises
    ------
    RecordingError
        When the colour or the depth stream is missing or has an unsupported format.
    """
    streams = {}
    for s in profiles:
        if s.stream_type() in (rs.stream.color, rs.stream.depth) and s.is_video_stream_profile():
            streams.setdefault(s.stream_type(), s.as_video_stream_profile())
    missing = [name for kind, name in [(rs.stream.color, "colour"), (rs.stream.depth, "depth")] if kind not in streams]
    if missing:
        found = ", ".join(sorted({str(s.stream_type()).split(".")[-1] for s in profiles})) or "none"
        raise RecordingError(
            f"the {what} has no {' and no '.join(missing)} stream (streams found: {found}); "
            "record with both the colour and the depth stream enabled (RealSense Viewer: switch on "
            "'Stereo Module' and 'RGB Camera' before pressing record, or use `o3d-mvps record`)"
        )
    color, depth = streams[rs.stream.color], streams[rs.stream.depth]
    if color.format() not in _COLOR_BYTES:
        raise RecordingError(
            f"the {what}'s colour stream has format {color.format()}; supported: RGB8, BGR8, RGBA8, BGRA8, "
            "YUYV; record colour as RGB8"
        )
    if depth.format() != rs.format.z16:
        raise RecordingError(f"the {what}'s depth stream has format {depth.format()}; record depth as Z16")
    color_K, color_meta = _intrinsics_to_numpy(color.get_intrinsics())
    depth_K, depth_meta = _intrinsics_to_numpy(depth.get_intrinsics())
    try:
        depth_to_color = extrinsics_to_matrix(depth.get_extrinsics_to(color))
    except RuntimeError as err:
        raise RecordingError(
            f"the {what} has no depth-to-colour extrinsics ({err}); it cannot be registered — record "
            "with a RealSense SDK that stores the calibration (any Viewer or SDK 2.x recording does)"
        ) from err
    dev_info = _device_info(device)
    try:
        depth_units = float(device.first_depth_sensor().get_depth_scale())
    except RuntimeError:
        depth_units = 0.001  # the D400 default
        warnings.warn("the depth sensor reports no depth units; assuming 1 mm", stacklevel=2)
    for meta, name in [(color_meta, "colour"), (depth_meta, "depth")]:
        if max(map(abs, meta["coeffs"]), default=0.0) > 1e-3:
            warnings.warn(f"the {name} stream's lens distortion ({meta['model']}) is ignored", stacklevel=2)
    color_meta.update(fps=int(color.fps()), format=str(color.format()).split(".")[-1])
    depth_meta.update(fps=int(depth.fps()), format="z16")
    metadata = dict(dev_info, color_stream=color_meta, depth_stream=depth_meta, depth_units_m=depth_units,
                    depth_to_color=depth_to_color.tolist())  # fmt: skip
    return StreamInfo(
        color_K=color_K, depth_K=depth_K,
        color_size=(color_meta["width"], color_meta["height"]), depth_size=(depth_meta["width"], depth_meta["height"]),
        depth_to_color=depth_to_color, depth_units=depth_units, sensor=_sensor_name(dev_info), metadata=metadata,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Frames to arrays, arrays to a Capture
# --------------------------------------------------------------------------------------------
def color_frame_to_rgb8(frame) -> np.ndarray:
    """(H, W, 3) uint8 sRGB copy of an ``rs.video_frame`` in RGB8, BGR8, RGBA8, BGRA8 or YUYV."""
    frame = frame.as_video_frame()
    fmt = frame.get_profile().format()
    data = np.asanyarray(frame.get_data())
    h, w = frame.get_height(), frame.get_width()
    data = data.reshape(h, w, _COLOR_BYTES[fmt])
    if fmt == rs.format.rgb8:
        return data.copy()
    if fmt == rs.format.bgr8:
        return data[..., ::-1].copy()
    if fmt == rs.format.rgba8:
        return data[..., :3].copy()
    if fmt == rs.format.bgra8:
        return data[..., 2::-1].copy()
    return cv2.cvtColor(np.ascontiguousarray(data), cv2.COLOR_YUV2RGB_YUYV)


def depth_frame_to_z16(frame) -> np.ndarray:
    """(h, w) uint16 copy of a z16 ``rs.depth_frame`` (multiply by the depth units for metres)."""
    frame = frame.as_video_frame()
    return np.asanyarray(frame.get_data()).reshape(frame.get_height(), frame.get_width()).astype(np.uint16, copy=True)


def choose_scale_factor(color_size: tuple[int, int], depth_size: tuple[int, int]) -> int:
    """Super-resolution factor SF for native colour and depth sizes, both (width, height).

    The nearest integer to colour width / depth width (1280x720 colour with 640x360 depth
    gives 2; with 848x480 depth, 2 as well), lowered until it divides both colour sides.
    """
    sf = max(1, int(round(color_size[0] / depth_size[0])))
    while sf > 1 and (color_size[0] % sf or color_size[1] % sf):
        sf -= 1
    return sf


def capture_from_frames(
    colors: list[np.ndarray], depths: list[np.ndarray], info: StreamInfo, scale_factor: int | None = None,
    metadata: dict | None = None,
) -> Capture:  # fmt: skip
    """Build a Capture from native RealSense frames.

    Parameters
    ----------
    colors : list of (H, W, 3) uint8
        sRGB colour frames; decoded to linear float32 with :func:`o3d_mvps.colour.srgb_to_linear`.
    depths : list of (h_d, w_d) uint16
        Raw z16 depth in the depth camera (times ``info.depth_units`` = metres).
    info : StreamInfo
        Intrinsics, extrinsics and depth units of the streams.
    scale_factor : int, optional
        SF; default :func:`choose_scale_factor` of the native sizes. Colour sides must divide by it.
    metadata : dict, optional
        Extra entries stored under ``capture.metadata["realsense"]``.

    Returns
    -------
    Capture
        Colour (H, W, 3) linear, depth (H/SF, W/SF, 1) metres registered to the colour camera,
        depth intrinsics ``default_depth_intrinsic(color_K, SF)``.
    """
    W, H = info.color_size
    sf = choose_scale_factor(info.color_size, info.depth_size) if scale_factor is None else int(scale_factor)
    if sf < 1 or W % sf or H % sf:
        raise RecordingError(f"scale factor {scale_factor} must be a positive integer dividing the colour size {W}x{H}")
    out_size = (W // sf, H // sf)
    color_imgs, depth_imgs = [], []
    for rgb, z16 in zip(colors, depths):
        color_imgs.append(image_from_array(srgb_to_linear(rgb.astype(np.float32) / 255.0)))
        z = register_depth(z16.astype(np.float64) * info.depth_units, info.depth_K, info.color_K,
                           info.depth_to_color, out_size, scale_factor=sf)  # fmt: skip
        depth_imgs.append(image_from_array(z[..., None]))
    meta = dict(info.metadata, scale_factor=sf, **(metadata or {}))
    return Capture(
        color=color_imgs, depth=depth_imgs,
        color_intrinsic=o3d.core.Tensor(info.color_K),
        depth_intrinsic=o3d.core.Tensor(default_depth_intrinsic(info.color_K, sf)),
        depth_scale=1000.0, color_encoding="srgb", sensor=info.sensor, metadata={"realsense": meta},
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Frame selection
# --------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------
# Recordings
# --------------------------------------------------------------------------------------------
def _load_recording(path: Path):
    """The playback device of a recording, set to deliver every frame; RecordingError if unreadable."""
    if not path.exists():
        raise RecordingError(f"recording {str(path)!r} does not exist; {PLAYBACK_FORMATS}")
    if path.is_dir():
        raise RecordingError(f"{str(path)!r} is a folder, not a recording; {PLAYBACK_FORMATS}")
    if path.suffix.lower() not in (".bag", ".db3"):
        raise RecordingError(f"{str(path)!r} is not a RealSense recording (.bag or .db3); {PLAYBACK_FORMATS}")
    if path.stat().st_size == 0:
        raise RecordingError(f"recording {str(path)!r} is empty (0 bytes): it was truncated; record it again")
    try:
        device = rs.context().load_device(str(path))
        playback = device.as_playback()
        playback.set_real_time(False)  # the reader waits for our callbacks: no frame is dropped
        sensors = [s for s in device.query_sensors() if s.get_stream_profiles()]
    except RuntimeError as err:
        raise RecordingError(
            f"cannot play back {str(path)!r}: it is corrupt, truncated or not a RealSense recording "
            f"({err}); {PLAYBACK_FORMATS}"
        ) from err
    if not sensors:
        raise RecordingError(
            f"recording {str(path)!r} contains no streams or no frames; record again with colour and "
            "depth enabled, and stop the recording only after frames were captured"
        )
    return device, playback, sensors


class _PairCollector:
    """Collects (colour, depth) pairs from playback callbacks, keeping every ``step``-th colour frame.

    Each kept colour frame is paired with the depth frame nearest in time among those around it
    (librealsense calls the sensors' callbacks from their own threads, hence the lock). When
    ``cap`` is set, the candidates are halved (and ``step`` doubled) whenever they exceed it.
    """

    def __init__(self, step: int, cap: int | None, max_gap_ms: float):
        self.step, self.cap, self.max_gap_ms = step, cap, max_gap_ms
        self.lock = threading.Lock()
        self.n_color = 0
        self.candidates: list[dict] = []
        self.recent_depth: collections.deque = collections.deque(maxlen=8)
        self.error: BaseException | None = None
        self.last_frame = time.monotonic()

    def __call__(self, frame) -> None:
        try:
            with self.lock:
                self.last_frame = time.monotonic()
                kind = frame.get_profile().stream_type()
                if kind == rs.stream.depth:
                    self._on_depth(float(frame.get_timestamp()), depth_frame_to_z16(frame))
                elif kind == rs.stream.color:
                    self._on_color(frame)
        except BaseException as err:  # raised again by the reading thread
            self.error = err

    def _offer(self, cand: dict, t_depth: float, z16: np.ndarray) -> None:
        gap = abs(t_depth - cand["timestamp_ms"])
        if gap <= self.max_gap_ms and (cand["depth"] is None or gap < cand["gap"]):
            cand["depth"], cand["gap"] = z16, gap

    def _on_depth(self, t: float, z16: np.ndarray) -> None:
        self.recent_depth.append((t, z16))
        for cand in self.candidates[-4:]:
            self._offer(cand, t, z16)

    def _on_color(self, frame) -> None:
        index = self.n_color
        self.n_color += 1
        if index % self.step:
            return
        cand = {
            "index": index, "frame_number": int(frame.get_frame_number()), "timestamp_ms": float(frame.get_timestamp()),
            "rgb": color_frame_to_rgb8(frame), "depth": None, "gap": np.inf,
        }  # fmt: skip
        for t, z16 in self.recent_depth:
            self._offer(cand, t, z16)
        self.candidates.append(cand)
        if self.cap is not None and len(self.candidates) > self.cap:
            self.candidates = [c for c in self.candidates if c["index"] % (2 * self.step) == 0]
            self.step *= 2


def read_recording(
    path, frames: int = 20, stride: int | None = None, scale_factor: int | None = None, *,
    blur_fraction: float = 0.5, min_overlap: float = 0.5, max_candidates: int | None = None,
    progress: bool = False, stall_timeout_s: float = 10.0,
) -> Capture:  # fmt: skip
    """Read a RealSense recording (``.bag`` or ``.db3``) into a Capture at native depth resolution.

    Every frame of the file is played back (not in real time) and every ``stride``-th colour
    frame, paired with the depth frame nearest in time, becomes a candidate; :func:`select_frames`
    then keeps up to ``frames`` sharp candidates overlapping the reference, spread evenly.

    Parameters
    ----------
    path : str or Path
        Recording with a colour (RGB8/BGR8/RGBA8/BGRA8/YUYV) and a Z16 depth stream.
    frames : int
        Number of frames to keep (fewer when fewer are sharp and overlap the reference).
    stride : int, optional
        Consider every ``stride``-th colour frame. Default: automatic, starting at 1 and doubling
        whenever more than ``max_candidates`` candidates are held in memory.
    scale_factor : int, optional
        SF of the registered depth grid (colour size / SF). Default: from the native sizes,
        1280x720 colour with 640x360 depth -> 2.
    blur_fraction, min_overlap : float
        Frame selection thresholds, see :func:`select_frames`.
    max_candidates : int, optional
        Memory bound on candidates for the automatic stride; default ``max(3 * frames, 30)``.
    progress : bool
        Show a tqdm bar (colour frames played back).
    stall_timeout_s : float
        Give up waiting for the playback after this long without a frame (truncated files).

    Returns
    -------
    Capture
        Frame 0 is the reference; ``metadata["realsense"]`` holds the source, device, native
        stream intrinsics, extrinsics, frame numbers and selection scores.

    Raises
    ------
    RecordingError
        Missing, corrupt, truncated or empty recordings, or recordings without colour or depth.
    """
    path = Path(path)
    if stride is not None and int(stride) < 1:
        raise ValueError(f"stride must be a positive integer, got {stride}")
    device, playback, sensors = _load_recording(path)
    info = stream_info([p for s in sensors for p in s.get_stream_profiles()], device, "recording")
    period_ms = 1000.0 / max(1, info.metadata["color_stream"]["fps"])
    collector = _PairCollector(
        1 if stride is None else int(stride),
        (max(3 * frames, 30) if max_candidates is None else int(max_candidates)) if stride is None else None,
        max_gap_ms=1.5 * period_ms,
    )  # fmt: skip
    stopped = threading.Event()
    playback.set_status_changed_callback(lambda status: status == rs.playback_status.stopped and stopped.set())
    bar = _progress(progress, desc="reading recording", unit="frame")
    opened, started = [], []
    try:
        for sensor in sensors:
            sensor.open(sensor.get_stream_profiles())
            opened.append(sensor)
        playback.pause()  # the first sensor started would start playing before the others listen
        for sensor in sensors:
            sensor.start(collector)
            started.append(sensor)
        playback.resume()
        while not stopped.wait(0.1):
            bar.update(collector.n_color - bar.n)
            if time.monotonic() - collector.last_frame > stall_timeout_s:
                warnings.warn(f"{str(path)!r}: playback stalled; using the frames read so far", stacklevel=2)
                break
    except RuntimeError as err:
        raise RecordingError(f"cannot play back {str(path)!r} ({err}); it may be corrupt; {PLAYBACK_FORMATS}") from err
    finally:
        for sensor in started:
            sensor.stop()  # waits for running callbacks
        for sensor in opened:
            sensor.close()
        bar.update(collector.n_color - bar.n)
        bar.close()
    if collector.error is not None:
        raise RecordingError(f"cannot decode a frame of {str(path)!r}: {collector.error}") from collector.error
    candidates = [c for c in collector.candidates if c["depth"] is not None]
    if not candidates:
        raise RecordingError(
            f"recording {str(path)!r} has no frame with both colour and depth: it is empty or truncated; "
            "record again with both streams and stop only after frames were captured"
        )
    choice = select_frames([grey_thumbnail(c["rgb"]) for c in candidates], frames, blur_fraction, min_overlap)
    if len(choice.indices) < frames:
        warnings.warn(
            f"{str(path)!r}: kept {len(choice.indices)} of {frames} frames ({len(candidates)} candidates, "
            f"{len(choice.blurred)} blurred, {len(choice.low_overlap)} with little overlap); "
            "record longer or lower --stride",
            stacklevel=2,
        )
    chosen = [candidates[i] for i in choice.indices]
    meta = {
        "source": str(path), "frame_numbers": [c["frame_number"] for c in chosen],
        "timestamps_ms": [c["timestamp_ms"] for c in chosen],
        "selection": {"stride": collector.step, "candidates": len(candidates), "blur_fraction": blur_fraction,
                      "min_overlap": min_overlap, "sharpness": [choice.sharpness[i] for i in choice.indices],
                      "overlap": [choice.overlap[i] for i in choice.indices]},
    }  # fmt: skip
    return capture_from_frames([c["rgb"] for c in chosen], [c["depth"] for c in chosen], info, scale_factor, meta)


def _progress(enabled: bool, **kwargs):
    from tqdm import tqdm

    return tqdm(disable=not enabled, **kwargs)


# --------------------------------------------------------------------------------------------
# Live devices
# --------------------------------------------------------------------------------------------
def find_device(serial: str | None = None, context=None):
    """The connected RealSense device (the one with ``serial`` if given) of ``context``.

    Raises
    ------
    RecordingError
        No camera (or not the one asked for) is connected.
    """
    devices = list((rs.context() if context is None else context).query_devices())
    if not devices:
        raise RecordingError(
            "no RealSense camera found: connect the D415 with a USB 3 cable to a USB 3 port, check that "
            "`rs-enumerate-devices` or the RealSense Viewer sees it (on Linux install librealsense's udev "
            "rules), or convert an existing recording with `o3d-mvps convert RECORDING OUT`"
        )
    if serial is None:
        return devices[0]
    for device in devices:
        if _device_info(device).get("serial") == serial:
            return device
    found = ", ".join(_device_info(d).get("serial", "?") for d in devices)
    raise RecordingError(f"no RealSense camera with serial {serial} is connected (connected: {found})")


def _video_modes(device, kind, fmt) -> set[tuple[int, int, int]]:
    modes = set()
    for sensor in device.query_sensors():
        for p in sensor.get_stream_profiles():
            if p.stream_type() == kind and p.format() == fmt and p.is_video_stream_profile():
                v = p.as_video_stream_profile()
                modes.add((int(v.width()), int(v.height()), int(p.fps())))
    return modes


def check_modes(device, color_size: tuple[int, int], depth_size: tuple[int, int], fps: int) -> None:
    """Check that the device can stream RGB8 colour and Z16 depth at these sizes and rate.

    Raises
    ------
    RecordingError
        USB 2 links too slow for the modes (connect to USB 3), or sizes/rates the device does
        not offer (the message lists those it does).
    """
    usb = _device_info(device).get("usb", "")
    need = (color_size[0] * color_size[1] * 3 + depth_size[0] * depth_size[1] * 2) * fps
    if usb.startswith("2") and need > USB2_BANDWIDTH:
        raise RecordingError(
            f"the camera is connected over USB {usb}, too slow for {color_size[0]}x{color_size[1]} colour and "
            f"{depth_size[0]}x{depth_size[1]} depth at {fps} fps (~{need / 1e6:.0f} MB/s; USB 2 carries about "
            f"{USB2_BANDWIDTH / 1e6:.0f} MB/s): plug it into a USB 3 port (blue) with a USB 3 cable, or lower "
            "--fps or the resolutions"
        )
    for kind, fmt, size, name in [(rs.stream.color, rs.format.rgb8, color_size, "colour"),
                                  (rs.stream.depth, rs.format.z16, depth_size, "depth")]:  # fmt: skip
        modes = _video_modes(device, kind, fmt)
        if (size[0], size[1], fps) not in modes:
            rates: dict = {}
            for w, h, f in sorted(modes, reverse=True):
                rates.setdefault((w, h), []).insert(0, str(f))
            listing = ", ".join(f"{w}x{h} @ {'/'.join(r)} fps" for (w, h), r in rates.items())
            hint = " (a USB 2 link offers fewer modes: use a USB 3 port and cable)" if usb.startswith("2") else ""
            raise RecordingError(
                f"the camera does not stream {name} at {size[0]}x{size[1]} and {fps} fps{hint}; supported "
                f"{name} modes: {listing or 'none'}"
            )


INSTRUCTIONS = """\
Recording {frames} frames with {sensor}.
  * Switch the LED on and dim the room lights: the LED should light the object.
  * Keep the object 0.5-1 m from the camera, in the middle of the picture.
  * Move slowly around the object (a quarter turn at most), holding still for each shot.
  * {trigger}
"""


def record_capture(
    frames: int = 20, color_size: tuple[int, int] = (1280, 720), depth_size: tuple[int, int] = (640, 360), *,
    fps: int = 30, interval: float | None = 1.0, on_key: bool = False, emitter: bool = True,
    exposure_us: float | None = None, serial: str | None = None, warmup_s: float = 2.0,
    blur_fraction: float = 0.5, min_overlap: float = 0.5, progress: bool = True, out=None,
) -> Capture:  # fmt: skip
    """Record a capture live from a connected RealSense camera.

    A frame is kept every ``interval`` seconds (or at each Enter with ``on_key``): the sharpest
    of a burst of 5 framesets, retried when it is blurred (sharpness below ``blur_fraction``
    times the median of the frames kept so far) or overlaps the first frame less than
    ``min_overlap`` (see :func:`select_frames`). White balance is locked after the warm-up so
    colour gains stay constant (a global exposure change is absorbed by per-frame lighting).

    Parameters
    ----------
    frames : int
        Number of frames to record.
    color_size, depth_size : (int, int)
        Native (width, height) of the RGB8 colour and Z16 depth streams.
    fps : int
        Stream rate.
    interval : float or None
        Seconds between kept frames (ignored with ``on_key``).
    on_key : bool
        Keep a frame at each Enter on stdin; "q" + Enter stops early.
    emitter : bool
        Switch the IR dot projector on (better depth on untextured surfaces).
    exposure_us : float, optional
        Fixed colour exposure in microseconds (auto exposure off); default auto exposure.
    serial : str, optional
        Serial number of the camera to use when several are connected.
    warmup_s : float
        Seconds streamed before the first frame, for auto exposure to settle.
    progress : bool
        Show a tqdm bar and print instructions to ``out`` (default ``sys.stdout``).

    Returns
    -------
    Capture
        As :func:`read_recording`, with ``metadata["realsense"]["source"] == "live"``.

    Raises
    ------
    RecordingError
        No camera, USB 2 bandwidth too low, unsupported modes, or the stream failing.
    """
    context = rs.context()
    device = find_device(serial, context)
    check_modes(device, color_size, depth_size, fps)
    dev_info = _device_info(device)
    config = rs.config()
    if dev_info.get("serial"):
        config.enable_device(dev_info["serial"])
    config.enable_stream(rs.stream.depth, depth_size[0], depth_size[1], rs.format.z16, fps)
    config.enable_stream(rs.stream.color, color_size[0], color_size[1], rs.format.rgb8, fps)
    pipeline = rs.pipeline(context)
    try:
        profile = pipeline.start(config)
    except RuntimeError as err:
        raise RecordingError(
            f"the camera did not start streaming ({err}); unplug it, plug it back in and retry"
        ) from err
    keys = _KeyReader() if on_key else None
    kept, scores, times = [], [], []
    try:
        info = stream_info(profile.get_streams(), profile.get_device(), "camera")
        _set_options(profile.get_device(), emitter, exposure_us)
        trigger = ("Press Enter for each frame, q + Enter to stop." if on_key
                   else f"A frame is taken every {interval:g} s; Ctrl+C stops early.")  # fmt: skip
        if progress:
            text = INSTRUCTIONS.format(frames=frames, sensor=info.sensor, trigger=trigger)
            print(text, file=sys.stdout if out is None else out, flush=True)
        _wait_frames(pipeline, warmup_s)
        _lock_white_balance(profile.get_device())
        bar = _progress(progress, total=frames, desc="recording", unit="frame")
        reference, next_time, pending = None, time.monotonic(), False
        try:
            while len(kept) < frames:
                if keys is not None and not pending:  # a rejected shot is retried without a new key
                    if keys.next_key(pipeline) == "q":
                        break
                    pending = True
                elif keys is None and time.monotonic() < next_time:
                    pipeline.wait_for_frames(5000)
                    continue
                rgb, z16, t = _best_of_burst(pipeline, 5)
                grey = grey_thumbnail(rgb)
                score = sharpness(grey)
                if scores and score < blur_fraction * np.median(scores):
                    bar.write("  blurred: hold the camera still")
                    continue
                if reference is not None and image_overlap(reference, grey) < min_overlap:
                    bar.write("  too far from the first view: move back towards it")
                    continue
                reference = grey if reference is None else reference
                kept.append((rgb, z16))
                scores.append(score)
                times.append(t)
                bar.update()
                next_time, pending = time.monotonic() + (interval or 0.0), False
        except KeyboardInterrupt:
            bar.write("stopped")
        bar.close()
    except RuntimeError as err:
        raise RecordingError(f"the camera stopped delivering frames ({err}); check the USB cable and retry") from err
    finally:
        pipeline.stop()
        if keys is not None:
            keys.close()
    if len(kept) < 2:
        raise RecordingError(f"only {len(kept)} frame(s) recorded; at least 2 are needed — record again")
    meta = {
        "source": "live", "timestamps_ms": times, "emitter": bool(emitter), "exposure_us": exposure_us,
        "selection": {"sharpness": scores, "blur_fraction": blur_fraction, "min_overlap": min_overlap},
    }  # fmt: skip
    return capture_from_frames([k[0] for k in kept], [k[1] for k in kept], info, None, meta)


def _set_options(device, emitter: bool, exposure_us: float | None) -> None:
    depth_sensor = device.first_depth_sensor()
    if depth_sensor.supports(rs.option.emitter_enabled):
        depth_sensor.set_option(rs.option.emitter_enabled, 1.0 if emitter else 0.0)
    if exposure_us is None:
        return
    color_sensor = device.first_color_sensor()
    if not color_sensor.supports(rs.option.exposure):
        raise RecordingError("the colour sensor has no exposure control; record without --exposure")
    value = exposure_us / 100.0  # the RGB sensor's exposure option counts 100 µs units (UVC)
    r = color_sensor.get_option_range(rs.option.exposure)
    if not r.min <= value <= r.max:
        raise RecordingError(
            f"colour exposure {exposure_us:g} µs is out of range; use {r.min * 100:g}..{r.max * 100:g} µs"
        )
    color_sensor.set_option(rs.option.enable_auto_exposure, 0.0)
    color_sensor.set_option(rs.option.exposure, float(value))


def _lock_white_balance(device) -> None:
    try:
        sensor = device.first_color_sensor()
        if sensor.supports(rs.option.enable_auto_white_balance):
            sensor.set_option(rs.option.enable_auto_white_balance, 0.0)
    except RuntimeError:
        warnings.warn("could not lock the colour white balance; colours may drift between frames", stacklevel=2)


def _wait_frames(pipeline, seconds: float) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        pipeline.wait_for_frames(5000)


def _best_of_burst(pipeline, n: int):
    """The sharpest of the next n complete framesets: (rgb8, z16, colour timestamp ms)."""
    best = None
    for _ in range(n * 3):
        frames = pipeline.wait_for_frames(5000)
        color, depth = frames.get_color_frame(), frames.get_depth_frame()
        if not (color and depth):
            continue
        rgb = color_frame_to_rgb8(color)
        score = sharpness(grey_thumbnail(rgb))
        if best is None or score > best[0]:
            best = (score, rgb, depth_frame_to_z16(depth), float(color.get_timestamp()))
        n -= 1
        if n == 0:
            break
    if best is None:
        raise RuntimeError("no frameset with both colour and depth")
    return best[1], best[2], best[3]


class _KeyReader:
    """Lines typed on stdin, read by a daemon thread so that streaming goes on meanwhile."""

    def __init__(self):
        self._lines: queue.Queue = queue.Queue()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        for line in sys.stdin:
            self._lines.put(line.strip().lower())
        self._lines.put("q")  # end of input

    def next_key(self, pipeline) -> str:
        """Keep streaming (the camera's queues must be drained) until a line arrives."""
        while True:
            try:
                return self._lines.get_nowait()
            except queue.Empty:
                pipeline.wait_for_frames(5000)

    def close(self):
        pass  # a daemon thread blocked in readline ends with the process
