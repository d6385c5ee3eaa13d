"""Shared plumbing of the pipeline scripts (not a library: the work is done by o3d_mvps)."""

from __future__ import annotations

import argparse

from o3d_mvps.cli import restore_signals, run_handler, stop_on_signals
from o3d_mvps.cli.outputs import quiet_output


def run_main(parser: argparse.ArgumentParser, run, argv=None) -> int:
    """Parse ``argv`` and call ``run(args)``; exit codes as for ``o3d-mvps``: 0 ok, 1 failure
    (``PROG: error: message`` naming the fix), 2 usage, 130 interrupted (Ctrl-C or SIGTERM: one
    line, ended within a second). ``--quiet`` silences warnings, Open3D and Dask as for ``o3d-mvps``."""
    previous = stop_on_signals(parser.prog)
    try:
        args = parser.parse_args(argv)
        with quiet_output(getattr(args, "quiet", False)):
            return run_handler(parser.prog, run, args)
    finally:
        restore_signals(previous)


def say(args, *text) -> None:
    """Print unless ``--quiet``."""
    if not getattr(args, "quiet", False):
        print(*text)
