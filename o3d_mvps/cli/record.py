"""``o3d-mvps record`` (live, from a RealSense camera) and ``o3d-mvps convert`` (a recording).

Both write a capture folder (layout in docs/capture-guide.md and ``o3d_mvps.capture``) with
depth registered to the colour camera at the sensor's native resolution (colour / SF), ready
for ``o3d-mvps refine``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..capture import write_capture
from ..capture.layout import CAPTURE_LIGHTS
from .argtypes import image_size, positive_float, positive_int
from .outputs import add_overwrite_argument, check_folder

RECORD_EXAMPLES = """\
examples:
  o3d-mvps record capture/                               # 20 frames, one a second
  o3d-mvps record capture/ --frames 30 --interval 0.5 --exposure 8000
  o3d-mvps record capture/ --on-key --color 1920x1080 --depth 1280x720
"""

CONVERT_EXAMPLES = """\
examples:
  o3d-mvps convert recording.db3 capture/                # pyrealsense2 2.59+ recording
  o3d-mvps convert viewer.bag capture/ --frames 30 --stride 5
"""


def add_recording_arguments(group, frames_flag: str = "--frames") -> None:
    """Camera options shared by ``o3d-mvps record`` and pipelines/record_and_refine.py.

    ``frames_flag`` names the frame count (dest ``record_frames``) where ``--frames`` is taken.
    """
    group.add_argument(frames_flag, dest="record_frames", type=positive_int, default=20, metavar="N",
                       help="number of frames to record (default 20)")
    group.add_argument("--color", type=image_size, default=(1280, 720), metavar="WxH",
                       help="colour size (default 1280x720)")
    group.add_argument("--depth", type=image_size, default=(640, 360), metavar="WxH",
                       help="depth size (default 640x360)")
    group.add_argument("--fps", type=positive_int, default=30, help="stream rate (default 30)")
    when = group.add_mutually_exclusive_group()
    when.add_argument("--interval", type=positive_float, default=1.0, metavar="S",
                      help="seconds between frames (default 1)")
    when.add_argument("--on-key", action="store_true", help="take a frame at each Enter (q + Enter stops)")
    group.add_argument("--emitter", choices=["on", "off"], default="on", help="IR dot projector (default on)")
    group.add_argument("--exposure", type=positive_float, metavar="US",
                       help="fixed colour exposure in microseconds (default auto)")
    group.add_argument("--serial", help="serial number of the camera when several are connected")
    group.add_argument("--light", choices=CAPTURE_LIGHTS, default="led",
                       help="what lights the object, written to capture.json for refine's light model: the LED on "
                       "the camera (default) or room light")


def register(subparsers) -> None:
    rec = subparsers.add_parser(
        "record",
        help="record a capture live with a RealSense D415",
        description="Record a capture with a connected RealSense camera (an LED attached to it) and write the "
        "capture folder OUT. Move slowly around the object, 0.5-1 m away, LED on, room lights dim.",
        epilog=RECORD_EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    rec.add_argument("out", metavar="OUT", type=Path, help="capture folder to write")
    add_recording_arguments(rec)
    add_overwrite_argument(rec, "capture folder")
    rec.set_defaults(handler=run)

    conv = subparsers.add_parser(
        "convert",
        help="convert a RealSense recording (.bag, .db3) into a capture folder",
        description="Read a RealSense recording (.bag from the RealSense Viewer or older SDKs, .db3 from "
        "pyrealsense2 2.59+), keep sharp, overlapping frames and write the capture folder OUT with depth at "
        "its native resolution.",
        epilog=CONVERT_EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    conv.add_argument("recording", metavar="RECORDING", type=Path, help=".bag or .db3 recording")
    conv.add_argument("out", metavar="OUT", type=Path, help="capture folder to write")
    conv.add_argument("--frames", type=positive_int, default=20, metavar="N",
                      help="number of frames to keep from the recording (default 20)")
    conv.add_argument("--stride", type=positive_int, metavar="K", help="consider every K-th frame (default automatic)")
    conv.add_argument(
        "--scale-factor", type=positive_int, metavar="SF", help="depth grid = colour / SF (default: from the sizes)"
    )
    conv.add_argument("--light", choices=CAPTURE_LIGHTS,
                      help="what lit the object, written to capture.json for refine's light model: the LED on the "
                      "camera or room light (default: not written; refine then assumes the LED and warns)")
    add_overwrite_argument(conv, "capture folder")
    conv.set_defaults(handler=run_convert)


def run(args) -> int:
    from ..realsense import record_capture

    check_folder(args.out, args.overwrite, "capture folder")
    capture = record_capture(
        args.record_frames, args.color, args.depth, fps=args.fps, interval=args.interval, on_key=args.on_key,
        emitter=args.emitter == "on", exposure_us=args.exposure, serial=args.serial, light=args.light,
        progress=not args.quiet,
    )  # fmt: skip
    write_capture(capture, args.out, overwrite=args.overwrite)
    _report(args, capture)
    return 0


def run_convert(args) -> int:
    from ..realsense import read_recording

    check_folder(args.out, args.overwrite, "capture folder", inputs=[args.recording])
    capture = read_recording(args.recording, frames=args.frames, stride=args.stride, scale_factor=args.scale_factor,
                             light=args.light, progress=not args.quiet)  # fmt: skip
    write_capture(capture, args.out, overwrite=args.overwrite)
    _report(args, capture)
    return 0


def _report(args, capture) -> None:
    (H, W), (h, w) = capture.color_size, capture.depth_size
    print(f"wrote {capture.n_frames} frames to {args.out} (colour {W}x{H}, depth {w}x{h}, SF {capture.scale_factor})")
