"""``python -m EMRegModule`` is the ``emreg`` command."""

import sys

from .cli import run

sys.exit(run())
