"""Target programs are plain script folders (``python targets/amcl/amcl_node.py``), not
packages: their tests import a target's modules with its folder on sys.path, as the program
itself does. Module names start with their folder's name, so folders never clash; the modules
of targets/planar, linked into amcl and lama_local, are one file whichever folder finds them."""

from __future__ import annotations

import sys
from pathlib import Path

TARGETS = Path(__file__).resolve().parents[2] / 'targets'

for folder in sorted(p for p in TARGETS.iterdir() if p.is_dir()):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
