"""Two simulated robots on one DDS network, one supervisor each from the same config (namespace
and store given as ROS arguments): robot 1's node is SIGKILLed; robot 2 is not disturbed."""

from __future__ import annotations

from pathlib import Path

import pytest

from rory_eval.harness.fleet import robot2_timing, run_fleet

pytestmark = pytest.mark.ros

PERIOD_NS = 100_000_000  # grid_slam publishes a pose per scan, 10 Hz


def test_a_crash_on_robot_1_leaves_robot_2_outputs_and_timing_unchanged(
    tmp_path: Path, ros_domain: int
) -> None:
    result = run_fleet('office_small', tmp_path, domain_id=ros_domain, kill_at=6.0,
                       duration=16.0)
    assert not result.errors
    one, two = result.robots['robot1'], result.robots['robot2']

    # Robot 1 crashed once and was recovered; robot 2's node was never touched.
    assert [e['code'] for e in one.events if e['kind'] == 'exit'] == [-9]
    assert len(result.recovered('robot1')) == 1
    assert not [e for e in two.events if e['kind'] in ('exit', 'recovered')]
    assert len([e for e in two.events if e['kind'] == 'spawn']) == 1

    # Robot 2 published through robot 1's outage, every pose the same as undisturbed robot 1's
    # at that stamp (before the crash, and after the release: robot 1's recovery is exact).
    before, after = result.outage()
    # (From the warm standby robot 1 may miss as little as one pose.)
    assert after - before >= 2 * PERIOD_NS, 'robot 1 missed a pose while it was down'
    # Each robot's run ends with its own simulator, so the last pose of one may be stamped
    # after the other's recorder stopped: compare up to the last stamp both recorded.
    last_common = min(max(one.poses), max(two.poses))
    assert last_common >= 15 * 1_000_000_000, 'a robot stopped publishing early'
    compared = {s for s in one.poses if s <= last_common}
    assert compared <= set(two.poses)
    during = [s for s in two.poses if before < s < after]
    assert len(during) >= (after - before) // PERIOD_NS - 1
    assert last_common > after, 'robot 1 published after its release'
    assert all(one.poses[s] == two.poses[s] for s in compared)

    # Its timing while robot 1 recovered is that of the rest of its run.
    timing = robot2_timing(result)
    assert timing.during_count >= 10
    assert timing.during_max <= max(2 * timing.other_max, 400.0), timing

    # The relative safe-state topic: robot 1's held and released, robot 2's never; neither
    # simulator's e_stop was touched, and neither supervisor heard the other's channel.
    assert one.safe_stop == [True, False] and two.safe_stop == []
    assert one.e_stop_received == 0 and two.e_stop_received == 0
    for robot in (one, two):
        assert 'ignoring' not in robot.supervisor_log
        assert 'signature' not in robot.supervisor_log
