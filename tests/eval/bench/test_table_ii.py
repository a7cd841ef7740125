"""Table II on a quiet machine: pairs of bare and RORY runs, their medians, and sittings merged."""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

import pytest

from rory_eval.bench import stack_bench, table_ii
from rory_eval.bench.table_ii import STACK, Pair, Row, TableIIError, merge, row, table
from rory_eval.runs import runner
from rory_eval.runs.plan import RunSpec
from rory_eval.runs.runner import RunRecord


def test_ratio_and_added_memory_are_medians_of_each_pair() -> None:
    pairs = [Pair(10.0, 60.0, 12.0, 110.0, 1.5),
             Pair(20.0, 62.0, 22.0, 100.0, 1.0),  # a slower repetition, for both
             Pair(11.0, 61.0, 13.2, 111.0, 2.0)]
    r = row('amcl', pairs)
    assert r.pairs == 3 and r.failed == 0
    assert r.bare_cpu == 11.0 and r.rory_cpu == 13.2
    # Pair ratios 1.2, 1.1, 1.2: the median of the ratios, not the ratio of the medians (1.2).
    assert r.cpu_ratio == pytest.approx(1.2)
    assert r.pss_added == pytest.approx(50.0)
    assert r.rory_own_cpu == 1.5
    # The node's own process: (12 - 1.5) / 10, (22 - 1) / 20, (13.2 - 2) / 11.
    assert r.node_ratio == pytest.approx(1.05)


def test_a_program_with_no_pair_has_no_figures() -> None:
    r = row('amcl', [], failed=3)
    assert r.pairs == 0 and r.failed == 3 and math.isnan(r.cpu_ratio)
    assert '| amcl | 0 (3 failed) | - | - | - | - | - | - |' in table([r])


def test_the_table_lists_targets_in_their_order_and_the_stack_last() -> None:
    rows = [row(STACK, [Pair(60.0, 400.0, 63.0, 450.0, 2.0)]),
            row('lama_local', [Pair(10.0, 60.0, 12.0, 110.0, 1.5)]),
            row('grid_slam', [Pair(10.0, 58.0, 11.0, 100.0, 1.0)])]
    lines = table(rows).splitlines()
    assert lines[2].startswith('| grid_slam | 1 | 10.0% | 58 MB | 11.0% (1.10x) | 100 MB (+42 MB)')
    assert lines[3].startswith('| lama_local |')
    assert lines[4] == ('| the six, one supervisor | 1 | 60.0% | 400 MB | 63.0% (1.05x) '
                        '| 450 MB (+50 MB) | 2.0% | 1.02x |')


def sitting(*programs: str) -> dict[str, Any]:
    return {'date': '2026-11-26 23:00 UTC', 'minutes': 12.5, 'world': 'real_room',
            'load_before': 0.4, 'load_after': 1.1, 'command': 'python -m x',
            'rows': [row(p, [Pair(10.0, 60.0, 12.0, 110.0, 1.5)]) for p in programs]}


def test_sittings_merge_and_a_program_measured_twice_is_refused() -> None:
    assert [r.program for r in merge([sitting('amcl'), sitting('grid_slam', STACK)])] == [
        'amcl', 'grid_slam', STACK]
    with pytest.raises(TableIIError, match='amcl is in two of the folders'):
        merge([sitting('amcl'), sitting('amcl')])


def write(folder: Path, data: dict[str, Any]) -> Path:
    folder.mkdir(parents=True)
    (folder / table_ii.RESULT).write_text(
        json.dumps({**data, 'rows': [asdict(r) for r in data['rows']]}))
    return folder


def test_report_merges_the_folders_of_two_sittings(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    one = write(tmp_path / 'one', sitting('grid_slam', 'amcl'))
    two = write(tmp_path / 'two', sitting(STACK))
    assert table_ii.main(['--report', str(one), str(two)]) == 0
    out = capsys.readouterr().out
    assert '| grid_slam | 1 |' in out and '| the six, one supervisor | 1 |' in out
    assert 'load average 0.40 before and 1.10 after: `python -m x` (grid_slam, amcl)' in out


def test_report_names_a_folder_it_cannot_read(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    assert table_ii.main(['--report', str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f'table_ii: {tmp_path / table_ii.RESULT}: no such file '
                   '(not a folder this bench wrote)']
    (tmp_path / table_ii.RESULT).write_text('{"rows": [{"program": 1}]}')
    assert table_ii.main(['--report', str(tmp_path)]) == 2
    assert 'not a Table II result' in capsys.readouterr().err


def test_a_sitting_with_nothing_to_run_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        table_ii.main(['--targets', '--stack-runs', '0'])
    assert exit_.value.code == 2
    assert 'nothing to run' in capsys.readouterr().err


def test_a_target_runs_alternating_and_a_failed_run_loses_only_its_pair(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    order: list[tuple[int, str]] = []

    def fake_execute(spec: RunSpec, out: Path, *, domain_id: int,
                     instrumented: Path) -> RunRecord:
        order.append((spec.repetition, spec.method))
        assert spec.crash_at is None and spec.world == 'real_room'
        failed = spec.repetition == 1 and spec.method == 'rory'
        cpu = 10.0 if spec.method == 'bare' else 12.0
        return RunRecord(run=spec.to_json(), error='the clock never started' if failed else '',
                         steady_cpu_percent=cpu, pss_mb=60.0 if spec.method == 'bare' else 110.0,
                         usage_by_role={'node': {'steady_cpu_percent': cpu - 1.0}})

    monkeypatch.setattr(runner, 'execute', fake_execute)
    monkeypatch.setattr(runner, 'instrument', lambda target, into: into)
    pairs, failed = table_ii.target_pairs('amcl', 'real_room', 3, tmp_path, 88,
                                          progress=lambda line: None)
    assert order == [(0, 'bare'), (0, 'rory'), (1, 'rory'), (1, 'bare'), (2, 'bare'),
                     (2, 'rory')]
    assert failed == 1
    assert pairs == [Pair(10.0, 60.0, 12.0, 110.0, 1.0)] * 2


def test_rows_survive_the_json_they_are_written_to(tmp_path: Path) -> None:
    data = write(tmp_path / 'one', sitting('navigator'))
    loaded = table_ii.load(data)
    assert loaded['rows'] == [row('navigator', [Pair(10.0, 60.0, 12.0, 110.0, 1.5)])]
    assert isinstance(loaded['rows'][0], Row)


def test_the_stack_pairs_the_six_bare_with_the_six_under_one_supervisor(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    runs: list[tuple[str, Path]] = []

    def fake_run_once(config: str, world: str, out: Path, domain: int) -> dict[str, Any]:
        runs.append((config, out))
        if config == 'rory' and len(runs) == 3:
            raise RuntimeError('the clock never started')
        cpu = 60.0 if config == 'bare' else 63.0
        return {'config': config, 'cpu_percent': cpu, 'pss_mb': 400.0 if config == 'bare'
                else 450.0, 'goal_reached': True,
                'roles': {'node': {'cpu_percent': 60.5 if config == 'rory' else cpu}}}

    monkeypatch.setattr(stack_bench, 'run_once', fake_run_once)
    pairs, failed = table_ii.stack_pairs('real_room', 2, tmp_path, 88, progress=lambda _: None)
    assert [c for c, _ in runs] == ['bare', 'rory', 'rory', 'bare']
    assert runs[0][1] == tmp_path / 'stack' / 'bare-0'
    assert failed == 1
    assert pairs == [Pair(60.0, 400.0, 63.0, 450.0, 2.5)]
