"""The evaluation's tables: symbols, medians, overhead ratios, CSV."""

from __future__ import annotations

import csv
import os
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from rory_eval.evaluation.judge import Verdict
from rory_eval.evaluation.report import (
    columns,
    correctness_table,
    first_start,
    judge_all,
    overhead_by_process,
    overhead_table,
    recovery_table,
    running_time,
    steps_table,
    symbol,
    write_csv,
)
from rory_eval.runs.plan import BARE, RunSpec
from rory_eval.runs.runner import RunRecord


def test_symbols_follow_the_paper() -> None:
    ok, bad, unknown = Verdict(True), Verdict(False), Verdict(None)
    assert symbol([ok, ok, ok]) == '✓'
    assert symbol([bad, bad]) == '✗'
    assert symbol([ok, bad, ok]) == '? 2/3'
    assert symbol([ok, unknown]) == '✓ 1/1 of 2'
    assert symbol([unknown]) == 'n/a'
    assert symbol([]) == ''


def _runs(tmp_path: Path) -> list[tuple[RunRecord, Path]]:
    """grid_slam in office_small: a reference, restart (wrong map), rory (same map), and an
    overhead pair."""
    room = np.full((60, 60), -1, dtype=np.int8)
    room[5:55, 5:55] = 100
    room[6:54, 6:54] = 0
    half = room.copy()
    half[:, :30] = -1
    runs = []
    for method, crash, grid, total, cpu, rss in (
            (BARE, None, room, None, 10.0, 80.0),
            ('rory', None, room, None, 11.0, 120.0),
            ('restart', 9.0, half, 1500.0, 0.0, 0.0),
            ('rory', 9.0, room, 300.0, 0.0, 0.0)):
        spec = RunSpec('grid_slam', 'office_small', method, 0, crash, 30.0)
        folder = tmp_path / spec.name
        folder.mkdir()
        np.savez_compressed(folder / 'final_map.npz', data=grid, resolution=0.05, origin_x=0.0,
                            origin_y=0.0)
        events = [] if total is None else [{
            'kind': 'recovered', 'total_ms': total, 's1_ms': 1.0, 's2_ms': 2.0,
            'restart_ms': total - 100.0, 'restore_ms': 50.0, 'sync_ms': 20.0,
            'replay_ms': 25.0, 's4_ms': 2.0}]
        runs.append((RunRecord(run=spec.to_json(), events=events, cpu_percent=cpu,
                               peak_rss_mb=rss), folder))
    return runs


def test_tables_from_records(tmp_path: Path) -> None:
    runs = _runs(tmp_path)
    judged = judge_all(runs)
    assert [(j.record.spec.method, j.verdict.correct) for j in judged] == [
        ('restart', False), ('rory', True)]
    table_one = correctness_table(judged, ('restart', 'rory'))
    assert '| grid_slam (hector_mapping) | ✗ | ✓ |' in table_one
    assert 'office_small restart | office_small rory' in table_one
    assert '| grid_slam | 1500 | 300 |' in recovery_table(judged)
    steps = steps_table(judged)
    assert '| grid_slam | rory | 1 | 300 | 1 | 2 | 200 | 50 | 45 | 2 |' in steps
    overhead = overhead_table(runs)
    assert '| grid_slam | office_small | 1 | 10.0% | 80 MB | 11.0% (1.10x) |' in overhead
    assert '120 MB (1.50x, +40 MB)' in overhead


def test_a_method_at_the_other_pace_has_its_own_column_beside_it(tmp_path: Path) -> None:
    runs = _runs(tmp_path)
    rory_fast = runs[3][0]
    paced = RunSpec('grid_slam', 'office_small', 'rory', 0, 9.0, 30.0, replay='paced',
                    beside=True)
    folder = tmp_path / paced.name
    folder.mkdir()
    (folder / 'final_map.npz').write_bytes((runs[3][1] / 'final_map.npz').read_bytes())
    events = [dict(rory_fast.events[0], total_ms=900.0)]
    runs.append((RunRecord(run=paced.to_json(), events=events), folder))
    judged = judge_all(runs)
    assert [(j.record.spec.column, j.verdict.correct) for j in judged] == [
        ('restart', False), ('rory', True), ('rory paced', True)]
    recovery = recovery_table(judged)
    assert 'office_small rory | office_small rory paced |' in recovery
    assert '| grid_slam | 1500 | 300 | 900 |' in recovery
    table_three = correctness_table(judged, columns(judged, ('checkpoint', 'replay', 'rory')))
    assert '| grid_slam (hector_mapping) | ✓ | ✓ |' in table_three
    assert '| grid_slam | rory paced | 1 | 900 |' in steps_table(judged)
    # Table I keeps to the evaluation's own pace.
    assert 'paced' not in correctness_table(judged, ('restart', 'rory'))


def test_the_csv_has_a_row_per_run_with_its_verdict(tmp_path: Path) -> None:
    runs = _runs(tmp_path)
    write_csv(tmp_path / 'runs.csv', runs, judge_all(runs))
    with (tmp_path / 'runs.csv').open() as f:
        rows = list(csv.DictReader(f))
    assert [(r['method'], r['correct']) for r in rows] == [
        (BARE, ''), ('rory', ''), ('restart', '0'), ('rory', '1')]
    assert rows[2]['total_ms'] == '1500.0' and 'coverage=' in rows[2]['measures']


def test_running_time_sums_sittings_not_the_gaps_between_them(tmp_path: Path) -> None:
    # Two runs in parallel, then one after them; a day later, the rest of the evaluation.
    t0 = 1_800_000_000.0
    runs = []
    for k, (end, wall) in enumerate(((t0 + 30, 30.0), (t0 + 40, 35.0), (t0 + 75, 30.0),
                                     (t0 + 86_400 + 60, 60.0))):
        spec = RunSpec('grid_slam', 'office_small', BARE, k, None, 30.0)
        folder = tmp_path / spec.name
        folder.mkdir()
        record = RunRecord(run=spec.to_json(), wall_seconds=wall)
        record.save(folder)
        os.utime(folder / 'record.json', (end, end))
        runs.append((record, folder))
    busy, sittings = running_time(runs)
    assert sittings == 2
    assert busy == 75.0 + 60.0  # t0..t0+75, then the 60 s run
    # The evaluation's date is its first run's start, whenever the report is made.
    assert first_start(runs) == datetime.fromtimestamp(t0, UTC)
    assert first_start([(RunRecord(run=runs[0][0].run), tmp_path / 'none')]) is None


def test_overhead_by_process_shows_each_role_and_the_steady_half() -> None:
    def record(method: str, roles: dict[str, dict[str, float]], cpu: float, steady: float,
               rss: float, pss: float) -> tuple[RunRecord, Path]:
        spec = RunSpec('amcl', 'real_room', method, 0, None, 30.0)
        return (RunRecord(run=spec.to_json(), cpu_percent=cpu, steady_cpu_percent=steady,
                          peak_rss_mb=rss, pss_mb=pss, usage_by_role=roles), Path())

    def role(cpu: float, steady: float, rss: float, pss: float) -> dict[str, float]:
        return {'cpu_percent': cpu, 'steady_cpu_percent': steady, 'peak_rss_mb': rss,
                'pss_mb': pss}

    runs = [
        record(BARE, {'node': role(10.0, 9.5, 85.0, 70.0)}, 10.0, 9.5, 85.0, 70.0),
        record('rory', {'node': role(11.0, 10.5, 95.0, 60.0),
                        'supervisor': role(1.5, 0.8, 82.0, 45.0),
                        'standby': role(4.0, 0.3, 78.0, 40.0)}, 16.5, 11.6, 255.0, 145.0),
        # A record from before the breakdown has no roles and is left out.
        (RunRecord(run=RunSpec('amcl', 'real_room', 'rory', 1, None, 30.0).to_json(),
                   cpu_percent=99.0, peak_rss_mb=999.0), Path()),
    ]
    table = overhead_by_process(runs)
    assert '| amcl | real_room | bare | node | 10.0% | 9.5% | 85 MB | 70 MB |' in table
    assert '| amcl | real_room | rory | standby | 4.0% | 0.3% | 78 MB | 40 MB |' in table
    assert '| amcl | real_room | rory | **all** | 16.5% | 11.6% | 255 MB | 145 MB |' in table
    assert '99.0' not in table and '| bare | **all**' not in table
    assert overhead_by_process(runs[2:]) == ''
