"""The timers a node makes and cancels in its callbacks are state (issue 37; docs/architecture.md,
"Timers and the clock"): a talker in the shape of ros2/demos' deadline demo
(corpus/pause_talker.py: a callback cancels the publish timer and makes a one-shot pause timer,
whose expiry says the count, resets the publish timer and destroys itself), SIGKILLed inside a
pause, before and after a checkpoint took the pause timer (the two runs side by side, each
test judging its own).

What it said on /said, before and after the crash, must be what a run without a crash says:
every count once and in order (nothing said twice, none skipped), no saying of the cancelled
publish timer during a pause, one saying at each pause's end.

And a 1 Hz timer that samples what the node has counted (corpus/sampler.py), SIGKILLed mid-run:
each tick saw exactly the numbers applied before it, and the ticks stay one per second on the
grid of the first, as without the crash (the one due while the node was down fires at release).
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile
from rclpy.signals import SignalHandlerOptions
from side_by_side import SideBySide, side_by_side
from std_msgs.msg import String
from supervision import events, wait_for

from rory_eval.faults.corpus_campaign import sampler_grid
from rory_eval.harness.scenario import (
    Kill,
    Program,
    _environ_lock,
    child_process,
    joining,
    prepare,
    run,
    scenario_env,
)

pytestmark = pytest.mark.ros

CORPUS = Path(__file__).parent / 'corpus'
TALKER = Program(CORPUS, CORPUS / 'keyvars.yaml', 'pause_talker.py', '/state', 'pause_talker')
SUPERVISE = [sys.executable, '-m', 'rory_runtime.cli', 'supervise']
ENOUGH = 70  # counts: 7 s, three pauses


class _Listener:
    """Hears /said (every saying, kept) and /state in the test's own participant."""

    def __init__(self, domain: int) -> None:
        self.context = Context()
        # Runs side by side in threads of one process take turns at os.environ.
        with _environ_lock, joining(domain):
            rclpy.init(context=self.context, domain_id=domain,
                       signal_handler_options=SignalHandlerOptions.NO)
            self.node = Node('said_listener', context=self.context)
        every = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_ALL,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.said: list[str] = []
        self.state: dict[str, Any] = {}
        self.node.create_subscription(String, '/said', lambda m: self.said.append(m.data), every)
        self.node.create_subscription(String, '/state', self._on_state, QoSProfile(depth=10))
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def _on_state(self, msg: String) -> None:
        self.state = json.loads(msg.data)

    def spin_until(self, done: Any, timeout: float, what: str) -> None:
        end = time.monotonic() + timeout
        while not done():
            assert time.monotonic() < end, f'timed out waiting for {what}'
            self.executor.spin_once(timeout_sec=0.01)

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.context.try_shutdown()


def _judge(said: list[str]) -> list[str]:
    """What a run without a crash says, checked on what this one said."""
    problems = []
    counts = [int(s.split()[0]) for s in said]
    if counts != list(range(1, len(counts) + 1)):
        twice = sorted({c for c in counts if counts.count(c) > 1})
        problems.append(f'counts not said once each in order (twice: {twice}): {counts}')
    during = [s for s in said if s.endswith('tick paused')]
    if during:
        problems.append(f'the cancelled publish timer said {during} during a pause')
    return problems


def _run(tmp_path: Path, domain: int, into_pause: float) -> tuple[list[str], list[Any]]:
    """One run, SIGKILLed ``into_pause`` s into the second pause."""
    workdir = tmp_path.resolve()
    config = prepare(workdir, 'rory', interval=0.25, pace='fast', program=TALKER)
    store = workdir / 'store-rory'
    listener = _Listener(domain)
    try:
        with child_process([*SUPERVISE, str(config)], scenario_env(domain), workdir,
                           workdir / 'supervisor.log'):
            listener.spin_until(lambda: listener.state.get('pauses') == 2
                                and listener.state.get('paused'), 30, 'the second pause')
            began = time.monotonic()
            listener.spin_until(lambda: time.monotonic() - began >= into_pause, 5, 'delay')
            pid = [e['pid'] for e in events(store) if e['kind'] == 'spawn'][-1]
            os.kill(pid, signal.SIGKILL)
            wait_for(lambda: any(e['kind'] == 'recovered' for e in events(store)), 30,
                     'the recovery')
            listener.spin_until(lambda: len(listener.said) >= ENOUGH, 60, f'{ENOUGH} sayings')
        return listener.said, events(store)
    finally:
        listener.close()


def test_the_judge_takes_a_talk_without_a_crash_and_refuses_the_two_failures() -> None:
    # (What a run without a crash says passes; one that says a count twice or whose cancelled
    # publish timer fires during a pause does not. A real run without a crash is not run here:
    # the crashed runs below are held to the same judge.)
    talk = ['1 tick running', '2 tick running', '3 resume paused', '4 tick running']
    assert _judge(talk) == []
    assert _judge([*talk[:3], '3 tick running'])
    assert _judge(['1 tick running', '2 tick paused'])


INTO_PAUSE = {'before-a-checkpoint-took-it': 0.05, 'after-a-checkpoint-took-it': 0.45}


@pytest.fixture(scope='module')
def talker_runs(
    module_ros_domains: Callable[[], int], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[SideBySide[tuple[list[str], list[Any]]]]:
    """Both kills' runs side by side (independent: each its own domain, folder, processes and
    listener)."""
    def killed(into_pause: float) -> Callable[[int, Path], tuple[list[str], list[Any]]]:
        return lambda domain, folder: _run(folder, domain, into_pause)
    with side_by_side({k: killed(v) for k, v in INTO_PAUSE.items()}, module_ros_domains,
                      tmp_path_factory.mktemp('talker')) as runs:
        yield runs


@pytest.mark.xdist_group('timers_kept_talker')  # one worker: the runs are shared
@pytest.mark.parametrize('into_pause', INTO_PAUSE)
def test_killed_inside_a_pause_the_talker_says_what_it_would_have(
    into_pause: str, talker_runs: SideBySide[tuple[list[str], list[Any]]]
) -> None:
    said, log = talker_runs[into_pause]
    assert _judge(said) == [], said
    recovered = [e for e in log if e['kind'] == 'recovered']
    assert len(recovered) == 1
    errors = [e['message'] for e in log if e['kind'] == 'error']
    assert not [m for m in errors if 'timer' in m], errors
    # The pause the crash fell into ended with one resume, then the talk went on.
    assert sum(s.split()[1] == 'resume' for s in said) >= 2


# -- a 1 Hz timer whose output depends on the inputs its tick sees ----------------------------

SAMPLER = Program(CORPUS, CORPUS / 'keyvars.yaml', 'sampler.py', '/state', 'sampler')
NUMBERS = 400  # 8 s at 50 Hz: eight ticks


def test_a_1hz_sampler_killed_mid_run_samples_as_without_the_crash(
    tmp_path: Path, ros_domain: int
) -> None:
    common: dict[str, Any] = {'domain_id': ros_domain, 'count': NUMBERS, 'interval': None,
                              'pace': 'fast', 'program': SAMPLER}
    # (A run without a crash passes the same judge, corpus_campaign.sampler_grid, which make
    # faults holds the sampler's runs to; it is not run here, to keep make test short: the
    # judge's rules are what rcl's timer does, one tick a period on its grid.)
    crashed = run('rory', (Kill(after=3.5),), tmp_path / 'crashed', **common)
    assert len(crashed.recoveries) == 1
    assert sampler_grid(crashed.state, NUMBERS) == [], crashed.state['samples']
    assert len(crashed.state['samples']) >= NUMBERS // 50 - 1  # a tick a second of numbers
