"""The node's timers as part of its state (docs/architecture.md, "Timers and the clock").

Which timers a node has, their periods, whether its own code cancelled them, and where their
ticks fall are state as much as its variables: a callback that cancels a publish timer and
makes a one-shot pause timer (ros2/demos' deadline demo) must find the same timers after a
recovery, and a timer that samples its latest inputs must sample them at the same moments.

:class:`NodeTimers` keeps one :class:`AdoptedTimer` per timer the node made, numbered in the
order it made them (a logged tick names its timer by that number). It

* holds each timer until release (cancelled in rcl) without losing what the node's own code
  did to it meanwhile: ``cancel``, ``reset`` and ``destroy`` are wrapped on the timer, so a
  replayed callback that cancels a timer leaves it cancelled after release, and one that makes
  or resets a timer starts it on the grid it had when the callback first ran; a change of
  ``timer_period_ns`` (rclpy's property, patched once per process: :func:`install`) moves the
  grid as rcl does (the next call stays, the new period follows it);
* knows each timer's *grid* (a call time on the timer's own clock, every period from it):
  read from rcl for a running timer, taken from the event's time for a timer made or reset by
  a replayed callback, written into each checkpoint (:meth:`snapshot`) and restored from it
  (:meth:`restore`), where a timer made after start-up is made again;
* at release puts every timer the node's code left running back on its grid
  (:meth:`release`, timer_schedule.py): a tick that fell due while the node was down fires
  once, then the grid goes on.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgpack
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.timer import Timer

from . import event_clock
from .timer_schedule import resume


@dataclass
class AdoptedTimer:
    """One timer of the node, as its own code left it.

    Attributes:
        index: Its number, in the order the node made its timers.
        timer: The rclpy timer.
        callback: The node's own callback (the timer's runs it under the runtime's lock).
        cancelled: The node's code cancelled it (``reset`` undoes that).
        destroyed: The node destroyed it.
        grid_ns: The last point of its grid that fired (or its making, or last reset), on its
            clock: its next call is a period later. None when not known.
        grid_from: Where ``grid_ns`` came from: ``'made'`` (its making in this process, before
            release: the old grid only on a first start), ``'event'`` (made or reset by a
            callback, live or replayed), ``'checkpoint'`` or ``'rcl'`` (read from the timer:
            its next call less a period), ``'tick'`` (a replayed tick's time).
    """

    index: int
    timer: Timer
    callback: Callable[[], Any]
    cancelled: bool = False
    destroyed: bool = False
    grid_ns: int | None = None
    grid_from: str = 'made'

    @property
    def running(self) -> bool:
        """Whether the node's code left it running."""
        return not (self.cancelled or self.destroyed)


_PERIOD_HOOK = '_rory_period_changed'
# rclpy's own property (typed as an overload by its stubs: taken as the property it is).
_rcl_period: property = Timer.__dict__['timer_period_ns']
_installed = False


def install() -> None:
    """Route a change of an adopted timer's ``timer_period_ns`` to its :class:`NodeTimers`
    (idempotent, process-wide). A timer nobody adopted is set as rclpy sets it."""
    global _installed
    if _installed:
        return

    get_rcl, set_rcl = _rcl_period.fget, _rcl_period.fset
    assert get_rcl is not None and set_rcl is not None

    def set_period(timer: Timer, value: int) -> None:
        hook = timer.__dict__.get(_PERIOD_HOOK)
        if hook is None:
            set_rcl(timer, value)
            return
        old = int(get_rcl(timer))
        set_rcl(timer, value)
        hook(old, int(value))

    Timer.timer_period_ns = property(get_rcl, set_period)  # type: ignore[method-assign,assignment]
    _installed = True


def now_on(clock: Clock) -> int:
    """A clock's live time (never a replayed reading)."""
    return int(event_clock.original_now(clock).nanoseconds)


def rcl_grid(timer: Timer) -> int | None:
    """The grid of a timer rcl runs: its next call time, less a period; None if cancelled."""
    if timer.is_canceled():
        return None
    now = now_on(timer.clock)
    return now + int(timer.time_until_next_call() or 0) - int(timer.timer_period_ns)


def rebuild_name(node: object, callback: Callable[[], Any]) -> str | None:
    """The name of the node's method that ``callback`` is, so a checkpoint can make the timer
    again; None for anything else (a lambda, a closure, another object's method)."""
    name = getattr(callback, '__name__', None)
    if getattr(callback, '__self__', None) is node and isinstance(name, str) \
            and getattr(node, name, None) == callback:
        return name
    return None


def where(callback: Callable[[], Any]) -> str:
    """``file:line`` of a callback's definition, for messages."""
    code = getattr(inspect.unwrap(callback), '__code__', None)
    if code is None:
        return repr(callback)
    return f'{code.co_filename}:{code.co_firstlineno}'


class NodeTimers:
    """The node's timers, by number.

    Args:
        released: Whether the node is released (its timers run in rcl).
        error: Reports an error (the runtime's ERROR status).
    """

    def __init__(self, released: Callable[[], bool], error: Callable[[str], None]) -> None:
        self._released = released
        self._error = error
        self.timers: list[AdoptedTimer | None] = []  # None: a number no timer has here (yet)
        self._unbuildable_said: set[int] = set()
        self._at_start = 0  # timers made before start-up; those made later are made again
        self._placing = False  # RORY itself sets periods (restore, release): not the node's code
        install()

    def mark_start(self) -> None:
        """Start-up: timers made from now on are made by callbacks, and a restore makes
        them again (before it restores)."""
        self._at_start = len(self.timers)

    def known(self, timer: Timer) -> bool:
        """Whether ``timer`` is adopted already."""
        return any(t is not None and t.timer is timer for t in self.timers)

    def callback(self, index: int) -> Callable[[], Any] | None:
        """The node's own callback of timer ``index``, None if it has none here."""
        entry = self.timers[index] if index < len(self.timers) else None
        return None if entry is None else entry.callback

    def count(self) -> int:
        """How many numbers are in use (the next timer made gets this one)."""
        return len(self.timers)

    def adopt(self, timer: Timer, callback: Callable[[], Any]) -> AdoptedTimer:
        """Number a timer the node just made and take over its cancel, reset and destroy.

        Not released: it is held (cancelled in rcl); its grid is its making's time, which
        in a replayed callback is that event's recorded time.
        """
        entry = AdoptedTimer(len(self.timers), timer, callback, cancelled=timer.is_canceled())
        self.timers.append(entry)
        if self._released():
            entry.grid_ns, entry.grid_from = rcl_grid(timer), 'rcl'
        else:
            entry.grid_ns = self._event_time(timer)
            entry.grid_from = 'event' if event_clock.active() is not None else 'made'
            if not timer.is_canceled():
                timer.cancel()
        self._wrap(entry)
        return entry

    def _event_time(self, timer: Timer) -> int:
        """When the running event happened on the timer's clock (its making or reset)."""
        clock = timer.clock
        event = event_clock.active()
        if event is not None:
            at = event.event_time(clock)
            if at is not None:
                return at
        return now_on(clock)

    def _wrap(self, entry: AdoptedTimer) -> None:
        timer = entry.timer
        real_cancel: Callable[[], None] = timer.cancel
        real_reset: Callable[[], None] = timer.reset
        real_destroy: Callable[[], None] = timer.destroy

        def cancel() -> None:
            entry.cancelled = True
            real_cancel()

        def reset() -> None:
            entry.cancelled = False
            if self._released():
                real_reset()
                entry.grid_ns = rcl_grid(timer)
            else:
                entry.grid_ns = self._event_time(timer)  # held until release, then its grid
            entry.grid_from = 'event'

        def destroy() -> None:
            entry.destroyed = True
            real_destroy()

        def period_changed(old: int, new: int) -> None:
            if not self._placing:
                self._period_changed(entry, old, new)

        timer.cancel = cancel  # type: ignore[method-assign]
        timer.reset = reset  # type: ignore[method-assign]
        timer.destroy = destroy  # type: ignore[method-assign]
        timer._rory_reset = real_reset  # type: ignore[attr-defined]
        setattr(timer, _PERIOD_HOOK, period_changed)

    def _period_changed(self, entry: AdoptedTimer, old: int, new: int) -> None:
        """The node's code changed a timer's period. rcl keeps the next call where it was and
        puts every later one a new period after it; a running timer's grid is read from rcl, a
        held one's (a replayed callback's change) is moved here the same way: its next point
        on the old grid after the event, less the new period."""
        if self._released() or entry.grid_ns is None or old <= 0 or new <= 0:
            return
        at = self._event_time(entry.timer)
        grid = entry.grid_ns
        following = grid + old if at < grid else grid + ((at - grid) // old + 1) * old
        entry.grid_ns = following - new

    def ticked(self, index: int, tick_ns: int) -> None:
        """A replayed tick of timer ``index`` ran at ``tick_ns`` on its clock: its grid's
        point at or before it has fired, so the release waits for the next one. A timer whose
        grid no checkpoint or event gave (the replay method) takes the tick's time as its grid,
        to within the executor's lateness then."""
        entry = self.timers[index] if index < len(self.timers) else None
        if entry is None:
            return
        period = int(entry.timer.timer_period_ns)
        if entry.grid_from == 'made' or entry.grid_ns is None or period <= 0:
            entry.grid_ns, entry.grid_from = tick_ns, 'tick'
        elif tick_ns >= entry.grid_ns:
            entry.grid_ns += (tick_ns - entry.grid_ns) // period * period

    # -- checkpoints -------------------------------------------------------------------------

    def snapshot(self, node: object) -> bytes:
        """Every timer's state, for the checkpoint (under the runtime's lock, released)."""
        records: list[dict[str, Any] | None] = []
        for entry in self.timers:
            if entry is None:
                records.append(None)
                continue
            timer = entry.timer
            grid = entry.grid_ns
            if entry.running and self._released():
                grid = rcl_grid(timer) if not timer.is_canceled() else grid
            name = rebuild_name(node, entry.callback)
            # Attributes that hold a timer made by a callback are bound to it again when a
            # restore makes it again (``self.pause_timer = self.create_timer(...)``).
            attrs = ([] if entry.index < self._at_start or not entry.running else
                     [k for k, v in getattr(node, '__dict__', {}).items() if v is timer])
            records.append({
                'period_ns': int(timer.timer_period_ns) if not entry.destroyed else 0,
                'clock': int(timer.clock.clock_type) if not entry.destroyed else 0,
                'cancelled': entry.cancelled,
                'destroyed': entry.destroyed,
                'grid_ns': grid,
                'callback': name,
                'attrs': attrs,
            })
        packed: bytes = msgpack.packb(records)
        return packed

    def unbuildable(self, node: object) -> list[str]:
        """Timers made after start-up that a restore could not make again, as messages
        naming where their callback is (each said once)."""
        lines = []
        for entry in self.timers[self._at_start:]:
            if entry is None or not entry.running or entry.index in self._unbuildable_said:
                continue
            if rebuild_name(node, entry.callback) is None:
                self._unbuildable_said.add(entry.index)
                lines.append(
                    f'timer {entry.index} (callback at {where(entry.callback)}) was made after '
                    'start-up and its callback is not a method of the node: a recovery cannot '
                    'make it again')
        return lines

    def restore(self, data: bytes, node: Any) -> None:
        """Set each timer as the checkpoint had it; make again those made after start-up.

        Raises:
            ValueError: ``data`` is not a timers record.
        """
        records = msgpack.unpackb(data)
        if not isinstance(records, list):
            raise ValueError('timers: not a list')
        for index, record in enumerate(records):
            if record is None:
                continue
            if not isinstance(record, dict):
                raise ValueError(f'timers: record {index} is not a map')
            entry = self.timers[index] if index < len(self.timers) else None
            if entry is None and not record.get('destroyed'):
                entry = self._make_again(index, record, node)
            if entry is None:
                continue
            if record.get('destroyed'):
                node.destroy_timer(entry.timer)
                continue
            entry.cancelled = bool(record.get('cancelled'))
            period = int(record.get('period_ns') or 0)
            if period > 0 and period != int(entry.timer.timer_period_ns):
                self._set_period(entry.timer, period)
            grid = record.get('grid_ns')
            if isinstance(grid, int):
                entry.grid_ns, entry.grid_from = grid, 'checkpoint'
        while len(self.timers) < len(records):
            self.timers.append(None)  # the next timer made gets the number it had

    def _set_period(self, timer: Timer, period_ns: int) -> None:
        """Set a period as RORY, not as the node's code (the grid is RORY's to place)."""
        self._placing = True
        try:
            timer.timer_period_ns = period_ns
        finally:
            self._placing = False

    def _make_again(self, index: int, record: dict[str, Any], node: Any) -> AdoptedTimer | None:
        name = record.get('callback')
        callback = getattr(node, name, None) if isinstance(name, str) else None
        if callback is None:
            self._error(f'the checkpoint has timer {index}, made after start-up, whose callback '
                        'is not a method of the node: it is not made again')
            return None
        while len(self.timers) < index:
            self.timers.append(None)  # numbers of timers the node made and this one has not
        clock_type = int(record.get('clock') or int(ClockType.ROS_TIME))
        clock = None if clock_type == int(ClockType.ROS_TIME) else Clock(
            clock_type=ClockType(clock_type))
        period_s = int(record.get('period_ns') or 0) / 1e9
        timer = node.create_timer(period_s, callback, clock=clock)  # adopted as ``index``
        attrs = record.get('attrs')
        for name in attrs if isinstance(attrs, list) else []:
            if isinstance(name, str) and name.isidentifier():
                setattr(node, name, timer)
        return self.timers[index] if index < len(self.timers) else None

    # -- release ------------------------------------------------------------------------------

    def release(self, post: Callable[[Callable[[], Any]], None]) -> None:
        """Start every timer the node's code left running, on its grid; a tick that fell due
        while the node was down is handed to ``post`` (run once on the executor)."""
        for entry in self.timers:
            if entry is None or not entry.running:
                continue
            timer = entry.timer
            real_reset: Callable[[], None] = timer._rory_reset  # type: ignore[attr-defined]
            grid = entry.grid_ns  # its last point that fired (or its making)
            period = int(timer.timer_period_ns)
            if grid is None or period <= 0:
                real_reset()
                continue
            now = now_on(timer.clock)
            placed = resume(grid, period, now)
            # rcl_timer_reset sets the next call to now + period; with the period exchanged
            # for the distance to the grid's next call and back, the next call is on the grid
            # and every later one a period after it (an exchange leaves the next call alone).
            self._set_period(timer, max(1, placed.next_ns - now))
            real_reset()
            self._set_period(timer, period)
            if placed.fire_now:
                post(timer.callback)
