"""Two robots on one DDS network, one supervisor each, the same config: a crash on robot 1
must not disturb robot 2.

Each robot is a simulator in its own namespace (``rory sim ... --ros-args -r __ns:=/robotN``)
and grid_slam under ``rory supervise fleet.yaml --ros-args -r __ns:=/robotN ...`` with its store
given as a parameter. Both simulators run the same world, seed and route, so two undisturbed
robots publish byte-identical poses stamp for stamp. Robot 1's node is SIGKILLed; then

* robot 2 must have published every pose, each identical to robot 1's at the same stamp before
  the crash and after robot 1's release (which also shows robot 1's recovery exact);
* robot 2's timing: gaps between its poses (wall clock, as received) during robot 1's outage
  against the rest of the run;
* the safe-state topic is relative (``safe_stop``): robot 1's is held and released, robot 2's
  is never touched; neither supervisor hears the other's channel.

    python -m rory_eval.harness.fleet --runs 3          # prints robot 2's timing, run by run
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import subprocess
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rory_eval.harness.simrun import LATCHED, SimRun, SimRunResult, store_events
from rory_eval.targets import TARGETS

GRID_SLAM = TARGETS['grid_slam']
ROBOTS = ('robot1', 'robot2')
POSE = GRID_SLAM.pose_topic.removeprefix('/')  # relative: inside each robot's namespace
SAFE_TOPIC = 'safe_stop'
# grid_slam's absolute topic names, moved into the robot's namespace by remaps.
_MOVED = (*GRID_SLAM.inputs, GRID_SLAM.result_topic, GRID_SLAM.pose_topic, '/clock')


@dataclass
class Robot:
    """One robot's run."""

    name: str
    poses: dict[int, bytes]  # stamp (ns) -> serialized PoseStamped
    received: dict[int, float]  # stamp -> monotonic receive time
    safe_stop: list[bool]
    events: list[dict[str, Any]]
    supervisor_log: str
    e_stop_received: int  # what its simulator counted on its own e_stop


@dataclass
class FleetResult:
    """Both robots, and the crash of robot 1."""

    robots: dict[str, Robot]
    killed_at: float | None  # monotonic
    errors: list[str] = field(default_factory=list)

    def recovered(self, robot: str) -> list[dict[str, Any]]:
        """The robot's 'recovered' events."""
        return [e for e in self.robots[robot].events if e['kind'] == 'recovered']

    def outage(self) -> tuple[int, int]:
        """Robot 1's missing stamps as (last before the crash, first after the release)."""
        stamps = sorted(self.robots['robot1'].poses)
        gaps = [(b - a, a, b) for a, b in itertools.pairwise(stamps)]
        _, before, after = max(gaps)
        return before, after


def fleet_config(out: Path, world: str) -> Path:
    """One config for every robot: grid_slam under RORY, a relative safe-state topic."""
    inst = out / 'inst'
    if not inst.exists():
        subprocess.run([sys.executable, '-m', 'rory_instrument', str(GRID_SLAM.folder), '--vars',
                        str(GRID_SLAM.keyvars), '-o', str(inst)], check=True,
                       capture_output=True)
    config = {
        'nodes': [{'name': GRID_SLAM.name,
                   'command': ['python', str(inst / GRID_SLAM.node_file),
                               *GRID_SLAM.argv(world)[2:]],
                   'method': 'rory', 'checkpoint_interval': 2.0, 'replay': 'fast'}],
        # Relative: /robot1/safe_stop for robot 1's supervisor. Not the simulator's e_stop,
        # which would stop robot 1 and make its later inputs differ from robot 2's.
        'safe_state': [{'topic': SAFE_TOPIC, 'type': 'std_msgs/msg/Bool',
                        'hold': {'data': True}, 'release': {'data': False}}],
        'store': 'unused-store',  # each robot's comes as a parameter
    }
    path = out / 'fleet.yaml'
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def robot_ros_args(robot: str, store: Path) -> list[str]:
    """The supervisor's ROS arguments for one robot (its nodes get them too)."""
    args = ['--ros-args', '-r', f'__ns:=/{robot}']
    for topic in _MOVED:
        args += ['-r', f'{topic}:=/{robot}{topic}']
    return [*args, '-p', f'rory_supervisor:store:={store}']


def run_fleet(world: str, out: Path, *, domain_id: int, kill_at: float = 6.0,
              duration: float = 16.0) -> FleetResult:
    """One run of both robots; robot 1's node is killed ``kill_at`` sim seconds in."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Bool

    from rory_eval.harness.killer import Killer

    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    config = fleet_config(out, world)
    runs: dict[str, SimRun] = {}
    for robot in ROBOTS:
        store = out / robot / 'store'
        run = SimRun(world, out / robot / 'run', domain_id=domain_id, duration=duration,
                     wait_for={f'/{robot}/scan': 2},
                     sim_args=['--start-delay', '1.0', '--ros-args', '-r', f'__ns:=/{robot}'])
        run.add_node('supervisor', [sys.executable, '-m', 'rory_runtime.cli', 'supervise',
                                    str(config), *robot_ros_args(robot, store)])
        run.record(f'/{robot}/{POSE}', PoseStamped, qos=1000)
        run.record(f'/{robot}/{SAFE_TOPIC}', Bool, qos=LATCHED)
        runs[robot] = run
    killer = Killer(out / 'robot1' / 'run' / 'sim.log', world, out / 'robot1' / 'store',
                    kill_at)
    results: dict[str, SimRunResult] = {}
    errors: list[str] = []

    def go(robot: str) -> None:
        try:
            results[robot] = runs[robot].run()
        except Exception as err:  # reported with the result; the other robot still ends
            errors.append(f'{robot}: {type(err).__name__}: {err}')

    threads = [threading.Thread(target=go, args=(r,), name=r) for r in ROBOTS]
    killer.start()
    try:
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    finally:
        killer.stop()
    if killer.error:
        errors.append(f'robot1: the crash was not made: {killer.error}')
    robots: dict[str, Robot] = {}
    for robot, result in results.items():
        poses: dict[int, bytes] = {}
        received: dict[int, float] = {}
        for msg, at in zip(result.messages[f'/{robot}/{POSE}'],
                           result.received_at[f'/{robot}/{POSE}'], strict=True):
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            poses[stamp] = bytes(serialize_message(msg))
            received[stamp] = at
        events = store_events(out / robot / 'store')
        robots[robot] = Robot(robot, poses, received,
                              [bool(m.data) for m in result.messages[f'/{robot}/{SAFE_TOPIC}']],
                              events, result.log('supervisor'),
                              int(result.summary.get('e_stop_received', -1)))
    killed_at = None if killer.killed_at is None else killer.killed_at
    return FleetResult(robots, killed_at, errors)


@dataclass(frozen=True)
class Timing:
    """Robot 2's pose gaps (ms, wall clock as received) inside and outside robot 1's outage."""

    during_median: float
    during_max: float
    during_count: int
    other_median: float
    other_max: float


def robot2_timing(result: FleetResult, margin_ns: int = 1_000_000_000) -> Timing:
    """Robot 2's gaps while robot 1 was down (its outage by stamps, plus a second after)."""
    before, after = result.outage()
    robot2 = result.robots['robot2']
    stamps = sorted(robot2.received)
    during: list[float] = []
    other: list[float] = []
    for a, b in itertools.pairwise(stamps):
        gap = (robot2.received[b] - robot2.received[a]) * 1000
        (during if before <= b <= after + margin_ns else other).append(gap)
    return Timing(statistics.median(during), max(during), len(during),
                  statistics.median(other), max(other))


def main(argv: Sequence[str] | None = None) -> int:
    """Run the fleet ``--runs`` times; print robot 2's outputs and timing against robot 1's."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.harness.fleet', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--world', default='office_small')
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument('--domain', type=int, default=97)
    parser.add_argument('--out', type=Path, default=Path('fleet-out'))
    args = parser.parse_args(argv)
    print('| run | robot 1 recovered (ms) | robot 2 poses | identical to robot 1 | robot 2 gap '
          'median / max during robot 1 outage (ms) | elsewhere (ms) |')
    print('|---|---:|---:|---:|---:|---:|')
    failed = False
    for k in range(args.runs):
        result = run_fleet(args.world, args.out / f'run{k + 1}', domain_id=args.domain)
        if result.errors:
            print(f'run {k + 1}: {result.errors}')
            failed = True
            continue
        one, two = result.robots['robot1'], result.robots['robot2']
        common = set(one.poses) & set(two.poses)
        same = sum(one.poses[s] == two.poses[s] for s in common)
        timing = robot2_timing(result)
        recovered = result.recovered('robot1')
        ms = f'{recovered[0]["total_ms"]:.0f}' if recovered else '-'
        print(f'| {k + 1} | {ms} | {len(two.poses)} | {same}/{len(common)} | '
              f'{timing.during_median:.0f} / {timing.during_max:.0f} '
              f'({timing.during_count} gaps) | {timing.other_median:.0f} / '
              f'{timing.other_max:.0f} |')
        failed |= same != len(common)
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
