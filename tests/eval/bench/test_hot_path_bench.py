"""rory_eval/bench/hot_path_bench.py runs against the runtime as it is: its stand-ins for rclpy's
subscription and timer must offer what the runtime wraps."""

from __future__ import annotations

import pytest

from rory_eval.bench import hot_path_bench


def test_the_bench_runs_every_configuration_and_prints_its_table(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert hot_path_bench.main(['--events', '50', '--repeats', '1']) == 0
    table = capsys.readouterr().out
    for event in ('LaserScan (360 beams)', 'timer tick, one clock reading'):
        for config in ('bare', 'restart', 'rory'):
            assert f'| {event} | {config} |' in table
