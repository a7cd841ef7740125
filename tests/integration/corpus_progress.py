"""How many numbers a corpus node (tests/integration/corpus) has applied, read from the state
it publishes on /state: at most as many as it applied, exactly as many once all are in (the
harness's Program.progress, which times Kill(after_applied=...) and ends a run)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def _enum_machine(state: dict[str, Any]) -> int:
    """The numbers it counted and those it skipped while paused (a pause open at its latest
    transition: at least up to it)."""
    applied = state['counted']
    paused_at = None
    for n, phase in state['transitions']:
        if phase == 'paused':
            paused_at = n
        elif paused_at is not None:
            applied += n - paused_at
            paused_at = None
    if paused_at is not None:
        applied = max(applied + 1, paused_at)
    return int(applied)


PROGRESS: dict[str, Callable[[Any], int]] = {
    'closures.py': lambda s: len(s['values']),
    'functional.py': lambda s: s['counter'],
    'dataclass_state.py': lambda s: s['count'],
    'enum_machine.py': _enum_machine,
    'numpy_state.py': lambda s: int(sum(s['histogram'])),
    'message_list.py': lambda s: int(s[-1][0]) if s else 0,  # the last pose's x: its number
    # The Kalman filter's estimate follows the ramp 1, 2, ...: it rounds to the last number.
    'helper_objects.py': lambda s: round(s['x'][0]),
    'kwargs_sub.py': lambda s: len(s['squares']),
    'derived.py': lambda s: s['count'],
}
