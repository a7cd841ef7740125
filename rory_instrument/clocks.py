"""Clock reads RORY cannot replay: ``time.time()`` and the like, found with file:line:col.

Inside a callback RORY logs and replays what rclpy clocks return (docs/architecture.md,
"Timers and the clock"); the standard library's clocks it cannot see. Reading one is not an
error (a node may use it for logging or timeouts), so ``rory-instrument`` warns and goes on.
``time.perf_counter`` is left out: it measures durations, it does not say when.
"""

from __future__ import annotations

from dataclasses import dataclass

import libcst as cst
from libcst.metadata import MetadataWrapper, PositionProvider, QualifiedNameProvider

# Qualified names of the calls that read wall or monotonic time outside rclpy.
WALL_CLOCK_READS = frozenset(
    {
        'time.time',
        'time.time_ns',
        'time.monotonic',
        'time.monotonic_ns',
        'datetime.datetime.now',
        'datetime.datetime.utcnow',
        'datetime.datetime.today',
        'datetime.date.today',
    }
)


@dataclass(frozen=True)
class ClockRead:
    """One call of a clock RORY cannot replay."""

    line: int
    column: int  # 1-based, as editors count
    name: str


class WallClockReads(cst.CSTVisitor):
    """Collects the calls of :data:`WALL_CLOCK_READS`, by qualified name (aliases too)."""

    METADATA_DEPENDENCIES = (QualifiedNameProvider, PositionProvider)

    def __init__(self) -> None:
        super().__init__()
        self.found: list[ClockRead] = []

    def visit_Call(self, node: cst.Call) -> None:
        names = self.get_metadata(QualifiedNameProvider, node.func, set())
        for qualified in sorted(names, key=lambda q: q.name):
            if qualified.name in WALL_CLOCK_READS:
                start = self.get_metadata(PositionProvider, node).start
                self.found.append(ClockRead(start.line, start.column + 1, qualified.name))
                return


def wall_clock_warnings(wrapper: MetadataWrapper, display: str) -> tuple[str, ...]:
    """One warning line per clock read RORY cannot replay, ``file:line:col: warning: ...``."""
    visitor = WallClockReads()
    wrapper.visit(visitor)
    return tuple(
        f'{display}:{read.line}:{read.column}: warning: {read.name}() is read directly; RORY '
        'cannot replay it after a crash (in a callback, read self.get_clock().now())'
        for read in visitor.found
    )
