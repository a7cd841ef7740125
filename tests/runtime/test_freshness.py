"""Freshness rules (freshness.py): the age on the node's clock and the three outcomes."""

from __future__ import annotations

import time

import pytest

from rory_runtime import codec
from rory_runtime.freshness import ClockReading, Rule, checkpoint_age, describe, judge
from rory_runtime.inspection import age_line, variable_ages
from rory_runtime.store import Checkpoint

S = 1_000_000_000


@pytest.mark.parametrize(('taken', 'now', 'age'), [
    (ClockReading(10 * S, False), ClockReading(13 * S, False), 3.0),
    (ClockReading(10 * S, True), ClockReading(12 * S, True), 2.0),
    (ClockReading(10 * S, True), ClockReading(12 * S, False), None),  # another time base
    (ClockReading(10 * S, False), ClockReading(12 * S, True), None),
    (ClockReading(10 * S, True), ClockReading(3 * S, True), None),  # a simulation restarted
    (ClockReading(10 * S, True), ClockReading(0, True), None),  # no /clock yet
    (None, ClockReading(12 * S, False), None),
])
def test_the_age_counts_on_one_clock_or_is_unknown(
    taken: ClockReading | None, now: ClockReading, age: float | None
) -> None:
    assert checkpoint_age(taken, now) == age


def test_each_outcome_and_an_unknown_age_counting_as_stale() -> None:
    rules = (Rule('pose', 5.0, 'reset'), Rule('goal', 5.0, 'keep'),
             Rule('global:mode', 5.0, 'refuse'), Rule('map', 60.0))
    keys = ('map', 'pose', 'goal', 'count', 'global:mode')
    fresh = judge(keys, rules, ClockReading(100 * S, False), ClockReading(103 * S, False))
    assert fresh.restored == list(keys) and not (fresh.reset or fresh.kept_stale or fresh.refused)
    old = judge(keys, rules, ClockReading(100 * S, False), ClockReading(110 * S, False))
    assert (old.restored, old.reset, old.kept_stale, old.refused) == (
        ['map', 'count'], ['pose'], ['goal'], ['global:mode'])
    unknown = judge(keys, rules, None, ClockReading(110 * S, False))
    assert unknown.restored == ['count'] and unknown.reset == ['map', 'pose']
    assert describe(old) == (
        'restored: map, count; stale, refused: global:mode (max_age 5 s); stale, reset: pose '
        '(max_age 5 s); stale, kept: goal (max_age 5 s) (checkpoint age 10.0 s, system clock)')


def test_a_rule_must_make_sense() -> None:
    with pytest.raises(ValueError, match='pose'):
        Rule('pose', 0.0)
    with pytest.raises(ValueError, match='pose'):
        Rule('pose', 1.0, 'drop')


def test_inspect_shows_each_variables_age_and_rule() -> None:
    now = time.time_ns()
    ckpt = Checkpoint(node='n', seq=1, incarnation=1, created_ns=now - 12 * S, manifest='m',
                      method='rory', cut=None, windows={},
                      vars_blob=codec.encode_vars({'pose': 1.0, 'count': 3}),
                      clock_ns=now - 12 * S, freshness=(('pose', 5.0, 'reset'),))
    assert age_line(ckpt, now) == 'age 12.0 s'
    assert variable_ages(ckpt, now) == {
        'pose': 'age 12.0 s, max_age 5 s, on_stale reset: stale',
        'count': 'age 12.0 s, no rule (always restored)'}
