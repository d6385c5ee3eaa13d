"""Reading RealSense recordings (ROS1 .bag, ROS2 .db3) into a capture."""

from __future__ import annotations

import collections
import threading
import warnings
import time
from pathlib import Path

import numpy as np
import pyrealsense2 as rs

from ..capture import Capture
from ..capture.validation import check_light
from ..errors import RecordingError
from .frames import capture_from_frames, color_frame_to_rgb8, depth_frame_to_z16
from .selection import grey_thumbnail, select_frames
from .streams import stream_info

PLAYBACK_FORMATS = (
    "pyrealsense2 plays back ROS1 .bag recordings (RealSense Viewer, SDKs before 2.59) and "
    "ROS2 .db3 recordings (pyrealsense2 2.59+ recorder)"
)


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
    light: str | None = None, progress: bool = False, stall_timeout_s: float = 10.0,
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
    light : {"led", "room"}, optional
        What lit the object, written to ``capture.json`` (refine picks its light model from it;
        without it refine assumes the LED and warns).
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
    check_light(light, "capture ")
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
    bar = progress_bar(progress, desc="reading recording", unit="frame")
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
    return capture_from_frames([c["rgb"] for c in chosen], [c["depth"] for c in chosen], info, scale_factor, meta, light)


def progress_bar(enabled: bool, **kwargs):
    from tqdm import tqdm

    return tqdm(disable=not enabled, **kwargs)
