"""``python -m sim ...``: the same as ``rory sim ...``."""

from __future__ import annotations

import sys

from .cli import main

sys.exit(main())
