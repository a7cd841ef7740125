"""Quality of targets/navigator: does it reach every goal of every world, without collision?

Each run is the simulator (``--driver none``), the navigator node with ``/map`` remapped to the
simulator's ``/ground_truth/map``, a goal published latched on ``/goal_pose``, and a
localization source on ``/amcl_pose``: by default a relay of ``/ground_truth/pose`` with
Gaussian noise, at 10 Hz on the scan's stamps and 40 ms late, as AMCL delivers it (``--localization
amcl`` uses targets/amcl instead). The navigator sees drifting wheel odometry between poses.

    python -m rory_eval.quality.navigator [--worlds W ...] [--goals G ...] [--out DIR]

prints, per goal: reached or not, time to goal (sim s, until it settles at the goal), final
position and heading error (ground truth), collisions (the simulator's summary), the driven
length against the first A* plan's length, the number of plans and recoveries, and the
navigator's CPU% and peak RSS; and draws each run's plan and driven path over its world.
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rory_eval.harness.goals import goal_message
from rory_eval.harness.simrun import SimRun
from rory_eval.targets import TARGETS

TARGET = TARGETS['navigator']

SETTLE_XY = 0.15  # m: the robot counts as at the goal within this (the node's tolerance 0.08)
SETTLE_YAW = 0.2  # rad

# Sim seconds each run gets: the goal's path at ~0.4 m/s plus start-up and margin.
DURATIONS = {
    ('office_small', 'storage'): 55.0,
    ('office_small', 'meeting_room'): 60.0,
    ('office_small', 'open_office'): 40.0,
    ('workshop', 'behind_pillars'): 50.0,
    ('workshop', 'office'): 65.0,
    ('workshop', 'rack_aisle'): 65.0,
    ('real_room', 'far_corner'): 30.0,
}


@dataclass
class GoalRun:
    """What one navigation run gave."""

    world: str
    goal: str
    reached: bool  # the node said REACHED and the robot is at the goal (ground truth)
    statuses: list[str]
    time_to_goal: float | None  # sim s until it settled at the goal
    position_error: float  # m, final, ground truth
    yaw_error: float  # rad, final
    collisions: int
    driven_length: float  # m, ground truth, until settled (or the end)
    astar_length: float  # m, the first plan
    plans: int
    cpu_percent: float
    peak_rss_mb: float
    out: Path
    driven: list[tuple[float, float]]  # ground truth (x, y), 10 Hz

    def row(self) -> str:
        """One line of the table."""
        t = f'{self.time_to_goal:6.1f}' if self.time_to_goal is not None else '     -'
        ratio = self.driven_length / self.astar_length if self.astar_length else math.nan
        return (f'{self.world:12s} {self.goal:15s} {"yes" if self.reached else "NO":>7s} {t} '
                f'{self.position_error:7.3f} {math.degrees(self.yaw_error):6.1f} '
                f'{self.collisions:4d} {self.driven_length:7.2f} {self.astar_length:7.2f} '
                f'{ratio:5.2f} {self.plans:5d} {self.cpu_percent:6.1f} {self.peak_rss_mb:6.0f}')


HEADER = (f'{"world":12s} {"goal":15s} {"reached":>7s} {"t (s)":>6s} {"err m":>7s} '
          f'{"err deg":>6s} {"coll":>4s} {"driven":>7s} {"A*":>7s} {"ratio":>5s} '
          f'{"plans":>5s} {"CPU%":>6s} {"RSS MB":>6s}')


def relay_argv(seed: int = 1, noise: float = 0.02) -> list[str]:
    """The command running ``relay_main`` as its own process."""
    code = 'import sys; from rory_eval.quality.navigator import relay_main; sys.exit(relay_main())'
    return [sys.executable, '-c', code, '--seed', str(seed), '--noise', str(noise),
            '--ros-args', '-p', 'use_sim_time:=true']


def relay_main(argv: Sequence[str] | None = None) -> int:
    """A stand-in localization node: ``/ground_truth/pose`` to ``/amcl_pose``, honestly.

    Every 100 ms of stamps (the scan's 10 Hz), the pose at that stamp with Gaussian noise
    (``--noise`` m, half as many rad), published when the pose 40 ms later arrives (AMCL is
    late by its processing time). The noise comes from its own seeded generator.
    """
    import numpy as np
    import rclpy
    import rclpy.utilities
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from rclpy.executors import ExternalShutdownException
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    parser = argparse.ArgumentParser(prog='relay')
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--noise', type=float, default=0.02)
    args, ros_args = parser.parse_known_args(sys.argv[1:] if argv is None else argv)
    rclpy.init(args=['relay', *ros_args])
    node = Node('ground_truth_localizer')
    rng = np.random.default_rng(args.seed)
    pub = node.create_publisher(PoseWithCovarianceStamped, '/amcl_pose',
                                QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
    pending: list[PoseWithCovarianceStamped] = []
    period_ns, delay_ns = 100_000_000, 40_000_000

    def on_truth(msg: Any) -> None:
        ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        while pending:
            head = pending[0].header.stamp
            if head.sec * 1_000_000_000 + head.nanosec + delay_ns > ns:
                break
            pub.publish(pending.pop(0))
        if ns % period_ns:
            return
        out = PoseWithCovarianceStamped()
        out.header = msg.header
        out.header.frame_id = 'map'
        q = msg.pose.orientation
        yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        yaw += float(rng.normal(0.0, args.noise / 2))
        out.pose.pose.position.x = msg.pose.position.x + float(rng.normal(0.0, args.noise))
        out.pose.pose.position.y = msg.pose.position.y + float(rng.normal(0.0, args.noise))
        out.pose.pose.orientation.z = math.sin(yaw / 2)
        out.pose.pose.orientation.w = math.cos(yaw / 2)
        var = args.noise ** 2
        out.pose.covariance[0] = out.pose.covariance[7] = var
        out.pose.covariance[35] = var / 4
        pending.append(out)

    node.create_subscription(PoseStamped, '/ground_truth/pose', on_truth,
                             QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.utilities.try_shutdown()
    return 0


def run_goal(world: str, goal: str, out: Path, *, domain_id: int,
             duration: float | None = None, seed: int = 0, localization: str = 'relay',
             figure: bool = True) -> GoalRun:
    """One navigation run to a named goal; its measurements (and a PNG in ``out``)."""
    from nav_msgs.msg import Path as PathMsg
    from std_msgs.msg import String

    from rory_eval.harness.simrun import LATCHED

    run = SimRun(world, out, domain_id=domain_id, driver='none', seed=seed, depth=False,
                 duration=duration or DURATIONS.get((world, goal), 60.0),
                 wait_for={'/scan': 1, '/odom': 1, '/ground_truth/pose': 1})
    run.add_node('navigator', [sys.executable, str(TARGET.node), '--ros-args',
                               '-p', 'use_sim_time:=true', '-r', '/map:=/ground_truth/map'])
    if localization == 'amcl':
        run.add_node('amcl', TARGETS['amcl'].argv(world))
        run.wait_for['/ground_truth/pose'] = 0
    else:
        run.add_node('localizer', relay_argv(seed + 1))
    run.record('/navigator/plan', PathMsg, qos=LATCHED)
    run.record('/navigator/status', String, qos=LATCHED)
    run.publish_latched('/goal_pose', goal_message(world, goal))
    result = run.run()
    return _measure(world, goal, result, figure)


def _measure(world: str, goal_name: str, result: Any, figure: bool) -> GoalRun:
    from sim.worlds import get_world

    goal = get_world(world).goals[goal_name]
    truth = result.ground_truth
    statuses: list[str] = []
    for msg in result.messages.get('/navigator/status', []):
        if not statuses or statuses[-1] != msg.data:
            statuses.append(msg.data)
    plans = result.messages.get('/navigator/plan', [])
    first_plan = [(p.pose.position.x, p.pose.position.y) for p in plans[0].poses] if plans else []
    astar_length = _length(first_plan)
    at_goal = [math.hypot(x - goal.x, y - goal.y) <= SETTLE_XY
               and abs(_wrap(yaw - goal.yaw)) <= SETTLE_YAW for _, x, y, yaw in truth]
    settled: int | None = None
    for k in range(len(at_goal) - 1, -1, -1):
        if not at_goal[k]:
            break
        settled = k
    _, fx, fy, fyaw = truth[-1] if truth else (0.0, math.nan, math.nan, math.nan)
    end = settled + 1 if settled is not None else len(truth)
    driven = _length([(x, y) for _, x, y, _ in truth[:end]])
    usage = result.usage.get('navigator')
    run = GoalRun(
        world=world, goal=goal_name,
        reached=bool(statuses) and statuses[-1] == 'REACHED' and settled is not None,
        statuses=statuses,
        time_to_goal=truth[settled][0] if settled is not None else None,
        position_error=math.hypot(fx - goal.x, fy - goal.y),
        yaw_error=abs(_wrap(fyaw - goal.yaw)),
        collisions=int(result.summary.get('collisions', -1)),
        driven_length=driven, astar_length=astar_length, plans=len(plans),
        cpu_percent=usage.cpu_percent if usage else math.nan,
        peak_rss_mb=usage.peak_rss_mb if usage else math.nan,
        out=result.out,
        driven=[(x, y) for _, x, y, _ in truth],
    )
    if figure:
        from sim.render import render_world

        render_world(get_world(world), result.out / f'navigator_{world}_{goal_name}.png',
                     paths={'first A* plan': first_plan,
                            'driven (ground truth)': [(x, y) for _, x, y, _ in truth]},
                     show_route=False,
                     title=f'navigator, {world} -> {goal_name}: '
                           f'{"reached" if run.reached else "NOT reached"}, '
                           f'{run.collisions} collisions')
    return run


def _world_figure(world: str, runs: Sequence[GoalRun], out: Path) -> None:
    """Every goal's driven path in one figure of the world."""
    from sim.render import render_world
    from sim.worlds import get_world

    if not runs:
        return
    reached = sum(r.reached for r in runs)
    collisions = sum(r.collisions for r in runs)
    render_world(get_world(world), out / f'navigator_{world}.png',
                 paths={f'to {r.goal}': r.driven for r in runs}, show_route=False,
                 title=f'navigator in {world}: {reached}/{len(runs)} goals reached, '
                       f'{collisions} collisions (driven paths, ground truth)')


def _length(points: Sequence[tuple[float, float]]) -> float:
    return sum(math.dist(a, b) for a, b in itertools.pairwise(points))


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def main(argv: Sequence[str] | None = None) -> int:
    """Run every goal of the chosen worlds; print the table; 0 if all were reached cleanly."""
    from sim.worlds import get_world

    parser = argparse.ArgumentParser(prog='python -m rory_eval.quality.navigator',
                                     description=__doc__.splitlines()[0])
    parser.add_argument('--worlds', nargs='+', default=['office_small', 'workshop', 'real_room'])
    parser.add_argument('--goals', nargs='+', help='only these goal names')
    parser.add_argument('--out', type=Path, default=Path('quality-out/navigator'))
    parser.add_argument('--domain', type=int, default=160, help='ROS_DOMAIN_ID of the runs')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--localization', choices=['relay', 'amcl'], default='relay')
    args = parser.parse_args(argv)
    runs: list[GoalRun] = []
    print(HEADER, flush=True)
    for world in args.worlds:
        for goal in get_world(world).goals:
            if args.goals and goal not in args.goals:
                continue
            run = run_goal(world, goal, args.out / f'{world}_{goal}', domain_id=args.domain,
                           seed=args.seed, localization=args.localization)
            runs.append(run)
            print(run.row(), flush=True)
        _world_figure(world, [r for r in runs if r.world == world], args.out)
    ok = all(r.reached and r.collisions == 0 for r in runs)
    print(f'{sum(r.reached for r in runs)}/{len(runs)} goals reached, '
          f'{sum(r.collisions for r in runs)} collisions; figures in {args.out}/*/')
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
