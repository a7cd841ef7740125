"""The side thread's decisions (node/pulse.py): when it beats by itself, when it probes the
executor, when a checkpoint is due; driven tick by tick with a fake executor and a fake clock."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import pytest
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node as RclpyNode

from rory_runtime.node.pulse import PARKED_PROBE_EVERY, CheckpointSchedule, Pulse, executor_parked

SECOND = 1_000_000_000


class FakeExecutor:
    """Keeps the tasks posted to it; runs them when the test says the executor spins."""

    def __init__(self) -> None:
        self.tasks: list[Callable[[], None]] = []
        self.shut_down = False

    def create_task(self, callback: Callable[[], None]) -> object:
        if self.shut_down:
            raise AttributeError("'NoneType' object has no attribute 'trigger'")
        self.tasks.append(callback)
        return object()

    def spin_once(self) -> None:
        tasks, self.tasks = self.tasks, []
        for task in tasks:
            task()


class Node:
    """What the pulse reads of the node: its executor, its progress, its clock, its beats."""

    def __init__(self) -> None:
        self.executor: FakeExecutor | None = FakeExecutor()
        self.progress = 0
        self.now_ns = 0
        self.beats = 0
        self.checkpoints = 0

    def pulse(self) -> Pulse:
        return Pulse(lambda: self.executor, self._beat, lambda: self.progress,
                     lambda: self.now_ns)

    def _beat(self) -> None:
        self.beats += 1

    def checkpoint(self) -> None:
        self.checkpoints += 1


def test_a_node_busy_with_its_callbacks_is_never_woken_for_its_heartbeat() -> None:
    node = Node()
    pulse = node.pulse()
    for _ in range(10):
        node.progress += 3  # callbacks ran to their end since the last look
        pulse.tick()
    assert node.beats == 10
    assert node.executor is not None and node.executor.tasks == []


def test_an_idle_node_is_probed_once_per_look_and_beats_when_the_probe_runs() -> None:
    node = Node()
    pulse = node.pulse()
    executor = node.executor
    assert executor is not None
    pulse.tick()  # the first look: progress 0 is news
    assert node.beats == 1
    for expected in (2, 3, 4):
        pulse.tick()
        assert len(executor.tasks) == 1
        executor.spin_once()
        assert node.beats == expected


def _probed_once(node: Node, parked: bool, asked: list[int]) -> tuple[Pulse, FakeExecutor]:
    """A pulse whose executor the test says is parked (or not), after its first probe ran on
    this thread (which the pulse then knows as the executor's)."""
    def is_parked(thread_id: int) -> bool:
        asked.append(thread_id)
        return parked

    pulse = Pulse(lambda: node.executor, node._beat, lambda: node.progress, lambda: node.now_ns,
                  parked=is_parked)
    executor = node.executor
    assert executor is not None
    pulse.tick()  # progress 0 is news
    pulse.tick()  # no thread known yet: a probe
    assert len(executor.tasks) == 1
    executor.spin_once()
    return pulse, executor


def test_an_idle_executor_parked_in_its_wait_beats_without_a_probe_but_every_2_s() -> None:
    node = Node()
    asked: list[int] = []
    pulse, executor = _probed_once(node, True, asked)
    beats = node.beats
    posted = 0
    for _ in range(3 * PARKED_PROBE_EVERY):
        pulse.tick()
        posted += len(executor.tasks)
        executor.spin_once()
    assert node.beats == beats + 3 * PARKED_PROBE_EVERY  # a beat at every look
    assert posted == 3  # a probe every PARKED_PROBE_EVERY looks, not one a look
    assert set(asked) == {threading.get_ident()}  # the thread the probe ran on


def test_parked_but_deaf_the_beat_stops() -> None:
    # Found parked, probed, and the probe never runs: no more beats, as for a stuck executor.
    node = Node()
    pulse, executor = _probed_once(node, True, [])
    for _ in range(PARKED_PROBE_EVERY):
        pulse.tick()
    assert len(executor.tasks) == 1  # the probe, not run
    beats = node.beats
    for _ in range(50):
        pulse.tick()
    assert node.beats == beats
    assert len(executor.tasks) == 1


def test_not_parked_and_no_progress_is_probed_at_every_look() -> None:
    node = Node()
    pulse, executor = _probed_once(node, False, [])
    for _ in range(5):
        pulse.tick()
        assert len(executor.tasks) == 1
        executor.spin_once()


@pytest.mark.ros
def test_a_real_executor_is_parked_when_idle_and_not_inside_a_callback(
    context: Context
) -> None:
    node = RclpyNode('parked_probe', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    inside, release = threading.Event(), threading.Event()
    spin_thread: list[int] = []

    def spin() -> None:
        spin_thread.append(threading.get_ident())
        executor.spin()

    def stuck() -> None:
        inside.set()
        release.wait(10.0)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 5.0
        while not (spin_thread and executor_parked(spin_thread[0])):
            assert time.monotonic() < deadline, 'the idle executor was never found parked'
            time.sleep(0.01)
        executor.create_task(stuck)
        assert inside.wait(5.0)
        assert not executor_parked(spin_thread[0])  # inside a callback: not parked
        release.set()
        deadline = time.monotonic() + 5.0
        while not executor_parked(spin_thread[0]):
            assert time.monotonic() < deadline, 'not parked again after the callback'
            time.sleep(0.01)
    finally:
        release.set()
        executor.shutdown(timeout_sec=2.0)
        thread.join(5.0)
        node.destroy_node()


def test_a_stuck_executor_stops_the_beat_and_is_not_flooded_with_probes() -> None:
    # A callback that never returns, a deadlock, a busy loop: no callback ends, the probe
    # waits; the supervisor sees the beat stop (hang_timeout) as it did with the timer.
    node = Node()
    pulse = node.pulse()
    pulse.tick()
    beats = node.beats
    for _ in range(50):
        pulse.tick()
    assert node.beats == beats
    assert node.executor is not None and len(node.executor.tasks) == 1
    node.executor.spin_once()  # it comes back
    assert node.beats == beats + 1


def test_no_executor_yet_no_beat_and_no_post() -> None:
    node = Node()
    node.executor = None
    pulse = node.pulse()
    pulse.tick()  # the first look counts progress 0 as news
    pulse.tick()
    pulse.tick()
    assert node.beats == 1


def test_an_executor_shut_down_under_the_pulse_is_no_error() -> None:
    node = Node()
    pulse = node.pulse()
    pulse.tick()
    assert node.executor is not None
    node.executor.shut_down = True
    pulse.tick()
    pulse.tick()
    assert node.executor.tasks == []


def test_after_stop_nothing_is_posted() -> None:
    node = Node()
    pulse = node.pulse()
    pulse.tick()
    pulse.stop()
    pulse.tick()
    assert node.executor is not None and node.executor.tasks == []


def test_checkpoints_are_posted_on_the_node_clock_grid_one_at_a_time() -> None:
    node = Node()
    pulse = node.pulse()
    node.now_ns = 100 * SECOND
    pulse.schedule_checkpoints(2.0, node.checkpoint)
    executor = node.executor
    assert executor is not None
    ran_at: list[float] = []
    for step in range(1, 61):  # 6 s in looks of 0.1 s
        node.now_ns = 100 * SECOND + step * SECOND // 10
        node.progress += 1
        pulse.tick()
        if executor.tasks:
            executor.spin_once()
            ran_at.append(node.now_ns / SECOND)
    assert node.checkpoints == 3
    assert ran_at == [102.0, 104.0, 106.0]


def test_a_checkpoint_waiting_for_the_executor_is_not_posted_again() -> None:
    node = Node()
    pulse = node.pulse()
    pulse.schedule_checkpoints(1.0, node.checkpoint)
    executor = node.executor
    assert executor is not None
    for second in range(1, 6):  # the executor is stuck for 5 s
        node.now_ns = second * SECOND
        pulse.tick()
    waiting = [t for t in executor.tasks]
    assert len(waiting) == 2  # one probe, one checkpoint
    executor.spin_once()
    assert node.checkpoints == 1


def test_simulation_time_that_stands_still_takes_no_checkpoint() -> None:
    node = Node()
    pulse = node.pulse()
    node.now_ns = 0
    pulse.schedule_checkpoints(2.0, node.checkpoint)
    for _ in range(100):
        node.progress += 1
        pulse.tick()
    assert node.executor is not None and node.executor.tasks == []


def test_the_schedule_keeps_its_grid_and_runs_missed_ones_once() -> None:
    schedule = CheckpointSchedule(interval_ns=2 * SECOND, next_ns=2 * SECOND)
    assert not schedule.due(1 * SECOND)
    assert schedule.due(2 * SECOND + 300)  # a little late: the grid does not move
    assert schedule.next_ns == 4 * SECOND
    assert schedule.due(11 * SECOND)  # three missed: once
    assert schedule.next_ns == 12 * SECOND
    assert not schedule.due(11 * SECOND + 1)


def test_the_schedule_starts_again_when_the_clock_goes_back() -> None:
    schedule = CheckpointSchedule(interval_ns=2 * SECOND, next_ns=100 * SECOND)
    assert not schedule.due(5 * SECOND)  # a simulation restarted at 5 s
    assert schedule.next_ns == 7 * SECOND
    assert schedule.due(7 * SECOND)


def test_the_thread_beats_an_idle_executor_through_probes() -> None:
    node = Node()
    pulse = node.pulse()
    executor = node.executor
    assert executor is not None
    pulse.start(period=0.01)
    try:
        deadline = time.monotonic() + 5.0
        while node.beats < 4 and time.monotonic() < deadline:
            executor.spin_once()
            time.sleep(0.005)
    finally:
        pulse.stop()
    assert node.beats >= 4
