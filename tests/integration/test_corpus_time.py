"""Nodes that compute with their clock, work in timers, are tuned by parameters, commanded by
a service or managed as lifecycle nodes at run time, SIGKILLed mid-interval.

Their clock readings, timer ticks, parameter changes, service requests and lifecycle
transitions are inputs (docs/architecture.md, "Timers and the clock", "Parameters",
"Services", "Lifecycle nodes"): logged while live, replayed as recorded. Two runs of such a
node never read the same times, so each crashed run is judged as ``make faults``' corpus
campaign judges it without a reference (rory_eval/faults/corpus_campaign.py): every number applied
once and in order, the state what its own readings and settings imply, no reading or tick
taken from the replay's time instead of the recorded one (which shows as a lag or a gap of
the time since the checkpoint, here about 1 s). The campaign adds the no-crash run and
random kill times. The five crashed runs are independent (each its own domain, folder and
processes) and run three at a time (side_by_side.py); each test judges its own node's run.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from side_by_side import SideBySide, side_by_side

from rory_eval.faults.corpus_campaign import NODES, judge_run, run_node
from rory_eval.harness.scenario import Kill, ScenarioResult

# The runs are shared: the module's tests on one xdist worker.
pytestmark = [pytest.mark.ros, pytest.mark.xdist_group('corpus_time')]

BY_NAME = {node.name: node for node in NODES}
# The operators take their steps in order (corpus/operator.py): the first at numbers 20-30,
# usually before the node's first checkpoint (2 s after its release, 1-1.7 s into the numbers,
# but later in the numbers when they start late on a busy machine), the others 5-15 numbers
# after that checkpoint; the node is killed 1 s after it, 1 s before its second. Which changes
# come back from the checkpoint and which from the log depends on where the checkpoint fell:
# every change comes back once, in order, either way (every placement is forced in
# tests/runtime/test_input_order.py).
KILL = Kill(after_checkpoint=1, delay=1.0)


NAMES = ('clock_integrator', 'timer_mapper', 'gain_controller', 'mode_switch',
         'lifecycle_counter')
# A run takes about a third of a core (supervisor, node, standby, publisher, operator).
AT_ONCE = 3


@pytest.fixture(scope='module')
def crashed_runs(
    module_ros_domains: Callable[[], int], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[SideBySide[ScenarioResult]]:
    """Each node's crashed run, three at a time (independent runs: each its own domain, folder
    and processes)."""
    def crashed(name: str) -> Callable[[int, Path], ScenarioResult]:
        return lambda domain, folder: run_node(BY_NAME[name], (KILL,), folder, domain)
    with side_by_side({name: crashed(name) for name in NAMES}, module_ros_domains,
                      tmp_path_factory.mktemp('corpus-time'), AT_ONCE) as runs:
        yield runs


def _crashed(name: str, runs: SideBySide[ScenarioResult]) -> ScenarioResult:
    node = BY_NAME[name]
    result = runs[name]
    assert judge_run(node, None, result) == []
    assert result.recoveries[0]['replayed'] > 0
    return result


def _restored(result: ScenarioResult) -> dict[str, object]:
    hello = [e for e in result.events if e['kind'] == 'hello']
    restored = hello[-1]['restored']
    assert isinstance(restored, dict)
    return restored


def test_a_node_reading_its_clock_recovers_with_the_times_it_read(
    crashed_runs: SideBySide[ScenarioResult]
) -> None:
    result = _crashed('clock_integrator', crashed_runs)
    assert result.recoveries[0]['clock_fallbacks'] is not None


def test_a_node_working_in_a_timer_recovers_every_tick(
    crashed_runs: SideBySide[ScenarioResult]
) -> None:
    result = _crashed('timer_mapper', crashed_runs)
    assert result.recoveries[0]['ticks_replayed'] > 0


def test_a_node_tuned_at_run_time_keeps_its_parameters_through_a_crash(
    crashed_runs: SideBySide[ScenarioResult]
) -> None:
    # The gain set to 2 comes back from the checkpoint if it was set before it, else from the
    # log; the change to 3 always from the log.
    result = _crashed('gain_controller', crashed_runs)
    assert isinstance(result.state, dict)
    assert [gain for gain, _ in result.state['gains']] == [1.0, 2.0, 3.0]
    from_checkpoint = _restored(result)['parameters']
    assert from_checkpoint in ([], ['gain'])
    assert result.recoveries[0]['parameter_changes_replayed'] == 2 - len(from_checkpoint)


def test_a_node_commanded_by_a_service_keeps_its_commands_through_a_crash(
    crashed_runs: SideBySide[ScenarioResult]
) -> None:
    result = _crashed('mode_switch', crashed_runs)
    assert isinstance(result.state, dict)
    assert [factor for factor, _ in result.state['runs']] == [1, 2, 1]
    assert result.state['requests'] == 2
    # The second request always from the log; the first from the checkpoint or the log.
    assert result.recoveries[0]['requests_replayed'] in (1, 2)


def test_a_lifecycle_node_comes_back_through_its_callbacks(
    crashed_runs: SideBySide[ScenarioResult]
) -> None:
    # Back to the checkpoint's state through on_configure (which subscribes) and, if it was
    # active then, on_activate; the transitions after it are replayed from the log.
    result = _crashed('lifecycle_counter', crashed_runs)
    assert isinstance(result.state, dict)
    assert [counted for counted, _ in result.state['runs']] == [0, 1, 0, 1]
    at_checkpoint = _restored(result)['lifecycle']
    # configure at the start, so before the checkpoint; activate at 30, before it or not.
    assert at_checkpoint in ('active', 'inactive')
    replayed = {'active': 2, 'inactive': 3}[str(at_checkpoint)]
    assert result.recoveries[0]['requests_replayed'] == replayed
