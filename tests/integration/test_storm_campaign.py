"""Crash storms, short version: a few drawn schedules (fixed seed) and every kept regression.

Each run strikes the fault-injectable integrator under RORY with a schedule of 1-5 faults
soon after one another (rory_eval/faults/storm_campaign.py); the node must end with exactly 1..N in
order. The full campaign is part of ``make faults``; a schedule it finds wrong is kept in
``storm_schedules.json`` beside this file and replayed here from then on; the kept schedules
run side by side (side_by_side.py), each test asserting on its own schedule's run.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from side_by_side import SideBySide, side_by_side

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


KEPT = load_regressions()


@pytest.fixture(scope='module')
def kept_runs(
    module_ros_domains: Callable[[], int], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[SideBySide[Outcome]]:
    """Every kept schedule's run, side by side (independent runs: each its own domain, folder
    and processes; about a third of a core each)."""
    def schedule_run(schedule: Schedule) -> Callable[[int, Path], Outcome]:
        return lambda domain, folder: run_schedule(schedule, folder / 'run', domain)
    with side_by_side({s.label(): schedule_run(s) for s in KEPT}, module_ros_domains,
                      tmp_path_factory.mktemp('kept-storms')) as runs:
        yield runs


@pytest.mark.xdist_group('storm_campaign_kept')  # one worker: the runs are shared
@pytest.mark.parametrize('schedule', KEPT, ids=Schedule.label)
def test_kept_schedule_is_exact(schedule: Schedule, kept_runs: SideBySide[Outcome]) -> None:
    _check(kept_runs[schedule.label()])


@settings(max_examples=2, derandomize=True, database=None, deadline=None,
          phases=(Phase.generate,),
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(schedule=schedules())
def test_drawn_storm_is_exact(schedule: Schedule, tmp_path: Path, ros_domain: int) -> None:
    _check(run_schedule(schedule, tmp_path / f'run{next(_runs)}', ros_domain))
