"""Quality of targets/amcl: pose error over each world's route, and navigation on its pose.

For each world two runs in the simulator, all real processes (``SimRun``):

1. **Route**: ``--driver internal`` drives the world's whole route (deterministic for a seed);
   amcl localizes on ``/ground_truth/map``, starting from the world's start pose. Every
   ``/amcl_pose`` (one per scan) is compared with ground truth at its stamp: median, p95 and
   max position error, median and p95 yaw error; for scale, the error of the raw wheel
   odometry over the same route. The node's CPU% (CPU seconds per wall second of the run) and
   peak RSS.
2. **Navigation**: ``--driver none``; targets/navigator drives to the world's default goal on
   amcl's pose (``/amcl_pose``, as move_base drives on AMCL): reached or not, time, collisions,
   and amcl's error meanwhile.

    python -m rory_eval.quality.amcl [--worlds W ...] [--out DIR] [--no-navigation]

prints both tables and writes per world ``amcl_<world>.png`` (estimate, ground truth and
odometry over the world), ``amcl_navigation_<world>.png`` and ``amcl_errors.png`` (position
error over time, every world). ``rory_eval.quality.lama_local`` reuses this machinery.
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rory_eval.harness.simrun import LATCHED, SimRun, SimRunResult
from rory_eval.metrics import position_errors
from rory_eval.targets import TARGETS, Target

WORLDS = ('office_small', 'workshop', 'real_room')
# Sim seconds of the route runs: the route (104, 124, 80 s at 0.3 m/s) and a margin.
ROUTE_SECONDS = {'office_small': 107.0, 'workshop': 127.0, 'real_room': 83.0}

Sample = tuple[float, float, float, float]  # (t, x, y, yaw)


@dataclass
class RouteQuality:
    """One world's route run."""

    world: str
    poses: int
    median: float
    p95: float
    max: float
    yaw_median_deg: float
    yaw_p95_deg: float
    odometry_median: float
    odometry_max: float
    cpu_percent: float
    peak_rss_mb: float
    estimates: list[Sample] = field(repr=False)
    truth: list[Sample] = field(repr=False)
    odometry: list[tuple[float, float]] = field(repr=False)

    def row(self) -> str:
        """One line of the route table."""
        return (f'{self.world:12s} {self.poses:6d} {self.median:7.3f} {self.p95:7.3f} '
                f'{self.max:7.3f} {self.yaw_median_deg:7.2f} {self.yaw_p95_deg:7.2f} '
                f'{self.odometry_median:8.3f} {self.odometry_max:8.3f} '
                f'{self.cpu_percent:6.1f} {self.peak_rss_mb:7.0f}')


ROUTE_HEADER = (f'{"world":12s} {"poses":>6s} {"median":>7s} {"p95":>7s} {"max":>7s} '
                f'{"yaw med":>7s} {"yaw p95":>7s} {"odom med":>8s} {"odom max":>8s} '
                f'{"CPU%":>6s} {"RSS MB":>7s}')
ROUTE_UNITS = (f'{"":12s} {"":6s} {"m":>7s} {"m":>7s} {"m":>7s} {"deg":>7s} {"deg":>7s} '
               f'{"m":>8s} {"m":>8s} {"":6s} {"":7s}')


@dataclass
class NavigationQuality:
    """One world's navigation run to its default goal on the localizer's pose."""

    world: str
    goal: str
    reached: bool
    time_to_goal: float | None
    final_error: float
    collisions: int
    localization_median: float
    localization_max: float
    cpu_percent: float
    peak_rss_mb: float
    driven: list[tuple[float, float]] = field(repr=False)
    estimates: list[Sample] = field(repr=False)

    def row(self) -> str:
        """One line of the navigation table."""
        t = f'{self.time_to_goal:6.1f}' if self.time_to_goal is not None else '     -'
        return (f'{self.world:12s} {self.goal:15s} {"yes" if self.reached else "NO":>7s} {t} '
                f'{self.final_error:7.3f} {self.collisions:5d} {self.localization_median:7.3f} '
                f'{self.localization_max:7.3f} {self.cpu_percent:6.1f} {self.peak_rss_mb:7.0f}')


NAV_HEADER = (f'{"world":12s} {"goal":15s} {"reached":>7s} {"t (s)":>6s} {"err m":>7s} '
              f'{"coll":>5s} {"loc med":>7s} {"loc max":>7s} {"CPU%":>6s} {"RSS MB":>7s}')


# -- measuring -----------------------------------------------------------------------------------

def pose_samples(messages: Sequence[Any]) -> list[Sample]:
    """(t, x, y, yaw) of PoseWithCovarianceStamped messages, t from their stamps."""
    out = []
    for m in messages:
        q = m.pose.pose.orientation
        yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        out.append((m.header.stamp.sec + m.header.stamp.nanosec * 1e-9,
                    m.pose.pose.position.x, m.pose.pose.position.y, yaw))
    return out


def yaw_errors(estimates: Sequence[Sample], truth: Sequence[Sample]) -> np.ndarray:
    """|yaw error| (rad) of each estimate inside the truth's time span."""
    if not estimates or len(truth) < 2:
        return np.zeros(0)
    t = np.array([r[0] for r in truth])
    yaw = np.unwrap(np.array([r[3] for r in truth]))
    est = np.array(estimates, dtype=np.float64)
    est = est[(est[:, 0] >= t[0]) & (est[:, 0] <= t[-1])]
    d = est[:, 3] - np.interp(est[:, 0], t, yaw)
    return np.asarray(np.abs((d + np.pi) % (2 * np.pi) - np.pi), dtype=np.float64)


def _odometry_in_map(result: SimRunResult) -> tuple[list[tuple[float, float]], np.ndarray]:
    from sim.render import read_path

    path = read_path(result.out / 'path.csv')
    odom, truth = path['odometry'], path['ground_truth']
    errors = np.array([math.dist(a, b) for a, b in zip(odom, truth, strict=True)])
    return odom, errors


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if values.size else math.nan


def run_route(spec: Target, world: str, out: Path, *, domain_id: int, seed: int = 0,
              duration: float | None = None) -> RouteQuality:
    """The world's route with the localizer running; its errors and usage."""
    from geometry_msgs.msg import PoseWithCovarianceStamped

    run = SimRun(world, out, domain_id=domain_id, seed=seed, depth=False,
                 duration=duration or ROUTE_SECONDS[world],
                 wait_for={'/scan': 1, '/odom': 1, '/ground_truth/map': 1})
    run.add_node(spec.name, spec.argv(world))
    run.record(spec.pose_topic, PoseWithCovarianceStamped, qos=200)
    result = run.run()
    estimates = pose_samples(result.messages[spec.pose_topic])
    errors = position_errors([e[:3] for e in estimates], result.ground_truth)
    yaw = np.degrees(yaw_errors(estimates, result.ground_truth))
    odometry, odom_errors = _odometry_in_map(result)
    usage = result.usage.get(spec.name)
    return RouteQuality(
        world=world, poses=len(estimates), median=_pct(errors, 50), p95=_pct(errors, 95),
        max=float(errors.max()) if errors.size else math.nan,
        yaw_median_deg=_pct(yaw, 50), yaw_p95_deg=_pct(yaw, 95),
        odometry_median=_pct(odom_errors, 50),
        odometry_max=float(odom_errors.max()) if odom_errors.size else math.nan,
        cpu_percent=usage.cpu_percent if usage else math.nan,
        peak_rss_mb=usage.peak_rss_mb if usage else math.nan,
        estimates=estimates, truth=list(result.ground_truth), odometry=odometry)


def run_navigation(spec: Target, world: str, out: Path, *, domain_id: int,
                   seed: int = 0, goal: str | None = None) -> NavigationQuality:
    """targets/navigator to the world's goal, driving on the localizer's pose."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from std_msgs.msg import String

    from rory_eval.harness.goals import goal_message
    from rory_eval.quality.navigator import DURATIONS, SETTLE_XY, SETTLE_YAW
    from sim.worlds import get_world

    w = get_world(world)
    goal = goal or w.default_goal
    run = SimRun(world, out, domain_id=domain_id, driver='none', seed=seed, depth=False,
                 duration=DURATIONS.get((world, goal), 60.0),
                 wait_for={'/scan': 2, '/odom': 2, '/ground_truth/map': 2})
    # The navigator listens on /amcl_pose; another localizer's topic is remapped onto it.
    extra = [] if spec.pose_topic == '/amcl_pose' else ['-r', f'{spec.pose_topic}:=/amcl_pose']
    run.add_node(spec.name, spec.argv(world, *extra))
    run.add_node('navigator', [sys.executable, str(TARGETS['navigator'].node), '--ros-args',
                               '-p', 'use_sim_time:=true', '-r', '/map:=/ground_truth/map'])
    run.record('/amcl_pose', PoseWithCovarianceStamped, qos=200)
    run.record('/navigator/status', String, qos=LATCHED)
    run.publish_latched('/goal_pose', goal_message(world, goal))
    result = run.run()
    target = w.goals[goal]
    truth = result.ground_truth
    at_goal = [math.hypot(x - target.x, y - target.y) <= SETTLE_XY
               and abs(_wrap(yaw - target.yaw)) <= SETTLE_YAW for _, x, y, yaw in truth]
    settled: int | None = None
    for k in range(len(at_goal) - 1, -1, -1):
        if not at_goal[k]:
            break
        settled = k
    statuses = [m.data for m in result.messages.get('/navigator/status', [])]
    estimates = pose_samples(result.messages['/amcl_pose'])
    errors = position_errors([e[:3] for e in estimates], truth)
    _, fx, fy, _ = truth[-1] if truth else (0.0, math.nan, math.nan, 0.0)
    usage = result.usage.get(spec.name)
    return NavigationQuality(
        world=world, goal=goal,
        reached=bool(statuses) and statuses[-1] == 'REACHED' and settled is not None,
        time_to_goal=truth[settled][0] if settled is not None else None,
        final_error=math.hypot(fx - target.x, fy - target.y),
        collisions=int(result.summary.get('collisions', -1)),
        localization_median=_pct(errors, 50),
        localization_max=float(errors.max()) if errors.size else math.nan,
        cpu_percent=usage.cpu_percent if usage else math.nan,
        peak_rss_mb=usage.peak_rss_mb if usage else math.nan,
        driven=[(x, y) for _, x, y, _ in truth], estimates=estimates)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


# -- figures -------------------------------------------------------------------------------------

def route_figure(spec: Target, q: RouteQuality, out: Path) -> Path:
    """The estimate, ground truth and odometry over the world."""
    from sim.render import render_world
    from sim.worlds import get_world

    return render_world(
        get_world(q.world), out / f'{spec.name}_{q.world}.png',
        paths={'ground truth': [(x, y) for _, x, y, _ in q.truth],
               f'{spec.name} estimate': [(x, y) for _, x, y, _ in q.estimates],
               'wheel odometry': q.odometry},
        show_route=False, show_goals=False,
        title=f'{spec.name} in {q.world}: median {100 * q.median:.1f} cm, p95 '
              f'{100 * q.p95:.1f} cm, max {100 * q.max:.1f} cm '
              f'(odometry max {q.odometry_max:.2f} m)')


def navigation_figure(spec: Target, q: NavigationQuality, out: Path) -> Path:
    """The driven path and the localizer's estimate on the way to the goal."""
    from sim.render import render_world
    from sim.worlds import get_world

    return render_world(
        get_world(q.world), out / f'{spec.name}_navigation_{q.world}.png',
        paths={'driven (ground truth)': q.driven,
               f'{spec.name} estimate': [(x, y) for _, x, y, _ in q.estimates]},
        show_route=False,
        title=f'navigator on {spec.name}, {q.world} -> {q.goal}: '
              f'{"reached" if q.reached else "NOT reached"}, {q.collisions} collisions')


def error_figure(spec: Target, routes: Sequence[RouteQuality], out: Path) -> Path:
    """Position error over time, one panel per world."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    path = out / f'{spec.name}_errors.png'
    fig, axes = plt.subplots(len(routes), 1, figsize=(8, 2.2 * len(routes) + 0.5),
                             squeeze=False)
    try:
        for ax, q in zip(axes[:, 0], routes, strict=True):
            t = [e[0] for e in q.estimates]
            errors = position_errors([e[:3] for e in q.estimates], q.truth)
            ax.plot(t[:errors.size], 100 * errors, lw=0.8, color='#1060d0')
            ax.axhline(15, color='#d02020', lw=0.8, ls='--', label='15 cm')
            ax.set_ylabel('error (cm)')
            ax.set_title(f'{q.world}: median {100 * q.median:.1f} cm', fontsize=9)
            ax.grid(True, lw=0.3)
            ax.legend(loc='upper right', fontsize=7)
        axes[-1, 0].set_xlabel('sim time (s)')
        fig.suptitle(f'{spec.name}: position error against ground truth, per scan', fontsize=10)
        fig.tight_layout()
        out.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
    finally:
        plt.close(fig)
    return path


# -- the command ---------------------------------------------------------------------------------

def evaluate(spec: Target, argv: Sequence[str] | None = None) -> int:
    """Parse the command line, run, print the tables, draw; 0 when every world passed."""
    parser = argparse.ArgumentParser(prog=f'python -m rory_eval.quality.{spec.name}',
                                     description=f'Quality of targets/{spec.name}')
    parser.add_argument('--worlds', nargs='+', default=list(WORLDS), choices=WORLDS)
    parser.add_argument('--out', type=Path, default=Path(f'quality-out/{spec.name}'))
    parser.add_argument('--domain', type=int, default=190,
                        help='ROS_DOMAIN_ID of the first run; each run takes the next one')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--no-navigation', action='store_true',
                        help='only the route runs')
    args = parser.parse_args(argv)
    out: Path = args.out
    # Each run gets a domain of its own: a latched /goal_pose of an earlier run in this process
    # was seen reaching the next run's navigator on a shared domain.
    domains = itertools.count(args.domain)
    routes: list[RouteQuality] = []
    print(ROUTE_HEADER)
    print(ROUTE_UNITS, flush=True)
    for world in args.worlds:
        q = run_route(spec, world, out / f'route_{world}', domain_id=next(domains),
                      seed=args.seed)
        routes.append(q)
        route_figure(spec, q, out)
        print(q.row(), flush=True)
    error_figure(spec, routes, out)
    navigations: list[NavigationQuality] = []
    if not args.no_navigation:
        print()
        print(NAV_HEADER, flush=True)
        for world in args.worlds:
            n = run_navigation(spec, world, out / f'navigation_{world}',
                               domain_id=next(domains), seed=args.seed)
            navigations.append(n)
            navigation_figure(spec, n, out)
            print(n.row(), flush=True)
    ok = all(q.median <= 0.15 for q in routes) and all(
        n.reached and n.collisions == 0 for n in navigations)
    poses = sum(q.poses for q in routes)
    print(f'\n{len(routes)} routes ({poses} poses), median error <= 0.15 m in '
          f'{sum(q.median <= 0.15 for q in routes)}; '
          f'{sum(n.reached for n in navigations)}/{len(navigations)} goals reached, '
          f'{sum(n.collisions for n in navigations)} collisions; figures in {out}/')
    return 0 if ok else 1


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m rory_eval.quality.amcl``."""
    return evaluate(TARGETS['amcl'], argv)


if __name__ == '__main__':
    sys.exit(main())
