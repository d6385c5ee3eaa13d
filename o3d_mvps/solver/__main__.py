"""``python -m o3d_mvps.solver PROBLEM.npz OUT.npz``: solve a saved problem, without Open3D."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from ..cli import restore_signals, run_handler, stop_on_signals
from ..cli.outputs import add_overwrite_argument, check_files, log_energy, print_summary
from ..run_report import peak_memory_mb, summarise
from .device import DEVICE_HELP, resolve_device
from .driver import solve
from .problem_input import SAVE_HOW, read_problem
from .solution import ENERGY_COLUMNS, write_solution

PROG = "python -m o3d_mvps.solver"
DESCRIPTION = f"""\
Solve a problem saved by `{SAVE_HOW}`
and write the solution to OUT.npz: depth (H, W) metres, mask, albedo (H, W, 3), K,
lighting (n, k), poses (n, 4, 4), energy (m, 4: {", ".join(ENERGY_COLUMNS)})
and report (JSON: energy rows, timings, info). Needs NumPy, SciPy, OpenCV and pyamg, not Open3D.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("problem", help="saved problem (.npz)")
    parser.add_argument("out", help="solution file to write (.npz)")
    parser.add_argument("--device", default="auto", help=DEVICE_HELP)
    add_overwrite_argument(parser, "solution file")
    parser.add_argument("--quiet", action="store_true", help="no progress bars or energy log")
    return parser


def run(args) -> int:
    (out,) = check_files([args.out], args.overwrite, inputs=[args.problem])
    device, device_line = resolve_device(args.device)
    problem_input = read_problem(args.problem)
    if not args.quiet:
        print(device_line)
    output = solve(problem_input, replace(problem_input.options, progress=not args.quiet), device)
    log_energy(output, args.quiet)
    write_solution(output, out, overwrite=args.overwrite)
    frames = [{"used": True} for _ in output.info.get("frames", [])]
    print_summary(summarise({"energy": output.energy, "timings": output.timings, "frames": frames,
                             "peak_memory_mb": peak_memory_mb(), "warnings": []}), args.quiet)
    print(f"wrote {out}")
    return 0


def main(argv=None) -> int:
    previous = stop_on_signals(PROG)
    try:
        return run_handler(PROG, run, build_parser().parse_args(argv))
    finally:
        restore_signals(previous)


if __name__ == "__main__":
    sys.exit(main())
