"""The stack harness's strikes (rory_eval/harness/stack.py): what ``T:NODE[,NODE...]`` and
``T:all`` parse to, what is refused, and the striker waiting for the stack to settle. No
process is started."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from rory_eval.harness.stack import NODES, Strike, Striker, first_in_line

SIX = ('grid_slam', 'graph_slam', 'depth_mapper', 'amcl', 'lama_local', 'navigator')


def test_a_strike_names_nodes_of_the_stack() -> None:
    assert Strike.parse('8:amcl') == Strike(8.0, ('amcl',))
    assert Strike.parse('16.5:amcl,navigator') == Strike(16.5, ('amcl', 'navigator'))
    assert Strike.parse('3:lama_local,grid_slam', SIX) == Strike(3.0, ('lama_local', 'grid_slam'))


def test_all_is_every_node_of_the_stack_in_its_order() -> None:
    assert Strike.parse('12:all') == Strike(12.0, NODES)
    assert Strike.parse('12:all', SIX) == Strike(12.0, SIX)


@pytest.mark.parametrize('text', [
    '8', '8:', ':amcl', 'x:amcl', 'nan:amcl', 'inf:amcl', '-1:amcl',  # the time
    '8:grid_slam',  # not of this stack (NODES: amcl and the navigator)
    '8:amcl,amcl', '8:all,amcl', '8:,',
])
def test_a_wrong_strike_is_refused_saying_what_it_should_be(text: str) -> None:
    with pytest.raises(ValueError, match='strike') as err:
        Strike.parse(text)
    assert repr(text) in str(err.value)


def test_the_striker_waits_for_the_stack_to_settle(tmp_path: Path) -> None:
    answers = ['amcl not running', '1 of 3 standbys ready', None]
    striker = Striker(tmp_path / 'sim.log', 'real_room', tmp_path, [Strike(0.0, SIX)],
                      ready=lambda: answers.pop(0), ready_timeout=5.0)
    assert striker._settled(striker.strikes[0])
    assert answers == [] and striker.errors == []


def test_a_stack_that_never_settles_is_not_struck(tmp_path: Path) -> None:
    striker = Striker(tmp_path / 'sim.log', 'real_room', tmp_path, [Strike(12.0, SIX)],
                      ready=lambda: 'amcl has no checkpoint', ready_timeout=0.05)
    assert not striker._settled(striker.strikes[0])
    assert striker.errors == ['not settled 0.05 s after the strike at 12.0 s: amcl has no '
                              'checkpoint']


def test_the_kills_go_first_in_line_and_everything_is_as_before_after() -> None:
    interval, policy = sys.getswitchinterval(), os.sched_getscheduler(0)
    with first_in_line():
        assert sys.getswitchinterval() == 1.0
        assert os.sched_getscheduler(0) in (os.SCHED_FIFO, policy)  # where the system lets it
    assert sys.getswitchinterval() == interval and os.sched_getscheduler(0) == policy
