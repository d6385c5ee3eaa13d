"""``python -m o3d_mvps`` runs the ``o3d-mvps`` command line."""

import os
import signal
import sys


def _interrupted_while_starting(signum, frame):
    """Ctrl-C or SIGTERM before the command line has set its own handlers: nothing to clean up yet."""
    sys.stderr.write("o3d-mvps: interrupted\n")
    sys.stderr.flush()
    os._exit(130)


for _sig in (signal.SIGINT, signal.SIGTERM):
    signal.signal(_sig, _interrupted_while_starting)

from .cli import main  # noqa: E402 - after the handlers

sys.exit(main())
