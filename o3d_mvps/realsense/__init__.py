"""Intel RealSense (D415) captures: live recording and reading recordings, native depth kept.

Two ways to a :class:`~o3d_mvps.capture.Capture`:

- :func:`record_capture` streams colour and depth from a connected camera and keeps one sharp
  frame every ``interval`` seconds (or at each key press);
- :func:`read_recording` plays back a recording made with the RealSense Viewer or the SDK.
  pyrealsense2 plays back ROS1 ``.bag`` files (RealSense Viewer, SDKs before 2.59) and ROS2
  ``.db3`` files (the 2.59+ recorder, which refuses ``.bag`` names).

Depth is read raw (z16 times the depth sensor's depth units) in the depth camera and
registered to the colour camera with :func:`o3d_mvps.depth_to_colour.register_depth` on the grid
colour resolution / SF, never upsampled (``o3d.t.io.RSBagReader`` aligns at colour resolution and loses the native
low-resolution depth; docs/capture-guide.md).

Frame selection (:func:`select_frames`): a frame is *blurred* when the variance of the
Laplacian of its grey image is below ``blur_fraction`` times the median over the candidates;
its *overlap* with the reference is estimated from the image translation between the two
(phase correlation of grey thumbnails, checked by normalised cross-correlation):
the fraction of the reference image still covered by the shifted frame, 0 when the views do not
correlate. Frames below ``min_overlap`` are dropped. The first sharp
frame is the reference; the kept frames are spread evenly over the recording.
"""

from .frames import capture_from_frames, color_frame_to_rgb8, depth_frame_to_z16
from .live import check_modes, find_device, record_capture
from .playback import PLAYBACK_FORMATS, read_recording
from .selection import FrameSelection, grey_thumbnail, image_overlap, select_frames, sharpness
from .streams import StreamInfo, extrinsics_to_matrix, stream_info

__all__ = [
    "read_recording", "record_capture", "find_device", "check_modes", "select_frames", "FrameSelection",
    "grey_thumbnail", "sharpness", "image_overlap", "capture_from_frames", "color_frame_to_rgb8",
    "depth_frame_to_z16", "StreamInfo", "stream_info", "extrinsics_to_matrix", "PLAYBACK_FORMATS",
]
