#!/usr/bin/env python
"""Capture folder -> refined folder, textured mesh and accuracy report.

Writes OUT/refined/ (depth, normals, albedo, poses, lighting, report.json; see
o3d_mvps.Refinement.save), OUT/mesh.obj (+ .mtl + albedo texture) and OUT/report.md
(energy per level, timings and, for synthetic captures, the accuracy table against the
baselines). OUT is written all or nothing.

The same solver arguments as `o3d-mvps refine`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from _common import run_main, say

from o3d_mvps import read_capture, refine
from o3d_mvps.cli.outputs import add_overwrite_argument, check_folder
from o3d_mvps.cli.refine import add_solver_arguments, log_energy, options_from_args
from o3d_mvps.export import write_mesh
from o3d_mvps.fileio import atomic_folder
from o3d_mvps.report import accuracy_rows, markdown_table

EXAMPLES = """examples:
  python pipelines/refine_capture.py captures/bunny out/bunny
  python pipelines/refine_capture.py capture/ out/scan --frames 10 --tau 100 --overwrite
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="refine_capture.py", description=__doc__, epilog=EXAMPLES,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("capture", type=Path, help="capture folder (color/, depth/, intrinsic.json, ...)")
    parser.add_argument("out", type=Path, help="output folder: refined/, mesh.obj, report.md")
    add_overwrite_argument(parser, "output folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or logs")
    add_solver_arguments(parser)
    return parser


def report_text(capture_path, refinement, rows) -> str:
    """report.md: settings, energy per level, timings and the accuracy table (if any)."""
    last = {row["level"]: row for row in refinement.energy}
    lines = [f"# Refinement of {capture_path}", "", f"frames: {refinement.info['frames']}", "",
             "| level | sweeps | energy |", "|---:|---:|---:|"]
    lines += [f"| {lv} | {r['iteration']} | {r['energy']:.6g} |" for lv, r in sorted(last.items(), reverse=True)]
    lines += ["", "time: " + ", ".join(f"{k} {v:.1f} s" for k, v in refinement.timings.items()), ""]
    if rows:
        lines += [markdown_table(rows), ""]
    return "\n".join(lines)


def run(args) -> int:
    check_folder(args.out, args.overwrite, "output folder", inputs=[args.capture])
    capture = read_capture(args.capture)
    refinement = refine(capture, options_from_args(args))
    log_energy(refinement, args.quiet)
    rows = []
    if capture.groundtruth is not None:
        rows = accuracy_rows(capture.select(refinement.info["frames"]), refinement)
        say(args, markdown_table(rows))
    with atomic_folder(args.out, overwrite=args.overwrite, what="output folder") as tmp:
        refinement.save(tmp / "refined", extra_report={"accuracy": rows} if rows else None)
        write_mesh(refinement.to_mesh(), tmp / "mesh.obj")
        (tmp / "report.md").write_text(report_text(args.capture, refinement, rows))
    print(f"wrote {args.out}/refined, {args.out}/mesh.obj, {args.out}/report.md")
    return 0


if __name__ == "__main__":
    sys.exit(run_main(build_parser(), run))
