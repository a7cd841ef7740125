"""A whole stack (AMCL + navigator) under one supervisor in the simulator, each with its own
method (AMCL rory, the navigator replay): one node struck alone recovers while the other keeps
running; both struck at once both recover; /e_stop is held from the first S1 to the last S4;
the robot still reaches its goal without a collision."""

from __future__ import annotations

from pathlib import Path

import pytest

from rory_eval.harness.stack import Strike, run_stack

pytestmark = pytest.mark.ros

ALONE = 8.0  # sim s: AMCL alone
TOGETHER = 16.0  # sim s: AMCL and the navigator at the same moment
# The run ends once both strikes are recovered and the navigator has said REACHED for this
# long (a replan after a recovery comes within a second), not 40 sim s in.
SETTLE = 5.0


def test_a_stack_recovers_one_node_while_the_other_runs_and_two_at_once(
    tmp_path: Path, ros_domain: int
) -> None:
    result = run_stack('real_room', tmp_path, domain_id=ros_domain, strikes=[
        Strike(ALONE, ('amcl',)), Strike(TOGETHER, ('amcl', 'navigator'))],
        methods={'amcl': 'rory', 'navigator': 'replay'}, settle=SETTLE)
    assert not result.errors
    struck = [(node, t) for t, node, _ in result.strikes]
    assert [node for node, _ in struck] == ['amcl', 'amcl', 'navigator']
    together_at = struck[1][1]

    # AMCL struck alone: recovered; the navigator's process went on untouched.
    amcl_recoveries = result.recoveries('amcl')
    navigator_spawns = result.spawns('navigator')
    assert len(amcl_recoveries) == 2 and amcl_recoveries[0]['t'] < together_at
    assert len(navigator_spawns) == 2 and navigator_spawns[1]['t'] >= together_at
    assert not [e for e in result.events if e['kind'] == 'exit' and e['node'] == 'navigator'
                and e['t'] < together_at]

    # Both struck together: both recovered.
    navigator_recoveries = result.recoveries('navigator')
    assert len(navigator_recoveries) == 1
    assert amcl_recoveries[1]['method'] == 'rory'
    assert navigator_recoveries[0]['method'] == 'replay'
    first_back, last_back = sorted([amcl_recoveries[1]['t'], navigator_recoveries[0]['t']])

    # The shared stop: held once per episode, released only when the last node was back.
    assert [held for _, held in result.e_stop] == [True, False, True, False]
    (_, _), (first_release, _), (second_hold, _), (second_release, _) = result.e_stop
    assert first_release < together_at <= second_hold
    # Released in the last node's S4, not the first one's (events.jsonl is written in order).
    order = [(e['kind'], e['node'], e.get('what')) for e in result.events
             if e['kind'] in ('recovered', 'safe_state') and e['t'] >= together_at]
    first_node = 'amcl' if amcl_recoveries[1]['t'] == first_back else 'navigator'
    last_node = 'navigator' if first_node == 'amcl' else 'amcl'
    assert order == [('safe_state', order[0][1], 'held'), ('recovered', first_node, None),
                     ('safe_state', last_node, 'released'), ('recovered', last_node, None)]
    assert abs(second_release - last_back) < 0.5

    assert result.reached, (result.statuses, result.goal_distance)
    assert result.collisions == 0
