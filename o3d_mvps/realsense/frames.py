"""RealSense frames to numpy arrays, and native frames to a :class:`~o3d_mvps.capture.Capture`."""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d
import pyrealsense2 as rs

from ..capture import Capture, default_depth_intrinsic, image_from_array
from ..capture.validation import check_light
from ..colour import srgb_to_linear
from ..errors import CaptureError, RecordingError
from ..model.sensor import choose_scale_factor
from ..depth_to_colour import register_depth
from .streams import COLOR_BYTES, StreamInfo


def color_frame_to_rgb8(frame) -> np.ndarray:
    """(H, W, 3) uint8 sRGB copy of an ``rs.video_frame`` in RGB8, BGR8, RGBA8, BGRA8 or YUYV."""
    frame = frame.as_video_frame()
    fmt = frame.get_profile().format()
    data = np.asanyarray(frame.get_data())
    h, w = frame.get_height(), frame.get_width()
    data = data.reshape(h, w, COLOR_BYTES[fmt])
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


def capture_from_frames(
    colors: list[np.ndarray], depths: list[np.ndarray], info: StreamInfo, scale_factor: int | None = None,
    metadata: dict | None = None, light: str | None = None,
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
        SF; default :func:`o3d_mvps.model.sensor.choose_scale_factor` of the native sizes (the nearest
        integer to the width ratio dividing the colour size). Colour sides must divide by it.
    metadata : dict, optional
        Extra entries stored under ``capture.metadata["realsense"]``.
    light : {"led", "room"}, optional
        What lit the frames (``Capture.light``; refine picks its light model from it).

    Returns
    -------
    Capture
        Colour (H, W, 3) linear, depth (H/SF, W/SF, 1) metres registered to the colour camera,
        depth intrinsics ``default_depth_intrinsic(color_K, SF)``.
    """
    check_light(light, "capture ")
    W, H = info.color_size
    try:  # sizes (width, height) here, (rows, columns) in the shared rule
        sf = choose_scale_factor((H, W), info.depth_size[::-1], scale_factor)
    except CaptureError as err:
        raise RecordingError(str(err)) from None
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
        depth_scale=1000.0, color_encoding="srgb", sensor=info.sensor, metadata={"realsense": meta}, light=light,
    )  # fmt: skip
