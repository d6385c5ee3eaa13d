"""``o3d-mvps bench ...``: the benchmarks of a source checkout (``python -m benchmarks``).

The benchmarks live in the repository's ``benchmarks/`` folder, next to the package, and are
not installed with it; this subcommand finds them beside an editable install (``make``
installs the package that way) and passes every argument on.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import MVPSError

CHECKOUT = Path(__file__).resolve().parents[2]
EXAMPLES = """examples:
  o3d-mvps bench accuracy --quick
  o3d-mvps bench speed
  o3d-mvps bench all            # everything, into benchmarks/results/ (tens of minutes)
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("bench", help="run the benchmarks (source checkout)", description=__doc__,
                              epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("args", nargs=argparse.REMAINDER, help="arguments of python -m benchmarks (try: --help)")
    p.set_defaults(handler=run)


def run(args) -> int:
    if not (CHECKOUT / "benchmarks" / "__main__.py").is_file():
        raise MVPSError(f"no benchmarks/ folder beside the package in {CHECKOUT}: the benchmarks ship with the "
                        "source checkout; clone the repository and run 'make bench' there")
    sys.path.insert(0, str(CHECKOUT))
    from benchmarks.__main__ import main as bench_main

    try:
        return bench_main(args.args or ["--help"])
    except SystemExit as stop:  # argparse's --help and usage errors
        return int(stop.code or 0)
