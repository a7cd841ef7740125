"""The overhead bench's summary: medians per configuration, ratios to the bare node."""

from __future__ import annotations

import math

import pytest

from rory_eval.bench.overhead_bench import main, summarise, table
from rory_eval.runs.plan import BARE, RunSpec
from rory_eval.runs.runner import RunRecord


def _record(config: str, repetition: int, roles: dict[str, tuple[float, float]],
            *, error: str = '') -> RunRecord:
    """roles: steady CPU % and PSS MB per role."""
    spec = RunSpec('amcl', 'real_room', config, repetition, None, 30.0)
    return RunRecord(
        run=spec.to_json(), error=error,
        cpu_percent=sum(c for c, _ in roles.values()) + 1.0,
        steady_cpu_percent=sum(c for c, _ in roles.values()),
        peak_rss_mb=sum(2 * p for _, p in roles.values()),
        pss_mb=sum(p for _, p in roles.values()),
        usage_by_role={role: {'steady_cpu_percent': c, 'pss_mb': p} for role, (c, p) in
                       roles.items()} if not error else {})


def test_medians_ratios_and_added_memory_per_configuration() -> None:
    records = {
        ('amcl', BARE): [_record(BARE, r, {'node': (c, 40.0)}) for r, c in
                         enumerate((10.0, 11.0, 30.0))],
        ('amcl', 'rory'): [
            _record('rory', 0, {'node': (12.0, 55.0), 'supervisor': (2.0, 50.0),
                                'standby': (1.0, 40.0)}),
            _record('rory', 1, {'node': (13.0, 55.0), 'supervisor': (2.0, 50.0),
                                'standby': (1.0, 40.0)}),
            _record('rory', 2, {}, error='SimRunError: the clock never started'),
        ],
    }
    rows = summarise(records)
    assert [(r['config'], r['runs'], r['failed']) for r in rows] == [
        (BARE, 3, 0), ('rory', 2, 1)]
    bare, rory = rows
    assert bare['all'] == 11.0 and bare['ratio'] == 1.0  # the median, not the mean
    assert rory['node'] == 12.5 and rory['supervisor'] == 2.0 and rory['all'] == 15.5
    assert math.isclose(rory['ratio'], 15.5 / 11.0)
    assert rory['added_pss_mb'] == 145.0 - 40.0
    text = table(rows)
    assert '| amcl | bare | 3 | 11.0% | - | - | - | 11.0% | 1.00x |' in text
    assert '| amcl | rory | 2 (1 failed) | 12.5% | 2.0% | 0.0% | 1.0% | 15.5% | 1.41x |' in text
    assert '+105 MB |' in text


def test_a_configuration_list_without_the_bare_node_is_refused(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit):
        main(['--configs', 'rory'])
    assert '--configs must include bare' in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(['--configs', 'bare', 'fast'])
    assert "invalid choice: 'fast'" in capsys.readouterr().err
