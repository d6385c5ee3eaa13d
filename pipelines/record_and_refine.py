#!/usr/bin/env python
"""Record a capture with a RealSense D415 (an LED taped next to the colour lens), refine it, mesh it.

Writes OUT/capture/ (the recording as a capture folder), OUT/refined/ and OUT/mesh.obj
(+ .mtl + albedo texture). Move slowly around the object, 0.5-1 m away, LED on, room lights
dim; the first frame is the view that is refined. Without a camera it stops with the
RecordingError message naming the fix (exit code 1).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from _common import run_main, say

from o3d_mvps import refine, write_capture
from o3d_mvps.cli.argtypes import image_size, positive_int
from o3d_mvps.cli.refine import add_solver_arguments, log_energy, options_from_args
from o3d_mvps.errors import OutputExistsError
from o3d_mvps.export import write_mesh
from o3d_mvps.fileio import atomic_folder

EXAMPLES = """examples:
  python pipelines/record_and_refine.py out/scan
  python pipelines/record_and_refine.py out/scan --frames 20 --interval 1.5 --color 1280x720 --depth 640x360
  python pipelines/record_and_refine.py out/scan --on-key      # Enter keeps a frame, q + Enter stops
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="record_and_refine.py", description=__doc__, epilog=EXAMPLES,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="output folder: capture/, refined/, mesh.obj")
    rec = parser.add_argument_group("recording")
    rec.add_argument("--record-frames", type=positive_int, default=20, metavar="N", help="frames to record (default 20)")
    rec.add_argument("--color", type=image_size, default=(1280, 720), metavar="WxH", help="colour size (default 1280x720)")
    rec.add_argument("--depth", type=image_size, default=(640, 360), metavar="WxH", help="depth size (default 640x360)")
    rec.add_argument("--fps", type=positive_int, default=30, help="stream rate (default 30)")
    when = rec.add_mutually_exclusive_group()
    when.add_argument("--interval", type=float, default=1.0, metavar="S", help="seconds between frames (default 1)")
    when.add_argument("--on-key", action="store_true", help="take a frame at each Enter (q + Enter stops)")
    rec.add_argument("--emitter", choices=["on", "off"], default="on", help="IR dot projector (default on)")
    rec.add_argument("--exposure", type=float, metavar="US", help="fixed colour exposure in microseconds")
    rec.add_argument("--serial", help="serial number of the camera when several are connected")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or logs")
    add_solver_arguments(parser)
    return parser


def run(args) -> int:
    from o3d_mvps.realsense import record_capture

    if args.out.exists() and not args.overwrite and (not args.out.is_dir() or any(args.out.iterdir())):
        raise OutputExistsError(f"{args.out} already exists and is not empty; choose another folder or pass --overwrite")
    capture = record_capture(args.record_frames, args.color, args.depth, fps=args.fps, interval=args.interval,
                             on_key=args.on_key, emitter=args.emitter == "on", exposure_us=args.exposure,
                             serial=args.serial, progress=not args.quiet)
    say(args, f"recorded {capture.n_frames} frames; refining ...")
    refinement = refine(capture, options_from_args(args))
    log_energy(refinement, args.quiet)
    with atomic_folder(args.out, overwrite=args.overwrite, what="output folder") as tmp:
        write_capture(capture, tmp / "capture")
        refinement.save(tmp / "refined")
        write_mesh(refinement.to_mesh(), tmp / "mesh.obj")
    say(args, f"wrote {args.out}/capture, {args.out}/refined, {args.out}/mesh.obj")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(build_parser(), run))
