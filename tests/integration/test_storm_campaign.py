"""Crash storms, short version: a few drawn schedules (fixed seed) and every kept regression.

Each run strikes the fault-injectable integrator under RORY with a schedule of 1-5 faults
soon after one another (rory_eval/faults/storm_campaign.py); the node must end with exactly 1..N in
order. The full campaign is part of ``make faults``; a schedule it finds wrong is kept in
``storm_schedules.json`` beside this file and replayed here from then on.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
from hypothesis import HealthCheck, Phase, given, settings

from rory_eval.faults.storm_campaign import (
    Outcome,
    Schedule,
    describe,
    load_regressions,
    run_schedule,
    schedules,
)

pytestmark = pytest.mark.ros

_runs = itertools.count()


def _check(outcome: Outcome) -> None:
    assert outcome.correct, f'{outcome.schedule.label()}: {describe(outcome)}'
    assert not outcome.gave_up
    # Every strike delivered was covered by a recovery (one before a release continues the
    # same recovery; a raise or hang still waiting for its next message has not struck).
    assert outcome.crashes <= outcome.strikes


@pytest.mark.parametrize('schedule', load_regressions(), ids=Schedule.label)
def test_kept_schedule_is_exact(schedule: Schedule, tmp_path: Path, ros_domain: int) -> None:
    _check(run_schedule(schedule, tmp_path / 'run', ros_domain))


@settings(max_examples=2, derandomize=True, database=None, deadline=None,
          phases=(Phase.generate,),
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(schedule=schedules())
def test_drawn_storm_is_exact(schedule: Schedule, tmp_path: Path, ros_domain: int) -> None:
    _check(run_schedule(schedule, tmp_path / f'run{next(_runs)}', ros_domain))
