"""Nodes that compute with their clock or work in timers, SIGKILLed mid-interval.

Their clock readings and timer ticks are inputs (docs/architecture.md, "Timers and the
clock"): logged while live, replayed with the recorded times. Two runs of such a node never
read the same times, so each crashed run is checked against itself: every message applied
once and in order, the state equal to what its own clock readings imply, and no reading or
tick taken from the replay's time instead of the recorded one (which shows as a lag or a gap
of the time since the checkpoint, here about 1.8 s).
"""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest

from rory_eval.scenario import Kill, Program, ScenarioResult, run

pytestmark = pytest.mark.ros

CORPUS = Path(__file__).parent / 'corpus'
COUNT = 200  # 4 s at 50 Hz
# The node checkpoints every 2 s from its start, about 1 s before the first number: killed
# 2.8 s into the numbers, it is about 1.8 s past its second checkpoint.
KILL_AFTER = 2.8
# What a message or tick may lag: the recovery's own outage and handover, well under the time
# since the checkpoint that a replay on live time would show.
MAX_LAG_NS = 900_000_000


def _crashed(file: str, name: str, tmp_path: Path, domain: int) -> ScenarioResult:
    program = Program(CORPUS, CORPUS / 'keyvars.yaml', file, '/state', name)
    result = run('rory', (Kill(after=KILL_AFTER),), tmp_path, domain_id=domain, count=COUNT,
                 interval=None, pace=None, program=program)
    assert len(result.recoveries) == 1
    assert result.recoveries[0]['replay'] == 'fast'
    assert result.recoveries[0]['replayed'] > 0
    assert isinstance(result.state, dict)
    return result


def test_a_node_reading_its_clock_recovers_with_the_times_it_read(
    tmp_path: Path, ros_domain: int
) -> None:
    result = _crashed('clock_integrator.py', 'clock_integrator', tmp_path, ros_domain)
    state = result.state
    assert isinstance(state, dict)
    numbers = [n for n, _ in state['readings']]
    assert numbers == list(range(1, COUNT + 1))
    assert state['count'] == COUNT and state['total'] == COUNT * (COUNT + 1) // 2
    position, last = 0.0, None
    for n, now_ns in state['readings']:
        if last is not None:
            position += n * (now_ns - last) / 1e9
        last = now_ns
    assert state['position'] == position
    times = [t for _, t in state['readings']]
    assert times == sorted(times)
    assert state['max_lag_ns'] < MAX_LAG_NS, state['max_lag_ns']


def test_a_node_working_in_a_timer_recovers_every_tick(
    tmp_path: Path, ros_domain: int
) -> None:
    result = _crashed('timer_mapper.py', 'timer_mapper', tmp_path, ros_domain)
    state = result.state
    assert isinstance(state, dict)
    assert state['count'] == COUNT
    covered = [n for batch in state['batches'] for n in batch] + state['pending']
    assert covered == list(range(1, COUNT + 1))
    ticks = state['tick_ns']
    gaps = [b - a for a, b in itertools.pairwise(ticks)]
    assert min(gaps) > 0
    assert max(gaps) < MAX_LAG_NS, max(gaps)
    assert result.recoveries[0]['ticks_replayed'] > 0
