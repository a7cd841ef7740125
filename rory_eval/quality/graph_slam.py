"""Quality of targets/graph_slam: its map, its pose and its loop closures, against odometry.

Each run is the simulator driving a world's whole route (``--driver internal``: the same
trajectory and messages every time for a seed) with three processes reading it:

* ``graph_slam``, the node as shipped, started at the world's start pose;
* ``odometry``, the same program with scan matching and loop closure off (keyframes at the
  wheel-odometry poses): the map and pose odometry alone gives, for comparison;
* ``idle``, an rclpy node with ``use_sim_time`` that subscribes ``/odom`` and ``/scan`` and
  publishes a pose per scan: what the ROS plumbing alone costs on this machine.

It prints, per world: how many observed cells of the last ``/map`` agree with the ground-truth
map and the IoU of their occupied cells (``map_score``, tolerance one cell), the fraction of the
world observed, the pose's median / max / final position error, the same for odometry alone,
the graph (keyframes, loop closures, optimisations and their longest time, from the node's
log) and each node's CPU% and peak RSS. It draws each world's map with the three paths and the
loop-closure edges, the odometry-only map, and the position error over time.

    python -m rory_eval.quality.graph_slam [--worlds W ...] [--out DIR] [--domain N] [--seed S]
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rory_eval.harness.simrun import LATCHED, SimRun
from rory_eval.metrics import grid_from_msg, map_score, position_errors
from rory_eval.targets import TARGETS
from sim.maps import ground_truth_map
from sim.worlds import get_world

TARGET = TARGETS['graph_slam']
WORLDS = ('office_small', 'workshop', 'real_room')
# Sim seconds per world: the internal driver's route (sim/README.md) plus a little.
DURATIONS = {'office_small': 107.0, 'workshop': 127.0, 'real_room': 82.0}
# The odometry-only instance's outputs, remapped off the real ones.
ODOM_REMAP = ['-r', '__node:=graph_slam_odometry', '-r', '/map:=/odometry/map',
              '-r', '/graph_slam/pose:=/odometry/pose', '-r', '/graph_slam/graph:=/odometry/graph',
              '-r', '/diagnostics:=/odometry/diagnostics']

IDLE = '''
import rclpy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan


class Idle(Node):
    def __init__(self):
        super().__init__('idle')
        self.pub = self.create_publisher(PoseStamped, '/idle/pose', 10)
        self.odom = None
        self.create_subscription(Odometry, '/odom', self.on_odom,
                                 QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
        self.create_subscription(LaserScan, '/scan', self.on_scan,
                                 QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))

    def on_odom(self, msg):
        self.odom = msg

    def on_scan(self, msg):
        out = PoseStamped()
        out.header = msg.header
        if self.odom is not None:
            out.pose = self.odom.pose.pose
        self.pub.publish(out)


rclpy.init()
try:
    rclpy.spin(Idle())
except KeyboardInterrupt:
    pass
'''

_OPTIMISED = re.compile(r'optimisation (applied|rejected).*?, ([0-9.]+) ms(?:, grid rebuilt in '
                        r'([0-9.]+) ms)?')
_LOOP = re.compile(r'loop closure at t=([0-9.]+) s: keyframe (\d+) -> (\d+)')


@dataclass
class WorldResult:
    """What one full-route run gave."""

    world: str
    duration: float  # sim s
    poses: int  # /graph_slam/pose messages (one per processed scan)
    agreement: float
    iou_occupied: float
    observed_fraction: float
    median_error: float  # m
    max_error: float  # m
    final_error: float  # m
    odom_agreement: float  # the same for odometry alone
    odom_iou_occupied: float
    odom_median_error: float
    odom_max_error: float
    odom_final_error: float
    keyframes: int
    loop_closures: int
    optimisations: int  # loop closures that moved the graph (the others already agreed)
    max_optimise_ms: float  # wall time of the longest optimisation (incl. rebuild)
    cpu_percent: float
    peak_rss_mb: float
    idle_cpu_percent: float  # a do-nothing node on the same topics
    idle_peak_rss_mb: float

    def row(self) -> str:
        """One line of the table."""
        return (f'{self.world:12s} {self.duration:5.0f} {self.poses:5d} {self.agreement:6.3f} '
                f'{self.iou_occupied:6.3f} {self.observed_fraction:5.2f} '
                f'{self.median_error:6.3f} {self.max_error:6.3f} {self.final_error:6.3f} | '
                f'{self.odom_agreement:6.3f} {self.odom_iou_occupied:6.3f} '
                f'{self.odom_median_error:6.3f} {self.odom_max_error:6.3f} '
                f'{self.odom_final_error:6.3f} | {self.keyframes:4d} {self.loop_closures:5d} '
                f'{self.optimisations:4d} {self.max_optimise_ms:6.1f} | '
                f'{self.cpu_percent:5.1f} {self.peak_rss_mb:4.0f} {self.idle_cpu_percent:5.1f} '
                f'{self.idle_peak_rss_mb:4.0f}')


HEADER = (f'{"":12s} {"":5s} {"":5s} {"graph_slam":-^40s} | {"odometry alone":-^34s} | '
          f'{"graph":-^24s} | {"graph_slam":^10s} {"idle":^10s}\n'
          f'{"world":12s} {"sim s":>5s} {"poses":>5s} {"agree":>6s} {"IoU":>6s} {"seen":>5s} '
          f'{"med m":>6s} {"max m":>6s} {"end m":>6s} | {"agree":>6s} {"IoU":>6s} '
          f'{"med m":>6s} {"max m":>6s} {"end m":>6s} | {"kfs":>4s} {"loops":>5s} {"opts":>4s} '
          f'{"max ms":>6s} | {"CPU%":>5s} {"MB":>4s} {"CPU%":>5s} {"MB":>4s}')
FOOTNOTE = ('loops: loop-closure edges; opts: those that moved the graph (Gauss-Newton run, '
            'grid rebuilt if a keyframe moved > 2 cm), the others already agreed with it; '
            'max ms: the longest optimisation plus rebuild; idle: rclpy alone on the same '
            'topics; MB: peak RSS')


def run_world(world: str, out: Path, *, domain_id: int, seed: int = 0,
              duration: float | None = None) -> tuple[WorldResult, dict[str, Any]]:
    """One full-route run; its result and what the figures need (maps, paths, errors)."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import OccupancyGrid
    from nav_msgs.msg import Path as PathMsg

    seconds = duration or DURATIONS[world]
    out.mkdir(parents=True, exist_ok=True)
    idle = out / 'idle_node.py'
    idle.write_text(IDLE)
    run = SimRun(world, out, domain_id=domain_id, duration=seconds, seed=seed, depth=False,
                 wait_for={'/scan': 4, '/odom': 3})
    run.add_node('graph_slam', TARGET.argv(world))
    run.add_node('odometry', TARGET.argv(world, '-p', 'scan_matching:=false',
                                         '-p', 'loop_closure:=false', *ODOM_REMAP))
    run.add_node('idle', [sys.executable, str(idle), '--ros-args', '-p', 'use_sim_time:=true'])
    run.record('/map', OccupancyGrid, qos=LATCHED, keep_last=True)
    run.record('/odometry/map', OccupancyGrid, qos=LATCHED, keep_last=True)
    run.record('/graph_slam/graph', PathMsg, qos=LATCHED, keep_last=True)
    run.record('/diagnostics', DiagnosticArray, keep_last=True)
    run.record('/graph_slam/pose', PoseStamped)
    run.record('/odometry/pose', PoseStamped)
    result = run.run()

    truth = result.ground_truth
    truth_map = ground_truth_map(get_world(world))
    slam = [(_stamp(p), p.pose.position.x, p.pose.position.y)
            for p in result.messages['/graph_slam/pose']]
    odom = [(_stamp(p), p.pose.position.x, p.pose.position.y)
            for p in result.messages['/odometry/pose']]
    errors = position_errors(slam, truth)
    odom_errors = position_errors(odom, truth)
    grid = grid_from_msg(result.last('/map'))
    odom_grid = grid_from_msg(result.last('/odometry/map'))
    score = map_score(grid, truth_map, tolerance=1)
    odom_score = map_score(odom_grid, truth_map, tolerance=1)
    values = {kv.key: kv.value for kv in result.last('/diagnostics').status[0].values}
    log = result.log('graph_slam')
    optimised = [float(m.group(2)) + float(m.group(3) or 0.0)
                 for m in _OPTIMISED.finditer(log) if m.group(1) == 'applied']
    keyframes = [(p.pose.position.x, p.pose.position.y)
                 for p in result.last('/graph_slam/graph').poses]
    loops = [(float(m.group(1)), int(m.group(2)), int(m.group(3))) for m in _LOOP.finditer(log)]
    usage, idle_usage = result.usage['graph_slam'], result.usage['idle']
    measured = WorldResult(
        world=world, duration=seconds, poses=len(slam), agreement=score.agreement,
        iou_occupied=score.iou_occupied, observed_fraction=score.observed_fraction,
        median_error=float(np.median(errors)), max_error=float(errors.max()),
        final_error=float(errors[-1]), odom_agreement=odom_score.agreement,
        odom_iou_occupied=odom_score.iou_occupied,
        odom_median_error=float(np.median(odom_errors)),
        odom_max_error=float(odom_errors.max()), odom_final_error=float(odom_errors[-1]),
        keyframes=int(values['keyframes']), loop_closures=int(values['loop_closures']),
        optimisations=len(optimised), max_optimise_ms=max(optimised, default=0.0),
        cpu_percent=usage.cpu_percent, peak_rss_mb=usage.peak_rss_mb,
        idle_cpu_percent=idle_usage.cpu_percent, idle_peak_rss_mb=idle_usage.peak_rss_mb)
    figure = {'grid': grid, 'odom_grid': odom_grid, 'slam': [(p[1], p[2]) for p in slam],
              'odometry': [(p[1], p[2]) for p in odom], 'truth': [(r[1], r[2]) for r in truth],
              'keyframes': keyframes, 'loops': loops,
              'times': [p[0] for p in slam][:len(errors)], 'errors': errors,
              'odom_times': [p[0] for p in odom][:len(odom_errors)], 'odom_errors': odom_errors}
    return measured, figure


def _stamp(msg: Any) -> float:
    return float(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)


def draw(world: str, figure: dict[str, Any], out: Path) -> list[Path]:
    """The node's map with the three paths; its pose graph (keyframes, loop edges) on the map;
    the odometry-only map."""
    from sim.render import render_world

    w = get_world(world)
    slam_png = render_world(
        w, out / f'{world}.png', grid=figure['grid'], show_goals=False, show_route=False,
        paths={'graph_slam': figure['slam'], 'wheel odometry': figure['odometry'],
               'ground truth': figure['truth']},
        title=f'{world}: graph_slam map and pose, against wheel odometry')
    graph_png = out / f'{world}_graph.png'
    _draw_graph(w, figure, graph_png)
    odom_png = render_world(
        w, out / f'{world}_odometry.png', grid=figure['odom_grid'], show_goals=False,
        show_route=False, paths={'wheel odometry': figure['odometry'],
                                 'ground truth': figure['truth']},
        title=f'{world}: the same scans at wheel-odometry poses (no scan matching, no loops)')
    return [slam_png, graph_png, odom_png]


def _draw_graph(world: Any, figure: dict[str, Any], out: Path) -> None:
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    grid = figure['grid']
    xmin, ymin, xmax, ymax = world.bounds
    scale = 8.0 / max(xmax - xmin, ymax - ymin)
    fig, ax = plt.subplots(figsize=(max(4.0, (xmax - xmin) * scale) + 1.5,
                                    max(3.0, (ymax - ymin) * scale) + 1.0))
    try:
        shade = np.where(grid.data < 0, 0.8, 1.0 - np.clip(grid.data, 0, 100) / 100.0)
        ax.imshow(shade, cmap='gray', vmin=0.0, vmax=1.0, origin='lower',
                  interpolation='nearest',
                  extent=(grid.origin_x, grid.origin_x + grid.width * grid.resolution,
                          grid.origin_y, grid.origin_y + grid.height * grid.resolution))
        kfs = np.array(figure['keyframes'])
        if kfs.size:
            ax.plot(kfs[:, 0], kfs[:, 1], '-', color='#1060d0', lw=0.8, label='keyframe chain')
            ax.plot(kfs[:, 0], kfs[:, 1], '.', color='#1060d0', ms=3)
            for k, (_, target, source) in enumerate(figure['loops']):
                if max(target, source) < len(kfs):
                    ax.plot(kfs[[target, source], 0], kfs[[target, source], 1], '-',
                            color='#20a020', lw=1.0, label='loop closure' if k == 0 else None)
        ax.set_xlim(xmin - 0.3, xmax + 0.3)
        ax.set_ylim(ymin - 0.3, ymax + 0.3)
        ax.set_aspect('equal')
        ax.set_xlabel('x (m, map frame)')
        ax.set_ylabel('y (m)')
        ax.set_title(f'{world.name}: pose graph ({len(kfs)} keyframes, '
                     f'{len(figure["loops"])} loop closures) on its map', fontsize=9)
        ax.legend(loc='upper left', bbox_to_anchor=(1.0, 1.0), fontsize=8)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(out, dpi=120)
    finally:
        plt.close(fig)


def draw_errors(figures: dict[str, dict[str, Any]], out: Path) -> Path:
    """Position error over time per world, graph_slam against odometry alone (log scale)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(figures), figsize=(4.5 * len(figures), 3.5), squeeze=False)
    try:
        for ax, (world, figure) in zip(axes[0], figures.items(), strict=True):
            ax.semilogy(figure['times'], np.maximum(figure['errors'], 1e-3) * 100.0, lw=1.0,
                        label='graph_slam')
            ax.semilogy(figure['odom_times'], np.maximum(figure['odom_errors'], 1e-3) * 100.0,
                        lw=1.0, label='wheel odometry')
            for k, (t, _, _) in enumerate(figure['loops']):
                ax.axvline(t, color='#20a020', lw=0.4, alpha=0.5,
                           label='loop closure' if k == 0 else None)
            ax.set_xlabel('sim time (s)')
            ax.set_ylabel('position error (cm)')
            ax.set_title(world, fontsize=9)
            ax.grid(True, lw=0.3, alpha=0.5)
            ax.legend(fontsize=7)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(out, dpi=120)
    finally:
        plt.close(fig)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Run the worlds, print the table, write figures and results.json under --out."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.quality.graph_slam',
                                     description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument('--worlds', nargs='+', default=list(WORLDS), choices=WORLDS)
    parser.add_argument('--out', type=Path, default=Path('quality-out/graph_slam'))
    parser.add_argument('--domain', type=int, default=120, help='ROS_DOMAIN_ID of the runs')
    parser.add_argument('--seed', type=int, default=0, help="the simulator's noise seed")
    args = parser.parse_args(argv)
    results: list[WorldResult] = []
    figures: dict[str, dict[str, Any]] = {}
    for world in args.worlds:
        measured, figure = run_world(world, args.out / world, domain_id=args.domain,
                                     seed=args.seed)
        results.append(measured)
        figures[world] = figure
        draw(world, figure, args.out)
        print(f'{world}: done', file=sys.stderr, flush=True)
    draw_errors(figures, args.out / 'errors.png')
    (args.out / 'results.json').write_text(
        json.dumps([asdict(r) for r in results], indent=2) + '\n')
    print(HEADER)
    for r in results:
        print(r.row())
    print(FOOTNOTE)
    print(f'figures: {args.out}/<world>.png (map and paths), <world>_graph.png (keyframes and '
          f'loop closures), <world>_odometry.png (odometry-only map), errors.png')
    return 0


if __name__ == '__main__':
    sys.exit(main())
