"""Shared plumbing of the pipeline scripts (not a library: the work is done by o3d_mvps)."""

from __future__ import annotations

import argparse

from o3d_mvps.cli import run_handler


def run_main(parser: argparse.ArgumentParser, run, argv=None) -> int:
    """Parse ``argv`` and call ``run(args)``; exit codes as for ``o3d-mvps``: 0 ok, 1 failure
    (``PROG: error: message`` naming the fix), 2 usage, 130 interrupted (Ctrl-C)."""
    return run_handler(parser.prog, run, parser.parse_args(argv))


def say(args, *text) -> None:
    """Print unless ``--quiet``."""
    if not getattr(args, "quiet", False):
        print(*text)
