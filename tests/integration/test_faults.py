"""Faults during recovery: a poison message is found, quarantined and skipped."""

from __future__ import annotations

import base64
import json
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from rclpy.serialization import deserialize_message
from side_by_side import SideBySide, side_by_side
from std_msgs.msg import Int64

from rory_eval.faults.fault_campaign import FLAKY_DIR
from rory_eval.harness.scenario import Kill, Program, ScenarioResult, run

# The three runs are shared (side_by_side.py): the module's tests on one xdist worker.
pytestmark = [pytest.mark.ros, pytest.mark.xdist_group('faults')]

FAULTS = Path(__file__).parent / 'faults'


def _poison(domain: int, folder: Path) -> ScenarioResult:
    program = Program(FAULTS, FAULTS / 'keyvars.yaml', 'poison.py', '/state', 'fragile')
    return run('rory', (), folder, domain_id=domain, count=150, program=program, timeout=120)


def _hang(domain: int, folder: Path) -> ScenarioResult:
    program = Program(FAULTS, FAULTS / 'keyvars.yaml', 'hang.py', '/state', 'stuck',
                      settings=(('hang_timeout', 1.5),))
    return run('rory', (), folder, domain_id=domain, count=150, program=program, timeout=120)


def _long_hang(domain: int, folder: Path) -> ScenarioResult:
    # The flaky integrator (queue depth 100, so its ring keeps 116 messages) hangs once at
    # 50 Hz; hang_timeout 4 s lets ~200 numbers arrive before the kill. The ring starts taking
    # them when the heartbeat is 0.6 s late, so the replacement gets every one.
    program = Program(FLAKY_DIR, FLAKY_DIR / 'keyvars.yaml', 'flaky_integrator.py',
                      '/integrator/state', 'integrator', settings=(('hang_timeout', 4.0),))
    return run('rory', (Kill(after=1.5, how='hang'),), folder, domain_id=domain, count=400,
               rate=50.0, interval=1.0, pace='fast', program=program, timeout=120)


@pytest.fixture(scope='module')
def fault_runs(
    module_ros_domains: Callable[[], int], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[SideBySide[ScenarioResult]]:
    """The three runs side by side (independent: each its own domain, folder and processes)."""
    with side_by_side({'poison': _poison, 'hang': _hang, 'long_hang': _long_hang},
                      module_ros_domains, tmp_path_factory.mktemp('faults')) as runs:
        yield runs


def test_poison_message_is_quarantined_and_the_node_goes_on(
    fault_runs: SideBySide[ScenarioResult]
) -> None:
    result = fault_runs['poison']
    kinds = [e['kind'] for e in result.events]
    exits = [e for e in result.events if e['kind'] == 'exit']
    # 1: dies live on 77; 2: dies again when the replay reaches 77 -> quarantined; 3: goes on
    assert len(exits) == 2, result.log[-3000:]
    assert kinds.count('quarantined') == 1
    quarantined = next(e for e in result.events if e['kind'] == 'quarantined')
    record = json.loads(Path(quarantined['path']).read_text())
    assert record['topic'] == '/numbers'
    message = deserialize_message(base64.b64decode(record['cdr_base64']), Int64)
    assert message.data == 77
    # nothing else lost, nothing doubled, 77 skipped
    assert result.state['history'] == [n for n in range(1, 151) if n != 77]
    states = [e['new'] for e in result.events if e['kind'] == 'state']
    # the node was running when the harness stopped it (the stop itself may or may not be in
    # the events yet): never FATAL
    assert [s for s in states if s not in ('STOPPING', 'STOPPED')][-1] == 'RUNNING', states
    assert 'FATAL' not in states


def test_a_hung_node_is_killed_recovered_and_its_hanging_message_quarantined(
    fault_runs: SideBySide[ScenarioResult]
) -> None:
    result = fault_runs['hang']
    hangs = [e for e in result.events if e['kind'] == 'hang']
    # 1: hangs live on 77; 2: hangs again when the replay reaches 77 -> quarantined; 3: goes on
    assert len(hangs) == 2, result.log[-3000:]
    assert all(h['topic'] == '/numbers' and h['waiting_for'] == 'heartbeat' for h in hangs)
    # Killed for the heartbeat, not sooner. How much later depends on when the supervisor's
    # tick next runs: on a loaded 2-core CI machine that was once past 3 s, so the upper bound
    # only rules out a hang found by some other way (the harness's own timeout).
    assert all(1.5 < h['stalled_s'] < 15.0 for h in hangs), hangs
    exits = [e for e in result.events if e['kind'] == 'exit']
    assert [e['code'] for e in exits] == [-9, -9]
    assert [e['kind'] for e in result.events].count('quarantined') == 1
    assert result.state['history'] == [n for n in range(1, 151) if n != 77]
    # SIGUSR1 before the kill: the node printed where it hung
    assert 'in on_number' in result.log, result.log[-3000:]


def test_a_hang_longer_than_the_ring_holds_loses_nothing(
    fault_runs: SideBySide[ScenarioResult]
) -> None:
    # (_long_hang: a hang of the flaky integrator, found after hang_timeout 4 s.)
    result = fault_runs['long_hang']
    hangs = [e for e in result.events if e['kind'] == 'hang']
    assert len(hangs) == 1 and hangs[0]['stalled_s'] > 4.0, result.log[-3000:]
    assert 'RORY keeps its inputs from now on' in result.log
    assert not [e for e in result.events if e['kind'] == 'input_gap'], result.log[-3000:]
    assert result.history == list(range(1, 401)), result.log[-3000:]
