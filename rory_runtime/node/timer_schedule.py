"""Where a node's timer goes on after a recovery: on the grid it kept before the crash.

An rcl timer's ticks fall on a grid: its first call time (creation or last reset, plus one
period) and every period after it, on the timer's own clock. A stalled executor does not move
the grid: an overdue timer is ready at once, fires **once**, and its next call time advances by
whole periods. A recovered node's timers do the same (docs/architecture.md, "Timers and the
clock"): from a point of the old grid (the last tick the log or the checkpoint recorded, or the
time it was made or reset), :func:`resume` says whether a tick fell due while the node was
down (it fires once, at release) and where the next tick of the grid after now falls.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Resume:
    """How one timer goes on at release.

    Attributes:
        fire_now: A tick fell due while the node was down: it fires once, at release.
        next_ns: The grid's next call time after now, on the timer's clock.
    """

    fire_now: bool
    next_ns: int


def resume(grid_ns: int, period_ns: int, now_ns: int) -> Resume:
    """The timer's next call on the grid through ``grid_ns`` (a tick, or the time it was made
    or reset) with ``period_ns``, at ``now_ns`` on its clock.

    A clock that stands still (simulation time before its next /clock) is not past the next
    tick, so nothing fires until it moves; a clock that went back (a simulation restarted) is
    before the grid point: the timer waits one period from now, as rcl would after a reset.
    """
    if period_ns <= 0:
        return Resume(False, now_ns)
    if now_ns < grid_ns:
        return Resume(False, now_ns + period_ns)
    due = grid_ns + period_ns
    if now_ns < due:
        return Resume(False, due)
    passed = (now_ns - grid_ns) // period_ns
    return Resume(True, grid_ns + (passed + 1) * period_ns)
