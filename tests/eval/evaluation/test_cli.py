"""`rory eval`'s command line: which methods also run at the other replay pace."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest

from rory_eval.bench import table_ii
from rory_eval.evaluation import cli
from rory_eval.evaluation.cli import main, parse_args
from rory_eval.runs.plan import build_plan
from rory_eval.runs.runner import RunRecord


def test_rory_also_runs_paced_by_default_but_not_in_the_quick_evaluation() -> None:
    assert parse_args([]).other_pace == ['rory']
    assert parse_args(['--replay', 'paced']).other_pace == ['rory']  # then fast beside
    assert parse_args(['--quick']).other_pace == []
    assert parse_args(['--methods', 'restart', 'checkpoint']).other_pace == []
    assert parse_args(['--other-pace']).other_pace == []
    assert parse_args(['--other-pace', 'replay', 'rory']).other_pace == ['replay', 'rory']


def test_a_method_without_a_pace_is_refused_in_one_line(capsys: pytest.CaptureFixture[str]
                                                         ) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(['--other-pace', 'restart'])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "--other-pace: invalid choice: 'restart'" in err[-1]


def test_report_only_runs_nothing_and_says_what_is_not_recorded(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """--report-only starts no run and instruments nothing; it reports what is not recorded.

    Issue 35: this failed with "--report-only started a process" when run beside other tests
    on a fresh machine. The process was not a run: it was matplotlib's ``fc-list``. The report
    imports matplotlib.pyplot for its figures, and a first import that finds no readable font
    cache (~/.cache/matplotlib/fontlist-v*.json) builds one by running ``fc-list`` through
    subprocess.check_output, which calls subprocess.run - and the test had replaced
    subprocess.run for the whole process. Alone, it passed where an earlier import had left the
    cache; in a parallel run it failed when no other test had written the cache yet (or one was
    writing it: matplotlib truncates the file before writing, and the reader takes no lock).
    With the cache directory empty it failed every time. Now only a process started by the
    evaluation's own code counts (the first caller outside the subprocess module is in
    rory_eval), and no run's folder nor the instrumented copies may appear.
    """
    real_run = subprocess.run

    def no_run(*args: Any, **kwargs: Any) -> Any:
        frame = sys._getframe(1)
        while frame.f_back is not None and frame.f_globals.get('__name__') == 'subprocess':
            frame = frame.f_back  # check_output, call: the caller is whoever called those
        caller = frame.f_globals.get('__name__', '')
        if caller.split('.')[0] == 'rory_eval':
            raise AssertionError(f'--report-only started a process from {caller}: {args}')
        return real_run(*args, **kwargs)  # a library's own helper process (matplotlib's fc-list)

    def no_instrumenting(*args: object, **kwargs: object) -> None:
        raise AssertionError('--report-only instrumented a target')

    monkeypatch.setattr(subprocess, 'run', no_run)
    monkeypatch.setattr(cli, 'instrument', no_instrumenting)
    out = tmp_path / 'eval-out'
    (out / 'runs').mkdir(parents=True)
    argv = ['--targets', 'grid_slam', '--worlds', 'office_small', '--methods', 'restart',
            '--repetitions', '1', '--out', str(out), '--report-only']
    plan_runs = build_plan(['grid_slam'], ['office_small'], ['restart'], repetitions=1,
                               crash_at=9.0, random_crash=False, duration=None, seed=0,
                               replay='fast', overhead_worlds=['real_room'], other_pace=[]).runs
    # One run recorded, and failed: reported as it failed, not run again.
    failed = plan_runs[0]
    (out / 'runs' / failed.name).mkdir()
    RunRecord(run=failed.to_json(), error='the clock never started').save(
        out / 'runs' / failed.name)
    assert main(argv) == 1
    text = (out / 'results.md').read_text()
    assert f'- {failed.name}: the clock never started' in text
    for spec in plan_runs[1:]:
        assert f'- {spec.name}: not recorded in {out / "runs" / spec.name}' in text
    assert [p.name for p in (out / 'runs').iterdir()] == [failed.name]
    assert not (out / 'instrumented').exists()


def test_report_only_without_recorded_runs_is_refused_in_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['--quick', '--out', str(tmp_path / 'nowhere'), '--report-only']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f'rory eval: --report-only: {tmp_path / "nowhere" / "runs"} does not exist '
                   '(no runs recorded there)']
    assert not (tmp_path / 'nowhere').exists()


def test_a_table_ii_folder_that_is_not_one_is_refused_before_any_run(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['--quick', '--out', str(tmp_path / 'out'), '--table-ii', str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f'rory eval: --table-ii: {tmp_path}/table_ii.json')
    assert not (tmp_path / 'out').exists()


def test_the_quiet_table_ii_comes_first_and_the_loaded_runs_are_named_as_such(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sitting = tmp_path / 'quiet'
    sitting.mkdir()
    (sitting / table_ii.RESULT).write_text(json.dumps({
        'date': '2026-11-27 00:10 UTC', 'minutes': 30.0, 'world': 'real_room',
        'load_before': 0.3, 'load_after': 1.2, 'command': 'python -m rory_eval.bench.table_ii',
        'rows': [asdict(table_ii.row('grid_slam', [table_ii.Pair(10.0, 58.0, 11.0, 100.0,
                                                                1.0)]))]}))
    out = tmp_path / 'eval-out'
    (out / 'runs').mkdir(parents=True)
    assert main(['--quick', '--out', str(out), '--report-only', '--table-ii', str(sitting)]) == 1
    text = (out / 'results.md').read_text()
    quiet = text.index('## Table II: overhead')
    loaded = text.index("## Overhead under the evaluation's load")
    assert quiet < loaded
    assert '| grid_slam | 1 | 10.0% | 58 MB | 11.0% (1.10x) | 100 MB (+42 MB) | 1.0% |' in text
    assert text.count('## Table II:') == 1
