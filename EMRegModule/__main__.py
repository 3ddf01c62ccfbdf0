"""``python -m EMRegModule`` is the ``emreg`` command."""

import sys

from .cli import main

sys.exit(main())
