"""The load campaign (rory_eval/faults/load_campaign.py) on fakes: its hogs started pinned and
always reaped, its counting of engagements and kills, its verdicts and exit codes; and real
hogs (OS processes only, no ROS): busy, pinned, gone afterwards however the campaign ends."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from rory_eval.faults import load_campaign
from rory_eval.faults.load_campaign import (
    NO_CRASH,
    Load,
    Options,
    RunRecord,
    compare_no_crash,
    from_scenario,
    table,
    totals,
)
from rory_eval.harness.scenario import ScenarioResult

_pids = itertools.count(40000)


class FakeProcess:
    """A hog that never runs: it records being killed and reaped."""

    def __init__(self) -> None:
        self.pid = next(_pids)
        self.killed = False
        self.reaped = False

    def poll(self) -> int | None:
        return -9 if self.killed else None

    def kill(self) -> None:
        self.killed = True

    def wait(self, timeout: float | None = None) -> int:
        assert self.killed, 'waited for a hog nobody killed: it would block forever'
        self.reaped = True
        return -9


class FakeOS:
    """The operating system a Load sees in these tests."""

    def __init__(self, fail_pin_at: int | None = None) -> None:
        self.processes: list[FakeProcess] = []
        self.pins: list[tuple[int, set[int]]] = []
        self.fail_pin_at = fail_pin_at

    def spawn(self) -> FakeProcess:
        process = FakeProcess()
        self.processes.append(process)
        return process

    def pin(self, pid: int, cores: set[int]) -> None:
        if len(self.pins) == self.fail_pin_at:
            raise OSError('no such core')
        self.pins.append((pid, cores))

    def load(self, per_core: int) -> Load:
        return Load(per_core, cores=[0, 1], spawn=self.spawn, pin=self.pin,
                    nice=lambda _pid: 0, cpu=lambda _pid: 12.5, clock=time.monotonic,
                    loadavg=lambda: (4.2, 3.1, 2.0), sample_every=0.01)

    @property
    def all_reaped(self) -> bool:
        return bool(self.processes) and all(p.killed and p.reaped for p in self.processes)


def test_hogs_are_started_per_core_each_pinned_to_its_core_and_reaped_on_the_way_out() -> None:
    fake = FakeOS()
    with fake.load(2) as load:
        assert len(fake.processes) == 4
        assert [cores for _, cores in fake.pins] == [{0}, {0}, {1}, {1}]
        assert [pid for pid, _ in fake.pins] == [p.pid for p in fake.processes]
        assert not any(p.killed for p in fake.processes)
    assert fake.all_reaped
    assert all(h.cpu_s == 12.5 and h.wall_s is not None for h in load.hogs)
    report = load.report()
    assert all(str(p.pid) in report for p in fake.processes)
    assert 'Load average at the end (1, 5, 15 min): 4.20, 3.10, 2.00' in report


def test_a_hog_that_cannot_be_pinned_takes_off_those_already_started() -> None:
    fake = FakeOS(fail_pin_at=2)
    with pytest.raises(OSError, match='no such core'), fake.load(2):
        pytest.fail('the load must not be entered')
    assert len(fake.processes) == 3
    assert fake.all_reaped


def _record(part: str = 'one', *, struck: bool = False, **fields: Any) -> RunRecord:
    kind = fields.pop('kind', 'SIGKILL' if struck else NO_CRASH)
    return RunRecord(part, kind, fields.pop('label', 'a run'), Path('/nonexistent/run'), struck,
                     **{'exact': True, 'lost': 0, 'twice': 0, 'hang_limit': 1.0, **fields})


def _parts(*records: RunRecord, raising: BaseException | None = None) -> dict[str, Any]:
    def part(_options: Options, _root: Path, _domain: int) -> Iterator[RunRecord]:
        yield from records
        if raising is not None:
            raise raising

    return dict.fromkeys(load_campaign.PARTS, part)


@pytest.fixture
def quiet_sigterm(monkeypatch: pytest.MonkeyPatch) -> None:
    """main() must not install its SIGTERM handler in the test process."""
    monkeypatch.setattr(load_campaign, 'exit_on_sigterm', lambda: None)


@pytest.mark.usefixtures('quiet_sigterm')
def test_the_hogs_are_reaped_when_a_part_raises_and_the_campaign_fails(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    fake = FakeOS()
    code = load_campaign.main(['--load', '1', '--parts', 'one', '--out', str(tmp_path)],
                              parts=_parts(_record(), raising=RuntimeError('the ring broke')),
                              load=fake.load)
    assert code == 1
    assert fake.all_reaped
    out = capsys.readouterr().out
    assert 'part one stopped: RuntimeError: the ring broke' in out
    assert all(str(p.pid) in out for p in fake.processes)  # the hogs' pids are printed


@pytest.mark.usefixtures('quiet_sigterm')
@pytest.mark.parametrize('stop', [KeyboardInterrupt(), SystemExit(128 + signal.SIGTERM)])
def test_the_hogs_are_reaped_on_ctrl_c_and_sigterm(tmp_path: Path, stop: BaseException) -> None:
    # exit_on_sigterm turns SIGTERM into SystemExit, Ctrl-C is KeyboardInterrupt: both end the
    # campaign (they are not a failed part) and both leave through the load's exit.
    fake = FakeOS()
    with pytest.raises(type(stop)):
        load_campaign.main(['--load', '2', '--out', str(tmp_path)],
                           parts=_parts(_record(), raising=stop), load=fake.load)
    assert len(fake.processes) == 4
    assert fake.all_reaped


@pytest.mark.usefixtures('quiet_sigterm')
def test_exit_0_when_every_run_passes_1_when_one_fails(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    good = [_record(), _record(struck=True, kills=1, exits=1, recoveries=1, safe_state=1)]
    args = ['--load', '1', '--parts', 'one', 'four', '--out', str(tmp_path)]
    assert load_campaign.main(args, parts=_parts(*good), load=FakeOS().load) == 0
    capsys.readouterr()
    bad = _record(label='integrator, no fault', safe_state=1)
    assert load_campaign.main(args, parts=_parts(*good, bad), load=FakeOS().load) == 1
    out = capsys.readouterr().out
    assert ('- part one, integrator, no fault: 1 safe-state engagements without a fault '
            '-> /nonexistent/run') in out


@pytest.mark.parametrize('argv', [
    [], ['--load', '-1'], ['--load', 'two'], ['--load', '1', '--parts', 'five'],
    ['--load', '1', '--runs', '0'], ['--load', '1', '--no-crash', '0'],
    ['--load', '1', '--targets', 'nobody'],
])
def test_bad_arguments_exit_2_with_one_line(argv: list[str],
                                            capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stopped:
        load_campaign.main(argv, parts={}, load=FakeOS().load)
    assert stopped.value.code == 2
    assert len([line for line in capsys.readouterr().err.splitlines()
                if line.startswith('python -m rory_eval.faults.load_campaign: error:')]) == 1


def _result(events: list[dict[str, Any]], e_stop: list[tuple[float, bool]],
            kills: list[tuple[str, float]]) -> ScenarioResult:
    return ScenarioResult('rory', 300, {'history': list(range(1, 301))}, [
        e for e in events if e['kind'] == 'recovered'], kills, e_stop, events)


def test_engagements_kills_crashes_and_hangs_are_counted_from_the_run() -> None:
    events = [
        {'kind': 'state', 'new': 'RUNNING'},
        {'kind': 'hang', 'waiting_for': 'heartbeat', 'stalled_s': 1.24},
        {'kind': 'hang', 'waiting_for': 'start', 'stalled_s': 61.0},  # a kill, not a hang found
        {'kind': 'unheard', 'beating_s': 10.2},
        {'kind': 'exit', 'code': -9}, {'kind': 'exit', 'code': -9}, {'kind': 'exit', 'code': -11},
        {'kind': 'safe_state', 'what': 'held'}, {'kind': 'safe_state', 'what': 'released'},
        {'kind': 'recovered', 'crashes': 2},
        {'kind': 'state', 'new': 'FATAL'},
    ]
    e_stop = [(0.0, False), (1.0, True), (2.0, False)]
    record = from_scenario(_record(), _result(events, e_stop, [('hang at 2 s', 5.0),
                                                               ('at 3 s', 6.0)]))
    assert (record.kills, record.exits, record.recoveries, record.give_ups) == (3, 3, 1, 1)
    assert record.safe_state == 1
    assert record.hang_stalls == [1.24]
    assert record.hang_strikes == 1
    # /e_stop heard more often than the supervisor recorded (a rated hold): the larger count.
    again = from_scenario(_record(), _result([], [(0.0, True), (0.5, True)], []))
    assert again.safe_state == 2
    assert again.kills == again.exits == again.recoveries == 0


def test_a_run_without_a_fault_fails_on_any_engagement_kill_crash_or_recovery() -> None:
    assert _record().failures() == []
    assert _record(safe_state=1).failures() == ['1 safe-state engagements without a fault']
    assert _record(kills=1, exits=1, recoveries=1).failures() == [
        '1 kills without a fault', '1 crashes without a fault', '1 recoveries without a fault']
    assert _record(exact=False, problems=['count 199']).failures() == ['not exact (count 199)']
    assert _record(lost=2, twice=1).failures() == ['2 lost', '1 applied twice']
    # part two has no safe state: nothing to engage, not a failure
    assert _record(safe_state=None).failures() == []


def test_a_struck_run_may_be_killed_and_recovered_but_must_be_exact() -> None:
    assert _record(struck=True, kills=2, exits=2, recoveries=2, safe_state=2).failures() == []
    assert _record(struck=True, exact=False, lost=3).failures() == ['not exact', '3 lost']
    assert _record(struck=True, give_ups=1).failures() == ['1 give-ups']
    assert _record(struck=True, error='did not run: RuntimeError: x').failures() == [
        'did not run: RuntimeError: x']


def test_a_hang_struck_must_be_found_within_its_timeout() -> None:
    assert _record(struck=True, hang_strikes=1, hang_stalls=[1.24]).failures() == []
    assert _record(struck=True, hang_strikes=1, hang_stalls=[1.5]).failures() == []
    assert _record(struck=True, hang_strikes=1).failures() == ['1 hang struck, none found']
    assert _record(struck=True, hang_strikes=1, hang_stalls=[1.62]).failures() == [
        'a hang found after 1.62 s of silence (hang_timeout 1 s)']
    # a hang found in a run without a fault is a kill too
    assert _record(kills=1, hang_stalls=[1.2]).failures() == ['1 kills without a fault']


def test_a_part_s_table_and_the_totals() -> None:
    records = [_record(), _record(struck=True, kind='hang', hang_strikes=1, hang_stalls=[1.3],
                                  kills=1, exits=1, recoveries=1),
               _record(struck=True, kind='SIGKILL', exits=1, recoveries=1, lost=None,
                       twice=None)]
    text = table(records)
    assert '| without a fault | 1 | 1 | 1 | 0 | 0 | - | 0 | 0 | 0 | 0 | 0 | 0 | 0 |' in text
    assert '| hang | 1 | 1 | 1 | 0 | 0 | - | 0 | 1 | 1 (1.30 s; limit 1 s) | 1 | 1 | 1 | 0 |' \
        in text
    assert '| SIGKILL | 1 | 1 | 1 | - | - | - | 0 | 0 | 0 | 0 | 1 | 1 | 0 |' in text
    assert '| **all** | 3 |' in text
    every = totals(records)
    assert '| without a fault | 1 |' in every and '| with a fault | 2 |' in every


def test_a_run_without_a_fault_is_compared_with_the_reference_up_to_both_ends() -> None:
    reference = {1: b'a', 2: b'b', 3: b'c', 4: b'd'}
    assert compare_no_crash(reference, {1: b'a', 2: b'b', 3: b'c'}) == (0, 0)  # cut earlier
    assert compare_no_crash(reference, {1: b'a', 2: b'b', 3: b'c', 4: b'd', 5: b'e'}) == (0, 0)
    assert compare_no_crash(reference, {1: b'a', 3: b'x'}) == (1, 1)
    assert compare_no_crash(reference, {}) == (4, 0)


def _hog_cpu(pid: int) -> float:
    seconds = load_campaign.cpu_seconds(pid)
    assert seconds is not None
    return seconds


def _gone(pid: int) -> bool:
    """Not running: no such process, or a zombie (a SIGKILLed campaign's hog is reaped by
    whoever inherits it, perhaps never in a container)."""
    try:
        stat = Path(f'/proc/{pid}/stat').read_text()
    except FileNotFoundError:
        return True
    return stat.rsplit(')', 1)[1].split()[0] in ('Z', 'X')


def test_a_real_hog_is_busy_on_its_core_at_our_nice_value_and_gone_afterwards() -> None:
    core = max(os.sched_getaffinity(0))
    with Load(1, cores=[core]) as load:
        (hog,) = load.hogs
        assert os.sched_getaffinity(hog.pid) == {core}
        assert os.getpriority(os.PRIO_PROCESS, hog.pid) == os.getpriority(os.PRIO_PROCESS, 0)
        first = _hog_cpu(hog.pid)
        deadline = time.monotonic() + 3.0
        while _hog_cpu(hog.pid) < first + 0.2 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _hog_cpu(hog.pid) >= first + 0.2  # it computes: its CPU time grows
    assert _gone(hog.pid)
    assert hog.cpu_s is not None and hog.cpu_s >= 0.2 and hog.share is not None


CAMPAIGN = '''
import sys, time
from rory_eval.faults.load_campaign import Load
from rory_eval.harness.simrun import exit_on_sigterm
exit_on_sigterm()
with Load(1, cores=[int(sys.argv[1])]) as load:
    print(load.hogs[0].pid, flush=True)
    time.sleep(30)
'''


@pytest.mark.parametrize('how', [signal.SIGTERM, signal.SIGKILL])
def test_no_hog_outlives_a_campaign_stopped_by_sigterm_or_killed(how: signal.Signals) -> None:
    core = max(os.sched_getaffinity(0))
    campaign = subprocess.Popen([sys.executable, '-c', CAMPAIGN, str(core)],
                                stdout=subprocess.PIPE, text=True)
    try:
        assert campaign.stdout is not None
        pid = int(campaign.stdout.readline())
        assert not _gone(pid)
        campaign.send_signal(how)
        assert campaign.wait(timeout=10) == (128 + signal.SIGTERM if how == signal.SIGTERM
                                             else -signal.SIGKILL)
        deadline = time.monotonic() + 3.0  # SIGKILLed: the kernel ends it (PR_SET_PDEATHSIG)
        while not _gone(pid) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert _gone(pid)
    finally:
        if campaign.poll() is None:
            campaign.kill()
            campaign.wait()
