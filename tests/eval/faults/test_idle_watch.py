"""The idle watch of ``make faults`` (rory_eval/faults/idle_watch.py) on made-up runs: what
it accepts, what it refuses and why, the run it asks the harness for, its exit codes. No
process is started."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from rory_eval.faults import idle_watch
from rory_eval.faults.idle_watch import judge
from rory_eval.harness.scenario import ScenarioResult

IDLE: list[dict[str, Any]] = [
    {'kind': 'spawn', 'pid': 4242, 'incarnation': 1, 'mode': 'start', 'warm': False},
    {'kind': 'hello', 'incarnation': 1},
    {'kind': 'state', 'new': 'RUNNING'},
    *[{'kind': 'checkpoint', 'incarnation': 1, 'number': k} for k in range(1, 91)],
]
"""Three idle minutes of the supervisor's events: the node started, then only checkpoints."""


def _result(events: list[dict[str, Any]] = IDLE, *, history: list[int] | None = None,
            e_stop: list[tuple[float, bool]] | None = None, log: str = '') -> ScenarioResult:
    state = {'count': 4, 'history': [1, 2, 3, 4] if history is None else history}
    return ScenarioResult('rory', 4, state, [e for e in events if e['kind'] == 'recovered'],
                          [], [(0.0, False)] if e_stop is None else e_stop, events, log)


def test_an_idle_run_without_a_kill_and_exact_is_accepted() -> None:
    verdict = judge(_result(), 1.0)
    assert verdict.accepted
    assert verdict.failures == []
    assert 'final state: history [1, 2, 3, 4] (expected 1..4), 0 lost, 0 applied twice' \
        in verdict.notes
    assert 'kills: 0 hang, 0 unheard' in verdict.notes
    assert 'checkpoints: 90 taken, 0 overdue warnings' in verdict.notes


def test_an_idle_node_taken_for_hung_is_refused_with_all_that_followed() -> None:
    events = [*IDLE,
              {'kind': 'hang', 'waiting_for': 'heartbeat', 'stalled_s': 1.02},
              {'kind': 'safe_state', 'what': 'held'},
              {'kind': 'exit', 'incarnation': 1, 'code': -9},
              {'kind': 'spawn', 'pid': 4243, 'incarnation': 2, 'mode': 'recover'},
              {'kind': 'recovered', 'crashes': 1, 'total_ms': 310.0},
              {'kind': 'safe_state', 'what': 'released'}]
    verdict = judge(_result(events, e_stop=[(0.0, False), (61.0, True), (61.3, False)]), 1.0)
    assert not verdict.accepted
    # Exact all the same (recovery works): what fails the run is that it happened at all.
    assert verdict.failures == ['1 safe-state engagements without a fault',
                                '1 kills without a fault', '1 crashes without a fault',
                                '1 recoveries without a fault']
    assert 'kills: 1 hang, 0 unheard' in verdict.notes
    assert 'safe state: 1 held events, 1 True on /e_stop' in verdict.notes


@pytest.mark.parametrize('event, why', [
    ({'kind': 'unheard', 'beating_s': 10.2}, '1 kills without a fault'),
    ({'kind': 'hang', 'waiting_for': 'start', 'stalled_s': 61.0}, '1 kills without a fault'),
    ({'kind': 'exit', 'incarnation': 1, 'code': 1}, '1 crashes without a fault'),
    ({'kind': 'state', 'new': 'FATAL'}, '1 give-ups'),
])
def test_any_kill_crash_or_give_up_refuses_the_run(event: dict[str, Any], why: str) -> None:
    assert judge(_result([*IDLE, event]), 1.0).failures == [why]


def test_the_safe_state_heard_on_e_stop_alone_refuses_the_run() -> None:
    verdict = judge(_result(e_stop=[(0.0, False), (30.0, True)]), 1.0)
    assert verdict.failures == ['1 safe-state engagements without a fault']


def test_a_final_state_not_exact_refuses_the_run() -> None:
    verdict = judge(_result(history=[1, 2, 2, 4]), 1.0)
    assert verdict.failures == [
        'not exact (history [1, 2, 2, 4], expected 1..4)', '1 lost', '1 applied twice']
    assert not judge(_result(history=[]), 1.0).accepted  # the observer heard nothing
    # Numbers from another graph (a test session on the same domain) are not taken as the
    # node's own, and a long history is cut to one line.
    stray = judge(_result(history=[1, 2, *range(7, 114), 3, 4]), 1.0)
    assert stray.failures[0] == ('not exact (history [1, 2, 7, 8, 9, 10, 11, 12, 13, 14, '
                                 '..., 4] (111 numbers), expected 1..4)')


def test_late_beats_are_reported_not_judged() -> None:
    log = ('07:41:20.123 [rory] integrator: no heartbeat for 0.5 s: RORY keeps its inputs '
           'from now on\n07:41:20.300 [rory] integrator: input capture stopped: beating again '
           '(0 messages kept meanwhile, dropped)\n07:43:01.010 [rory] integrator: no heartbeat '
           'for 0.7 s: RORY keeps its inputs from now on\n')
    verdict = judge(_result(log=log), 1.0)
    assert verdict.accepted
    assert 'late heartbeats (inputs kept, not judged): 2, the latest seen 0.7 s old' \
        in verdict.notes


def test_the_run_asked_of_the_harness_is_sparse_and_has_the_short_hang_timeout(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    asked: dict[str, Any] = {}

    def fake_run(method: str, kills: tuple[Any, ...], workdir: Path,
                 **kwargs: Any) -> ScenarioResult:
        asked.update(kwargs, method=method, kills=kills, workdir=workdir)
        return _result()

    monkeypatch.setattr(idle_watch, 'run', fake_run)
    idle_watch.scenario(3, 1.0, tmp_path, 9)
    assert (asked['method'], asked['kills'], asked['domain_id']) == ('rory', (), 9)
    assert asked['count'] == 4
    assert asked['rate'] == pytest.approx(1 / 60)
    assert dict(asked['program'].settings)['hang_timeout'] == 1.0
    assert asked['program'].file == 'integrator.py'
    assert asked['timeout'] > 3 * 60  # the harness must not give up before the last number


@pytest.fixture
def quiet_sigterm(monkeypatch: pytest.MonkeyPatch) -> None:
    """main() must not install its SIGTERM handler in the test process."""
    monkeypatch.setattr(idle_watch, 'exit_on_sigterm', lambda: None)


@pytest.mark.usefixtures('quiet_sigterm')
def test_exit_0_when_accepted_1_when_not_or_when_the_run_did_not_run(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    outcomes: list[ScenarioResult | Exception] = [
        _result(), _result([*IDLE, {'kind': 'unheard', 'beating_s': 10.1}]),
        RuntimeError('node did not start:\nthe log')]

    def fake_scenario(minutes: int, hang_timeout: float, workdir: Path,
                      domain: int) -> ScenarioResult:
        outcome = outcomes.pop(0)
        if isinstance(outcome, Exception):
            raise outcome
        return outcome

    monkeypatch.setattr(idle_watch, 'scenario', fake_scenario)
    args = ['--minutes', '3', '--out', str(tmp_path)]
    assert idle_watch.main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[-1].startswith('accepted: idle 60 s between 4 numbers for ')
    assert idle_watch.main(args) == 1
    lines = capsys.readouterr().out.splitlines()
    assert '  FAIL: 1 kills without a fault' in lines
    assert lines[-1].startswith('NOT accepted (') and lines[-1].endswith(f'-> {tmp_path}')
    assert idle_watch.main(args) == 1
    assert '  FAIL: did not run: node did not start:' in capsys.readouterr().out.splitlines()


@pytest.mark.parametrize('argv', [['--minutes', '0'], ['--minutes', 'three'],
                                  ['--hang-timeout', '0'], ['--hang-timeout', 'x']])
def test_bad_arguments_exit_2(argv: list[str]) -> None:
    with pytest.raises(SystemExit) as stopped:
        idle_watch.parser().parse_args(argv)
    assert stopped.value.code == 2
