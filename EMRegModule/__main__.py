"""``python -m EMRegModule`` is the ``emreg`` command."""

import sys

from .cli.main import run

sys.exit(run())
