"""The node's timers as state (node/timers.py): what its code did to them survives holding and
replay, each goes back on its grid at release, a checkpoint keeps them and a restore makes
again those made after start-up. Driven with stand-ins of rclpy's timers on a simulated clock.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
from rclpy.clock import ROSClock
from rclpy.clock_type import ClockType
from rclpy.context import Context
from rclpy.node import Node
from rclpy.time import Time
from runtime_fakes import FakeTimer

from rory_runtime.node.timers import NodeTimers

S = 1_000_000_000


def _clock(ns: int) -> ROSClock:
    clock = ROSClock()
    clock._set_ros_time_is_active(True)
    clock.set_ros_time_override(Time(nanoseconds=ns, clock_type=ClockType.ROS_TIME))
    return clock


def _set(clock: ROSClock, ns: int) -> None:
    clock.set_ros_time_override(Time(nanoseconds=ns, clock_type=ClockType.ROS_TIME))


class Talker:
    """The shape of ros2/demos' deadline talker: a publish timer a callback cancels, and a
    pause timer it makes, whose expiry publishes, resets the publish timer and destroys itself.
    Its create_timer adopts like the runtime's patched one."""

    def __init__(self, timers: NodeTimers, clock: ROSClock) -> None:
        self.timers = timers
        self.clock = clock
        self.log: list[str] = []
        self.pause_timer: FakeTimer | None = None
        self.publish_timer = self.create_timer(S / 1e9 / 2, self.publish)

    def create_timer(self, period_s: float, callback: Callable[[], Any],
                     clock: Any = None) -> FakeTimer:
        timer = FakeTimer(callback, self.clock, timer_period_ns=int(period_s * 1e9))
        timer.reset()  # rcl starts a timer at its making
        self.timers.adopt(timer, callback)
        return timer

    def destroy_timer(self, timer: FakeTimer) -> None:
        timer.destroy()

    def publish(self) -> None:
        self.log.append('publish')

    def pause_for(self) -> None:
        self.publish_timer.cancel()
        self.pause_timer = self.create_timer(3.0, self._pause_expired)

    def _pause_expired(self) -> None:
        self.publish()
        self.publish_timer.reset()
        assert self.pause_timer is not None
        self.destroy_timer(self.pause_timer)
        self.pause_timer = None


def _timers(released: list[bool]) -> tuple[NodeTimers, list[str]]:
    errors: list[str] = []
    return NodeTimers(lambda: released[0], errors.append), errors


def test_a_timer_cancelled_while_held_stays_cancelled_at_release() -> None:
    released = [False]
    timers, _ = _timers(released)
    clock = _clock(10 * S)
    node = Talker(timers, clock)
    timers.mark_start()
    node.pause_for()  # replayed: cancels the publish timer, makes the pause timer
    released[0] = True
    posted: list[Any] = []
    timers.release(posted.append)
    assert node.publish_timer.canceled  # not started again by the release
    assert node.pause_timer is not None and not node.pause_timer.canceled
    assert posted == []


def test_release_puts_a_timer_back_on_its_checkpoint_grid() -> None:
    released = [False]
    timers, _ = _timers(released)
    clock = _clock(100 * S)  # the new process made its timer at 100 s
    node = Talker(timers, clock)
    timers.mark_start()
    entry = timers.timers[0]
    assert entry is not None
    entry.grid_ns, entry.grid_from = 90 * S + S // 4, 'checkpoint'  # 90.25 + k * 0.5
    _set(clock, 100 * S + S // 10)  # released at 100.1 s
    released[0] = True
    posted: list[Any] = []
    timers.release(posted.append)
    assert node.publish_timer.next_call_ns == 100 * S + S // 4  # 100.25: on the grid
    assert node.publish_timer.timer_period_ns == S // 2  # its own period back
    assert posted == [node.publish_timer.callback]  # 99.75 fell due while it was down


def test_a_timer_made_by_a_replayed_callback_keeps_the_time_it_was_made() -> None:
    released = [False]
    timers, _ = _timers(released)
    clock = _clock(50 * S)
    node = Talker(timers, clock)
    timers.mark_start()
    node.pause_for()  # (outside an event here: made at 50 s on the clock)
    _set(clock, 51 * S)
    released[0] = True
    timers.release(lambda _cb: None)
    assert node.pause_timer is not None
    assert node.pause_timer.next_call_ns == 53 * S  # 3 s after it was made, not after release


def test_a_checkpoint_keeps_the_timers_and_a_restore_makes_the_pause_timer_again() -> None:
    released = [True]
    timers, _ = _timers(released)
    clock = _clock(10 * S)
    node = Talker(timers, clock)
    timers.mark_start()
    node.pause_for()
    data = timers.snapshot(node)

    # The next process: its __init__ made the publish timer; the pause timer is made again,
    # under the same number, bound to the attribute that held it.
    released2 = [False]
    timers2, errors = _timers(released2)
    clock2 = _clock(12 * S)
    node2 = Talker(timers2, clock2)
    timers2.mark_start()
    timers2.restore(data, node2)
    assert errors == []
    assert timers2.count() == 2
    pause = timers2.timers[1]
    assert pause is not None and node2.pause_timer is pause.timer
    assert pause.callback == node2._pause_expired
    first = timers2.timers[0]
    assert first is not None and first.cancelled
    released2[0] = True
    timers2.release(lambda _cb: None)
    assert node2.publish_timer.canceled
    assert pause.timer.next_call_ns == 13 * S  # made at 10 s with 3 s: on its grid


def test_a_destroyed_timer_keeps_its_number_and_is_not_made_again() -> None:
    released = [True]
    timers, _ = _timers(released)
    clock = _clock(10 * S)
    node = Talker(timers, clock)
    timers.mark_start()
    node.pause_for()
    node._pause_expired()  # destroys timer 1
    data = timers.snapshot(node)
    timers2, _ = _timers([False])
    node2 = Talker(timers2, _clock(20 * S))
    timers2.mark_start()
    timers2.restore(data, node2)
    assert timers2.count() == 2 and timers2.timers[1] is None
    node2.pause_for()  # the next timer made is number 2, as it was in the first process
    assert timers2.timers[2] is not None


def test_a_timer_whose_callback_is_a_closure_is_named_once_with_its_place() -> None:
    released = [True]
    timers, _ = _timers(released)
    node = Talker(timers, _clock(0))
    timers.mark_start()
    node.create_timer(1.0, lambda: None)
    lines = timers.unbuildable(node)
    assert len(lines) == 1 and 'timer 1' in lines[0] and 'test_node_timers.py:' in lines[0]
    assert timers.unbuildable(node) == []


def test_without_a_checkpoint_the_last_replayed_tick_gives_the_grid() -> None:
    released = [False]
    timers, _ = _timers(released)
    clock = _clock(30 * S)
    node = Talker(timers, clock)
    timers.mark_start()
    timers.ticked(0, 29 * S + S // 10)  # the log's last tick of timer 0: 29.1 s
    _set(clock, 30 * S + S // 5)
    released[0] = True
    posted: list[Any] = []
    timers.release(posted.append)
    assert node.publish_timer.next_call_ns == 30 * S + 6 * S // 10  # 30.6: 29.1 + 3 x 0.5
    assert len(posted) == 1


def test_a_tick_replayed_after_the_checkpoint_is_not_fired_again_at_release() -> None:
    # The checkpoint at 25.5 s saw the next call at 25.928; the log then had that tick; the
    # node was released at 26.213: the next call is 26.928, and nothing is overdue.
    released = [False]
    timers, _ = _timers(released)
    clock = _clock(26 * S)
    node = Talker(timers, clock)
    node.publish_timer.timer_period_ns = S
    timers.mark_start()
    entry = timers.timers[0]
    assert entry is not None
    entry.grid_ns, entry.grid_from = 24_928_000_000, 'checkpoint'
    timers.ticked(0, 25_928_400_000)  # replayed: fired 0.4 ms late then
    _set(clock, 26_213_000_000)
    released[0] = True
    posted: list[Any] = []
    timers.release(posted.append)
    assert posted == []
    assert node.publish_timer.next_call_ns == 26_928_000_000


def test_a_period_a_replayed_callback_changed_keeps_the_next_call_then_the_new_period() -> None:
    # On the checkpoint's grid 90.25 + k x 0.5, a callback at 92.6 s sets the period to 2 s:
    # rcl keeps the next call (92.75) and puts the later ones 2 s apart (94.75, 96.75, ...).
    released = [False]
    timers, _ = _timers(released)
    clock = _clock(100 * S)
    node = Talker(timers, clock)
    timers.mark_start()
    entry = timers.timers[0]
    assert entry is not None
    entry.grid_ns, entry.grid_from = 90 * S + S // 4, 'checkpoint'
    _set(clock, 92 * S + 6 * S // 10)  # (the replayed event's time, as the clock reads it)
    node.publish_timer.timer_period_ns = 2 * S
    _set(clock, 95 * S + S // 10)  # released at 95.1 s: 94.75 fell due while it was down
    released[0] = True
    posted: list[Any] = []
    timers.release(posted.append)
    assert node.publish_timer.next_call_ns == 96 * S + 3 * S // 4
    assert node.publish_timer.timer_period_ns == 2 * S
    assert posted == [node.publish_timer.callback]


def test_a_checkpoint_after_a_live_period_change_restores_the_new_period_and_grid() -> None:
    released = [True]
    timers, _ = _timers(released)
    clock = _clock(10 * S)
    node = Talker(timers, clock)  # next call at 10.5
    timers.mark_start()
    node.publish_timer.timer_period_ns = 2 * S  # rcl: next call stays at 10.5, then 12.5, ...
    data = timers.snapshot(node)
    released2 = [False]
    timers2, _ = _timers(released2)
    clock2 = _clock(20 * S)
    node2 = Talker(timers2, clock2)  # its __init__ makes it with 0.5 s again
    timers2.mark_start()
    timers2.restore(data, node2)
    _set(clock2, 21 * S)
    released2[0] = True
    timers2.release(lambda _cb: None)
    assert node2.publish_timer.timer_period_ns == 2 * S
    assert node2.publish_timer.next_call_ns == 22 * S + S // 2  # 10.5 + 6 x 2


@pytest.mark.ros
def test_install_routes_rclpys_period_setter_to_the_adopting_timers(context: Context) -> None:
    node = Node('period_setter', context=context)
    try:
        timers, _ = _timers([False])  # (installs the setter)
        timer = node.create_timer(1.0, lambda: None)
        entry = timers.adopt(timer, lambda: None)
        assert entry.grid_ns is not None
        grid = entry.grid_ns - S // 4  # 0.25 s into a period of 1 s
        entry.grid_ns = grid
        timer.timer_period_ns = S // 10
        assert timer.timer_period_ns == S // 10
        assert entry.grid_ns == grid + S - S // 10  # the next call stays; 0.1 s from there on
        plain = node.create_timer(1.0, lambda: None)  # not adopted: set as rclpy sets it
        plain.timer_period_ns = S // 2
        assert plain.timer_period_ns == S // 2
    finally:
        node.destroy_node()
