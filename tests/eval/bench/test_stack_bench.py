"""The stack bench's summary: medians per configuration, each against the bare run beside it."""

from __future__ import annotations

from typing import Any

import pytest

from rory_eval.bench.stack_bench import summarise, table


def record(config: str, cpu: float, pss: float) -> dict[str, Any]:
    return {'config': config, 'cpu_percent': cpu, 'pss_mb': pss,
            'roles': {'node': {'cpu_percent': cpu, 'pss_mb': pss, 'processes': 6}}}


def test_each_configuration_is_set_against_the_bare_run_of_its_repetition() -> None:
    runs = [record('bare', 30.0, 260.0), record('restart', 31.5, 290.0),
            record('rory', 33.0, 310.0),
            record('rory', 44.0, 320.0), record('restart', 42.0, 300.0),
            record('bare', 40.0, 262.0)]
    summary = summarise(runs)
    # repetition 1: 33/30 = 1.10, repetition 2: 44/40 = 1.10; restart 1.05 both times
    assert summary['rory']['cpu_ratio'] == pytest.approx(1.10)
    assert summary['restart']['cpu_ratio'] == pytest.approx(1.05)
    assert summary['rory']['pss_added_mb'] == pytest.approx(54.0)
    assert summary['restart']['pss_added_mb'] == pytest.approx(34.0)
    assert summary['cpu_ratio'] == summary['rory']['cpu_ratio']
    assert summary['pss_budget_mb'] == 150.0
    text = table(summary, 2)
    assert '| restart | **all** | | **36.8** | **295** | 1.05x, +34 MB |' in text
    assert 'CPU **1.10x** (goal 1.10x)' in text


def test_without_rory_there_is_no_headline_ratio() -> None:
    summary = summarise([record('bare', 30.0, 260.0), record('replay', 33.0, 300.0)])
    assert 'cpu_ratio' not in summary
    assert summary['replay']['cpu_ratio'] == pytest.approx(1.10)
    assert 'CPU **' not in table(summary, 1)
