"""Nodes that compute with their clock, work in timers, are tuned by parameters, commanded by
a service or managed as lifecycle nodes at run time, SIGKILLed mid-interval.

Their clock readings, timer ticks, parameter changes, service requests and lifecycle
transitions are inputs (docs/architecture.md, "Timers and the clock", "Parameters",
"Services", "Lifecycle nodes"): logged while live, replayed as recorded. Two runs of
such a node never read the same times, so each crashed run is checked against itself: every
message applied once and in order, the state equal to what its own readings imply, and no
reading or tick taken from the replay's time instead of the recorded one (which shows as a lag
or a gap of the time since the checkpoint, here about 1.8 s).
"""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import pytest

from rory_eval.scenario import Kill, Program, ScenarioResult, child_process, run, scenario_env

pytestmark = pytest.mark.ros

CORPUS = Path(__file__).parent / 'corpus'
COUNT = 200  # 4 s at 50 Hz
# The node checkpoints every 2 s from its start, about 1 s before the first number: killed
# 2.8 s into the numbers, it is about 1.8 s past its second checkpoint.
KILL_AFTER = 2.8
# What a message or tick may lag: the recovery's own outage and handover, well under the time
# since the checkpoint that a replay on live time would show.
MAX_LAG_NS = 900_000_000


def _crashed(file: str, name: str, tmp_path: Path, domain: int,
             other_readers: int = 0) -> ScenarioResult:
    program = Program(CORPUS, CORPUS / 'keyvars.yaml', file, '/state', name)
    result = run('rory', (Kill(after=KILL_AFTER),), tmp_path, domain_id=domain, count=COUNT,
                 interval=None, pace=None, program=program, other_readers=other_readers)
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


def test_a_node_tuned_at_run_time_keeps_its_parameters_through_a_crash(
    tmp_path: Path, ros_domain: int
) -> None:
    # The operator sets the gain to 2 before the node's second checkpoint (about number 50)
    # and to 3 after it (number 100), before the kill (about number 140): the first comes
    # back from the checkpoint, the second from the log.
    operator = [sys.executable, str(CORPUS / 'operator.py'), 'gain', '20=2.0', '100=3.0']
    with child_process(operator, scenario_env(ros_domain), tmp_path, tmp_path / 'operator.log'):
        result = _crashed('gain_controller.py', 'gain_controller', tmp_path, ros_domain,
                          other_readers=1)
    state = result.state
    assert isinstance(state, dict)
    assert state['count'] == COUNT
    assert [gain for gain, _ in state['gains']] == [1.0, 2.0, 3.0], state['gains']
    total, n = 0.0, 0
    for gain, how_many in state['gains']:
        for _ in range(how_many):
            n += 1
            total += gain * n
    assert state['total'] == total
    hello = [e for e in result.events if e['kind'] == 'hello']
    assert hello[-1]['restored']['parameters'] == ['gain']
    assert result.recoveries[0]['parameter_changes_replayed'] == 1


def test_a_node_commanded_by_a_service_keeps_its_commands_through_a_crash(
    tmp_path: Path, ros_domain: int
) -> None:
    # Fast mode on before the node's second checkpoint, off after it and before the kill.
    operator = [sys.executable, str(CORPUS / 'operator.py'), 'fast', '20=1', '100=0']
    with child_process(operator, scenario_env(ros_domain), tmp_path, tmp_path / 'operator.log'):
        result = _crashed('mode_switch.py', 'mode_switch', tmp_path, ros_domain,
                          other_readers=1)
    state = result.state
    assert isinstance(state, dict)
    assert state['count'] == COUNT
    assert [factor for factor, _ in state['runs']] == [1, 2, 1], state['runs']
    assert state['requests'] == 2
    total, n = 0, 0
    for factor, how_many in state['runs']:
        for _ in range(how_many):
            n += 1
            total += factor * n
    assert state['total'] == total
    assert result.recoveries[0]['requests_replayed'] == 1


def test_a_lifecycle_node_comes_back_active_through_its_callbacks(
    tmp_path: Path, ros_domain: int
) -> None:
    # Configured at once (it subscribes in on_configure), active before its second checkpoint,
    # then deactivated and activated again after it, before the kill: it must come back
    # active through on_configure and on_activate, and replay the two later transitions.
    operator = [sys.executable, str(CORPUS / 'operator.py'), 'lifecycle', '0=configure',
                '30=activate', '100=deactivate', '120=activate']
    with child_process(operator, scenario_env(ros_domain), tmp_path, tmp_path / 'operator.log'):
        result = _crashed('lifecycle_counter.py', 'lifecycle_counter', tmp_path, ros_domain,
                          other_readers=1)
    state = result.state
    assert isinstance(state, dict)
    assert state['count'] == COUNT
    assert [counted for counted, _ in state['runs']] == [0, 1, 0, 1], state['runs']
    total, n = 0, 0
    for counted, how_many in state['runs']:
        for _ in range(how_many):
            n += 1
            total += counted * n
    assert state['total'] == total
    hello = [e for e in result.events if e['kind'] == 'hello']
    assert hello[-1]['restored']['lifecycle'] == 'active'
    assert result.recoveries[0]['requests_replayed'] == 2
