"""``python -m rory_instrument``: the same as the ``rory-instrument`` command."""

from __future__ import annotations

from rory_instrument.cli import main

raise SystemExit(main())
