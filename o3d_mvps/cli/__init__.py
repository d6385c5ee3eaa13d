"""The ``o3d-mvps`` command line: one program, one module per subcommand.

Each subcommand module has ``register(subparsers)`` adding its parser with
``set_defaults(handler=run)``, and ``run(args) -> int``. Exit codes: 0 ok, 1 failure (the
message names the fix), 2 usage, 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import importlib
import sys

from ..errors import MVPSError

SUBCOMMANDS = ["demo", "render", "refine", "reconstruct", "export", "record"]
QUIET_HELP = "no progress bars or intermediate logs (the final 'wrote ...' lines are still printed)"
INTERRUPTED = 130  # 128 + SIGINT, the shell's code for a command stopped by Ctrl-C


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="o3d-mvps",
        description="Depth super-resolution and multi-view photometric stereo for an LED-lit RGB-D camera.",
        epilog="exit codes: 0 ok, 1 failure (the message names the fix), 2 usage, 130 interrupted (Ctrl-C)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(f"{__name__}.{name}").register(sub)
    for subparser in sub.choices.values():  # --quiet after the subcommand too; SUPPRESS keeps one given before
        subparser.add_argument("--quiet", action="store_true", default=argparse.SUPPRESS, help=QUIET_HELP)
    return parser


def run_handler(prog: str, run, args) -> int:
    """``run(args)``'s exit code; a failure prints ``PROG: error: message`` and gives 1, Ctrl-C
    prints ``PROG: interrupted`` and gives 130 (outputs are written all or nothing, so an
    interrupted command leaves none)."""
    try:
        return int(run(args) or 0)
    except (MVPSError, OSError, ValueError) as err:
        print(f"{prog}: error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return INTERRUPTED


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return run_handler(f"o3d-mvps {args.command}", args.handler, args)


if __name__ == "__main__":
    sys.exit(main())
