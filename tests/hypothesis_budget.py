"""How many examples a Hypothesis property test draws.

`make test` draws each test's full count. `make unit` sets RORY_HYPOTHESIS_SHARE=0.25 and draws
a quarter of it (at least 10), to keep the unit run quick; the full counts stay the reference,
and `make test` runs them on every change."""

from __future__ import annotations

import os

SHARE = float(os.environ.get('RORY_HYPOTHESIS_SHARE') or 1.0)


def examples(full: int) -> int:
    """A property test's max_examples: ``full`` unless a share of it is asked for."""
    if SHARE >= 1.0:
        return full
    return max(10, round(full * SHARE))
