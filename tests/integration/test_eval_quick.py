"""``rory eval --quick`` end to end: real runs of grid_slam in office_small, every method.

This is the CI smoke test of the evaluation (issue: Tables I-IV from one command). The paper's
headline must come out of real runs: after a SIGKILL at 9 s, ROS's respawn leaves an incomplete
map and RORY (and replay alone) the complete one.
"""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from rory_eval.runs.plan import METHODS

pytestmark = pytest.mark.ros


def test_quick_evaluation_writes_the_tables_and_restart_loses_the_map(
        tmp_path: Path, ros_domain: int) -> None:
    out = tmp_path / 'eval'
    # A relative --out, as `make eval` gives it: the supervisor respawns from elsewhere.
    # Two runs at a time, as `make eval` does (domains ros_domain and the next one).
    done = subprocess.run(
        [sys.executable, '-m', 'rory_eval.evaluation', '--quick', '--out', 'eval',
         '--jobs', '2', '--domain', str(ros_domain)],
        capture_output=True, text=True, timeout=600, check=False, cwd=tmp_path)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    with (out / 'runs.csv').open() as f:
        rows = list(csv.DictReader(f))
    assert [r['method'] for r in rows] == ['bare', 'rory', *METHODS]
    assert not [r for r in rows if r['error']]
    verdict = {r['method']: r['correct'] for r in rows if r['crash_at']}
    assert verdict['restart'] == '0' and verdict['rory'] == '1' and verdict['replay'] == '1'
    recovered = {r['method']: float(r['total_ms']) for r in rows if r['total_ms']}
    assert set(recovered) == set(METHODS)  # the supervisor timed every recovery
    results = (out / 'results.md').read_text()
    assert '| grid_slam (hector_mapping) | ✗ | ✓ |' in results  # Table I
    for heading in ('Table I:', 'Table II:', 'Table III:', 'Table IV:'):
        assert heading in results
    assert '`rory eval --quick --out eval --jobs 2' in results  # the command that made it
    assert (out / 'figures' / 'grid_slam-office_small.png').stat().st_size > 10_000
    # A second invocation finds every run recorded and only rewrites the report.
    again = subprocess.run(
        [sys.executable, '-m', 'rory_eval.evaluation', '--quick', '--out', 'eval',
         '--domain', str(ros_domain)],
        capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path)
    assert again.returncode == 0 and '6/6 runs' in again.stderr
