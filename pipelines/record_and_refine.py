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
from o3d_mvps.cli.outputs import add_overwrite_argument, check_folder
from o3d_mvps.cli.record import add_recording_arguments
from o3d_mvps.cli.refine import add_solver_arguments, log_energy, options_from_args
from o3d_mvps.export import write_mesh
from o3d_mvps.fileio import atomic_folder

EXAMPLES = """examples:
  python pipelines/record_and_refine.py out/scan
  python pipelines/record_and_refine.py out/scan --record-frames 20 --interval 1.5 --color 1280x720 --depth 640x360
  python pipelines/record_and_refine.py out/scan --on-key      # Enter keeps a frame, q + Enter stops

--record-frames N records N frames; --frames N (a solver option, as in o3d-mvps refine) then
refines with the first N of them.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="record_and_refine.py", description=__doc__, epilog=EXAMPLES,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="output folder: capture/, refined/, mesh.obj")
    add_recording_arguments(parser.add_argument_group("recording"), frames_flag="--record-frames")
    add_overwrite_argument(parser, "output folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or logs")
    add_solver_arguments(parser)
    return parser


def run(args) -> int:
    from o3d_mvps.realsense import record_capture

    check_folder(args.out, args.overwrite, "output folder")
    capture = record_capture(args.record_frames, args.color, args.depth, fps=args.fps, interval=args.interval,
                             on_key=args.on_key, emitter=args.emitter == "on", exposure_us=args.exposure,
                             serial=args.serial, light=args.light, progress=not args.quiet)
    say(args, f"recorded {capture.n_frames} frames; refining ...")
    refinement = refine(capture, options_from_args(args))
    log_energy(refinement, args.quiet)
    with atomic_folder(args.out, overwrite=args.overwrite, what="output folder") as tmp:
        write_capture(capture, tmp / "capture")
        refinement.save(tmp / "refined")
        write_mesh(refinement.to_mesh(), tmp / "mesh.obj")
    print(f"wrote {args.out}/capture, {args.out}/refined, {args.out}/mesh.obj")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(build_parser(), run))
