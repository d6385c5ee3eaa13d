#!/usr/bin/env python
"""Capture folder -> print-ready binary STL (a watertight solid in millimetres).

Refines the capture (frame 0 is the view that is printed), closes the refined relief into a
solid with a flat back plate (o3d_mvps.export.printable_solid), checks it is watertight and
writes it (o3d_mvps.export.write_stl). Optionally keeps the refinement folder too.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from _common import run_main, say

from o3d_mvps import read_capture, refine
from o3d_mvps.cli.argtypes import deprecated_alias, positive_float, positive_int
from o3d_mvps.cli.outputs import add_overwrite_argument, check_files, check_folder
from o3d_mvps.cli.refine import add_solver_arguments, log_energy, options_from_args
from o3d_mvps.export import DEFAULT_SIZE_MM, PIECES, printable_solid, write_stl

EXAMPLES = """examples:
  python pipelines/print_scan.py capture/ scan.stl
  python pipelines/print_scan.py capture/ scan.stl --print 80 --base-mm 3 --pieces all --save-refined refined/
"""


def _stl_path(text: str) -> Path:
    path = Path(text)
    if path.suffix.lower() != ".stl":
        raise argparse.ArgumentTypeError(f"{text!r}: the output is a binary STL; name it *.stl")
    return path


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="print_scan.py", description=__doc__, epilog=EXAMPLES,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("capture", type=Path, help="capture folder (color/, depth/, intrinsic.json, ...)")
    parser.add_argument("out", type=_stl_path, help="output .stl file")
    solid = parser.add_argument_group("print-ready solid")
    solid.add_argument("--print", dest="size_mm", type=positive_float, default=DEFAULT_SIZE_MM, metavar="MM",
                       help="largest bounding-box extent of the solid in millimetres, as o3d-mvps export/reconstruct "
                            "--print MM (default: %(default)s)")
    solid.add_argument("--size-mm", dest="size_mm", type=positive_float, metavar="MM",
                       action=deprecated_alias("--print MM"), help="deprecated spelling of --print MM")
    solid.add_argument("--base-mm", type=positive_float, default=4.0, metavar="MM",
                       help="back plate thickness behind the deepest point (default: %(default)s)")
    solid.add_argument("--pieces", choices=PIECES, default="largest",
                       help="keep the largest connected piece or all pieces (default: %(default)s)")
    solid.add_argument("--max-triangles", type=positive_int, metavar="N",
                       help="simplify the relief to at most N triangles")
    parser.add_argument("--save-refined", type=Path, metavar="DIR", help="also write the refinement folder")
    add_overwrite_argument(parser, "output file or folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or logs")
    add_solver_arguments(parser)
    return parser


def run(args) -> int:
    check_files([args.out], args.overwrite, inputs=[args.capture])  # fail before the (slow) refinement
    if args.save_refined is not None:
        check_folder(args.save_refined, args.overwrite, "refinement folder", inputs=[args.capture])
    capture = read_capture(args.capture)
    refinement = refine(capture, options_from_args(args))
    log_energy(refinement, args.quiet)
    solid = printable_solid(refinement, size_mm=args.size_mm, base_mm=args.base_mm, pieces=args.pieces,
                            max_triangles=args.max_triangles)
    write_stl(solid, args.out, overwrite=args.overwrite)
    if args.save_refined is not None:
        refinement.save(args.save_refined, overwrite=args.overwrite)
    say(args, f"solid: {len(solid.triangle.indices)} triangles, {args.size_mm:g} mm")
    print(f"wrote {args.out}" + ("" if args.save_refined is None else f" and {args.save_refined}"))
    return 0


if __name__ == "__main__":
    sys.exit(run_main(build_parser(), run))
