"""Stream description of a RealSense device or recording: intrinsics, extrinsics, depth units."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import pyrealsense2 as rs

from ..errors import RecordingError

COLOR_BYTES = {rs.format.rgb8: 3, rs.format.bgr8: 3, rs.format.rgba8: 4, rs.format.bgra8: 4, rs.format.yuyv: 2}


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


def device_info(device) -> dict:
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
    if color.format() not in COLOR_BYTES:
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
    dev_info = device_info(device)
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
