"""The evaluation's plan: which runs, in which order, with which crash times."""

from __future__ import annotations

import pytest

from rory_eval.runs.plan import (
    BARE,
    MAPPING_SECONDS,
    METHODS,
    RunSpec,
    build_plan,
)
from rory_eval.targets import NAVIGATION_SECONDS, TARGETS


def test_every_cell_has_a_reference_and_a_crash_run_per_method() -> None:
    plan = build_plan(['grid_slam', 'amcl'], ['office_small', 'workshop'], METHODS,
                      repetitions=2, overhead_worlds=())
    assert len(plan.runs) == 2 * 2 * 2 * (1 + len(METHODS))
    for rep in range(2):
        for target in ('grid_slam', 'amcl'):
            for world in ('office_small', 'workshop'):
                cell = [r for r in plan.runs
                        if (r.target, r.world, r.repetition) == (target, world, rep)]
                assert [r.method for r in cell] == [BARE, *METHODS]
                assert cell[0].crash_at is None
                assert {r.crash_at for r in cell[1:]} == {9.0}  # the paper's crash time
                assert len({r.seed for r in cell}) == 1  # same noise for all of a cell


def test_repetitions_come_last_so_a_partial_run_covers_every_cell() -> None:
    plan = build_plan(['grid_slam'], ['office_small', 'real_room'], ['rory'], repetitions=3,
                      overhead_worlds=())
    assert [r.repetition for r in plan.runs] == [0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]
    assert [r.seed for r in plan.runs[::4]] == [0, 1, 2]  # another noise realisation each


def test_the_overhead_run_is_rory_without_a_crash_in_the_overhead_worlds_only() -> None:
    plan = build_plan(['grid_slam'], ['office_small', 'real_room'], ['restart'],
                      repetitions=1)
    no_crash = [(r.world, r.method) for r in plan.runs if r.crash_at is None]
    assert no_crash == [('office_small', BARE), ('real_room', BARE), ('real_room', 'rory')]


def test_random_crash_times_are_drawn_per_repetition_and_seeded() -> None:
    def times(seed: int) -> list[float | None]:
        plan = build_plan(['grid_slam'], ['office_small'], ['restart', 'rory'],
                          repetitions=5, random_crash=True, seed=seed, overhead_worlds=())
        return [r.crash_at for r in plan.crash_runs()]

    first = times(0)
    assert first == times(0)
    assert first != times(1)
    assert first[0::2] == first[1::2]  # both methods of a repetition crash at the same time
    assert all(t is not None and 2.0 <= t <= MAPPING_SECONDS - 8.0 for t in first)
    assert len(set(first)) == 5


def test_run_lengths_follow_the_target_kind() -> None:
    plan = build_plan(list(TARGETS), ['workshop'], ['rory'], repetitions=1, overhead_worlds=())
    lengths = {r.target: r.duration for r in plan.runs}
    assert lengths['grid_slam'] == lengths['depth_mapper'] == MAPPING_SECONDS
    assert lengths['navigator'] == lengths['amcl'] == NAVIGATION_SECONDS['workshop']


@pytest.mark.parametrize(('kwargs', 'message'), [
    ({'targets': ['slam9000']}, 'unknown target(s) slam9000'),
    ({'methods': ['reboot']}, 'unknown method(s) reboot'),
    ({'crash_at': 28.0}, 'leaves no time to recover'),
    ({'other_pace': ['restart']}, 'restart cannot run at another pace'),
    ({'replay': 'slow'}, "unknown replay pace 'slow'"),
])
def test_bad_plans_are_refused_with_the_reason(kwargs: dict[str, object],
                                               message: str) -> None:
    args: dict[str, object] = {'targets': ['grid_slam'], 'worlds': ['office_small'],
                               'methods': ['rory'], 'repetitions': 1}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message.replace('(', r'\(').replace(')', r'\)')):
        build_plan(**args)  # type: ignore[arg-type]


def test_a_spec_goes_through_json_and_names_its_folder() -> None:
    spec = RunSpec('amcl', 'real_room', 'checkpoint', 3, 9.0, 30.0, seed=3)
    assert RunSpec.from_json(spec.to_json()) == spec
    assert spec.name == 'amcl-real_room-checkpoint-crash9.0-r3'
    assert RunSpec('amcl', 'real_room', BARE, 0, None, 30.0).name.endswith('-nocrash-r0')


def test_a_method_at_the_other_pace_crashes_beside_its_own() -> None:
    # Table IV with the evaluation's pace and the other one beside it: one more crash run per
    # cell and repetition, the same crash, its own folder and column.
    plan = build_plan(['grid_slam'], ['office_small'], list(METHODS), repetitions=2,
                      overhead_worlds=(), other_pace=['rory'])
    assert len(plan.runs) == 2 * (1 + len(METHODS) + 1)
    beside = [r for r in plan.runs if r.beside]
    assert [(r.method, r.replay, r.column, r.repetition) for r in beside] == [
        ('rory', 'paced', 'rory paced', 0), ('rory', 'paced', 'rory paced', 1)]
    own = [r for r in plan.runs if r.method == 'rory' and not r.beside]
    assert [r.replay for r in own] == ['fast', 'fast'] and [r.column for r in own] == ['rory'] * 2
    assert [r.crash_at for r in beside] == [r.crash_at for r in own]
    assert len({r.name for r in plan.runs}) == len(plan.runs)
    assert beside[0].name == 'grid_slam-office_small-rory-paced-crash9.0-r0'
    assert RunSpec.from_json(beside[0].to_json()) == beside[0]
    # The other way round: a paced evaluation has fast runs beside.
    paced = build_plan(['grid_slam'], ['office_small'], ['rory'], repetitions=1,
                       overhead_worlds=(), replay='paced', other_pace=['rory', 'replay'])
    assert [(r.column, r.replay) for r in paced.runs if r.crash_at is not None] == [
        ('rory', 'paced'), ('rory fast', 'fast'), ('replay fast', 'fast')]


def test_a_record_from_before_the_other_pace_loads_as_its_own_pace() -> None:
    old = RunSpec('amcl', 'real_room', 'rory', 0, 9.0, 30.0).to_json()
    del old['beside']
    spec = RunSpec.from_json(old)
    assert not spec.beside and spec.column == 'rory'
    assert spec.name == 'amcl-real_room-rory-crash9.0-r0'
