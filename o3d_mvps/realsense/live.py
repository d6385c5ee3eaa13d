"""Recording live from a connected RealSense camera."""

from __future__ import annotations

import queue
import sys
import threading
import warnings
import time

import numpy as np
import pyrealsense2 as rs

from ..capture import Capture
from ..capture.validation import check_light
from ..errors import RecordingError
from .frames import capture_from_frames, color_frame_to_rgb8, depth_frame_to_z16
from .playback import progress_bar
from .selection import grey_thumbnail, image_overlap, sharpness
from .streams import device_info, stream_info

USB2_BANDWIDTH = 35e6
"""Bytes per second a USB 2 link sustains in practice (480 Mbit/s nominal)."""


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
        if device_info(device).get("serial") == serial:
            return device
    found = ", ".join(device_info(d).get("serial", "?") for d in devices)
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
    usb = device_info(device).get("usb", "")
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
    blur_fraction: float = 0.5, min_overlap: float = 0.5, light: str = "led", progress: bool = True, out=None,
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
    light : {"led", "room"}
        What lights the object, written to ``capture.json`` (refine picks its light model from it).
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
    check_light(light, "capture ")
    context = rs.context()
    device = find_device(serial, context)
    check_modes(device, color_size, depth_size, fps)
    dev_info = device_info(device)
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
        bar = progress_bar(progress, total=frames, desc="recording", unit="frame")
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
    return capture_from_frames([k[0] for k in kept], [k[1] for k in kept], info, None, meta, light)


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
