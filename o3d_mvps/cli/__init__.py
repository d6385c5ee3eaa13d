"""The ``o3d-mvps`` command line: one program, one module per subcommand.

Each subcommand module has ``register(subparsers)`` adding its parser with
``set_defaults(handler=run)``, and ``run(args) -> int``. Exit codes: 0 ok, 1 failure, 2 usage.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from ..errors import MVPSError

SUBCOMMANDS = ["demo", "render", "refine", "export", "record", "bench"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="o3d-mvps",
        description="Depth super-resolution and multi-view photometric stereo for an LED-lit RGB-D camera.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars or logs")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as err:
            if err.name != f"{__name__}.{name}":
                raise
            continue
        module.register(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except (MVPSError, OSError, ValueError) as err:
        print(f"o3d-mvps {args.command}: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
