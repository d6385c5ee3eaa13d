"""Shared plumbing of the pipeline scripts (not a library: the work is done by o3d_mvps)."""

from __future__ import annotations

import argparse
import sys

from o3d_mvps.errors import MVPSError


def run_main(parser: argparse.ArgumentParser, run, argv=None) -> int:
    """Parse ``argv``, call ``run(args)``; on a failure print ``PROG: error: message``, return 1.

    Exit codes as for ``o3d-mvps``: 0 ok, 1 failure (the message names the fix), 2 usage.
    """
    args = parser.parse_args(argv)
    try:
        return int(run(args) or 0)
    except (MVPSError, OSError, ValueError) as err:
        print(f"{parser.prog}: error: {err}", file=sys.stderr)
        return 1


def say(args, *text) -> None:
    """Print unless ``--quiet``."""
    if not getattr(args, "quiet", False):
        print(*text)
