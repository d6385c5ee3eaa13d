"""``python -m o3d_mvps`` runs the ``o3d-mvps`` command line."""

import sys

from .cli import main

sys.exit(main())
