#!/usr/bin/env python
"""Capture folder that goes around an object -> textured mesh (OBJ) and, optionally, a print solid (STL).

A thin example of the Python API behind ``o3d-mvps reconstruct``: read the capture and its poses
(o3d_mvps.read_capture, read_capture_poses), reconstruct the object (o3d_mvps.reconstruct:
reference views refined as Dask tasks, fused, cleaned, textured from the refined albedos),
write the textured mesh (o3d_mvps.export.write_mesh: mesh.obj + mesh.mtl + mesh_albedo.png)
and the closed solid (Reconstruction.printable_solid, write_stl).
"""

from __future__ import annotations

import argparse
import sys
import warnings
from dataclasses import replace
from pathlib import Path

from _common import run_main, say

import o3d_mvps
from o3d_mvps.capture import read_capture, read_capture_poses
from o3d_mvps.cli.argtypes import positive_float, positive_int
from o3d_mvps.cli.outputs import add_overwrite_argument, check_folder
from o3d_mvps.cli.refine import add_solver_arguments, options_from_args
from o3d_mvps.export import write_mesh, write_stl
from o3d_mvps.fileio import atomic_folder
from o3d_mvps.reconstruct import ReconstructOptions

EXAMPLES = """examples:
  python pipelines/reconstruct_object.py ring/ object/
  python pipelines/reconstruct_object.py ring/ object/ --references 12 --print 80 --workers 4
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="reconstruct_object.py", description=__doc__, epilog=EXAMPLES,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("capture", type=Path, help="capture folder whose frames go around the object")
    parser.add_argument("out", type=Path, help="output folder (mesh.obj, mesh.mtl, mesh_albedo.png, print.stl)")
    parser.add_argument("--poses", default=None, metavar="FILE", help="pose file (default: the capture's, else registration)")
    parser.add_argument("--references", type=positive_int, default=ReconstructOptions.references,
                        help="reference views refined and fused (default: %(default)s)")
    parser.add_argument("--depth", choices=("refined", "raw"), default="refined",
                        help="fuse refined depth, or the sensor's (for comparison)")
    parser.add_argument("--print", dest="print_mm", type=positive_float, default=None, metavar="MM",
                        help="also write print.stl, a closed solid MM millimetres across")
    parser.add_argument("--workers", type=positive_int, default=None, help="local Dask workers (default: CPU count)")
    add_overwrite_argument(parser, "output folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or logs")
    add_solver_arguments(parser)
    return parser


def run(args) -> int:
    check_folder(args.out, args.overwrite, "output folder", inputs=[args.capture])  # before the slow work
    capture = read_capture(args.capture)
    given = read_capture_poses(args.capture, args.poses)
    options = ReconstructOptions(references=args.references, depth=args.depth, workers=args.workers,
                                 refine=replace(options_from_args(args), progress=False), progress=not args.quiet)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = o3d_mvps.reconstruct(capture, options, poses=None if given is None else given[0])
    for w in caught:
        say(args, f"warning: {w.message}")
    with atomic_folder(args.out, overwrite=args.overwrite, what="output folder") as tmp:
        write_mesh(result.mesh, tmp / "mesh.obj")
        if args.print_mm is not None:
            write_stl(result.printable_solid(args.print_mm), tmp / "print.stl")
    say(args, f"mesh: {result.info['vertices']} vertices, {result.info['triangles']} triangles, "
              f"textured: {result.info['textured']}; references {result.info['references']}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(build_parser(), run))
