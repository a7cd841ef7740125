"""Quality of targets/grid_slam: the map and the pose it builds from scans alone.

Each run is the simulator driving a world's whole route (``--driver internal``: the same
trajectory and scans every time for a seed) and the grid_slam node started at the world's start
pose. It prints, per world: how many observed cells of the last ``/map`` agree with the
ground-truth map and the IoU of their occupied cells (``map_score``, tolerance one cell), the
fraction of the world observed, the pose's median / max / final position error against ground
truth and its largest heading error, and the node's CPU% and peak RSS. It draws each world's
map with both paths, and the position error over time.

    python -m rory_eval.quality.grid_slam [--worlds W ...] [--out DIR] [--domain N] [--seed S]
"""

from __future__ import annotations

import argparse
import json
import math
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

TARGET = TARGETS['grid_slam']
WORLDS = ('office_small', 'workshop', 'real_room')
# Sim seconds per world: the internal driver's route (sim/README.md) plus a little.
DURATIONS = {'office_small': 107.0, 'workshop': 127.0, 'real_room': 82.0}


@dataclass
class WorldResult:
    """What one full-route run gave."""

    world: str
    duration: float  # sim s
    poses: int  # /grid_slam/pose messages (one per processed scan)
    agreement: float
    iou_occupied: float
    observed_fraction: float
    median_error: float  # m
    max_error: float  # m
    final_error: float  # m
    first_yaw_error: float  # deg, at the first scan (the map's anchoring)
    max_yaw_error: float  # deg
    anchored_median_error: float  # m, with the first scan's heading error taken out
    anchored_max_error: float  # m
    cpu_percent: float
    peak_rss_mb: float

    def row(self) -> str:
        """One line of the table."""
        return (f'{self.world:12s} {self.duration:6.0f} {self.poses:6d} {self.agreement:7.3f} '
                f'{self.iou_occupied:6.3f} {self.observed_fraction:6.2f} '
                f'{self.median_error:7.3f} {self.max_error:7.3f} {self.final_error:7.3f} '
                f'{self.first_yaw_error:6.2f} {self.max_yaw_error:6.2f} '
                f'{self.anchored_median_error:7.3f} {self.anchored_max_error:7.3f} '
                f'{self.cpu_percent:6.1f} {self.peak_rss_mb:6.0f}')


HEADER = (f'{"world":12s} {"sim s":>6s} {"poses":>6s} {"agree":>7s} {"IoU":>6s} {"seen":>6s} '
          f'{"med m":>7s} {"max m":>7s} {"end m":>7s} {"yaw0°":>6s} {"yaw°":>6s} '
          f'{"med m*":>7s} {"max m*":>7s} {"CPU%":>6s} {"RSS MB":>6s}')
FOOTNOTE = ('yaw0°: heading error at the first scan, which the map is anchored to (the node '
            'starts at map_start_yaw, the robot has already turned); *: position error with '
            'that heading offset taken out (the estimate rotated about the start by it)')


def run_world(world: str, out: Path, *, domain_id: int, seed: int = 0,
              duration: float | None = None) -> tuple[WorldResult, dict[str, Any]]:
    """One full-route run; its result and what the figures need (map, paths, errors)."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import OccupancyGrid

    seconds = duration or DURATIONS[world]
    run = SimRun(world, out, domain_id=domain_id, duration=seconds, seed=seed, depth=False)
    run.add_node('grid_slam', TARGET.argv(world))
    run.record('/map', OccupancyGrid, qos=LATCHED, keep_last=True)
    run.record('/grid_slam/pose', PoseStamped)
    result = run.run()

    truth = result.ground_truth
    poses = [(_stamp(p), p.pose.position.x, p.pose.position.y, _yaw(p.pose.orientation))
             for p in result.messages['/grid_slam/pose']]
    errors = position_errors([p[:3] for p in poses], truth)
    yaw_errors = _yaw_errors(poses, truth)
    anchored = position_errors(_rotate_about_first(poses, -math.radians(yaw_errors[0])), truth)
    grid = grid_from_msg(result.last('/map'))
    score = map_score(grid, ground_truth_map(get_world(world)), tolerance=1)
    usage = result.usage['grid_slam']
    measured = WorldResult(
        world=world, duration=seconds, poses=len(poses), agreement=score.agreement,
        iou_occupied=score.iou_occupied, observed_fraction=score.observed_fraction,
        median_error=float(np.median(errors)), max_error=float(errors.max()),
        final_error=float(errors[-1]), first_yaw_error=float(yaw_errors[0]),
        max_yaw_error=float(np.abs(yaw_errors).max()),
        anchored_median_error=float(np.median(anchored)),
        anchored_max_error=float(anchored.max()), cpu_percent=usage.cpu_percent,
        peak_rss_mb=usage.peak_rss_mb)
    figure = {'grid': grid, 'estimate': [(p[1], p[2]) for p in poses],
              'truth': [(r[1], r[2]) for r in truth],
              'times': [p[0] for p in poses][:len(errors)], 'errors': errors}
    return measured, figure


def _rotate_about_first(poses: Sequence[tuple[float, float, float, float]],
                        angle: float) -> list[tuple[float, float, float]]:
    """(t, x, y) of the poses rotated by ``angle`` about the first one's position."""
    x0, y0 = poses[0][1], poses[0][2]
    c, s = math.cos(angle), math.sin(angle)
    return [(t, x0 + c * (x - x0) - s * (y - y0), y0 + s * (x - x0) + c * (y - y0))
            for t, x, y, _ in poses]


def _stamp(msg: Any) -> float:
    return float(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)


def _yaw(q: Any) -> float:
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def _yaw_errors(poses: Sequence[tuple[float, float, float, float]],
                truth: Sequence[tuple[float, float, float, float]]) -> np.ndarray:
    """Heading error (deg) of each pose against the nearest ground-truth row (10 Hz, like
    the scans, so the stamps coincide)."""
    times = np.array([r[0] for r in truth])
    yaws = np.array([r[3] for r in truth])
    stamps = np.array([p[0] for p in poses])
    nearest = np.clip(np.searchsorted(times, stamps), 0, len(times) - 1)
    earlier = np.clip(nearest - 1, 0, len(times) - 1)
    nearest = np.where(np.abs(times[earlier] - stamps) < np.abs(times[nearest] - stamps),
                       earlier, nearest)
    diff = np.array([p[3] for p in poses]) - yaws[nearest]
    return np.asarray(np.degrees(np.arctan2(np.sin(diff), np.cos(diff))))


def draw(world: str, figure: dict[str, Any], out: Path) -> Path:
    """The world with the node's map underneath and both paths on top."""
    from sim.render import render_world

    return render_world(get_world(world), out, grid=figure['grid'],
                        paths={'grid_slam': figure['estimate'], 'ground truth': figure['truth']},
                        show_goals=False, title=f'{world}: grid_slam map and pose (route)')


def draw_errors(figures: dict[str, dict[str, Any]], out: Path) -> Path:
    """Position error over time, one line per world."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.0, 3.5))
    try:
        for world, figure in figures.items():
            ax.plot(figure['times'], np.asarray(figure['errors']) * 100.0, lw=1.0, label=world)
        ax.set_xlabel('sim time (s)')
        ax.set_ylabel('position error (cm)')
        ax.set_title('grid_slam: pose against ground truth over the route', fontsize=9)
        ax.grid(True, lw=0.3, alpha=0.5)
        ax.legend(fontsize=8)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(out, dpi=120)
    finally:
        plt.close(fig)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Run the worlds, print the table, write figures and results.json under --out."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.quality.grid_slam',
                                     description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument('--worlds', nargs='+', default=list(WORLDS), choices=WORLDS)
    parser.add_argument('--out', type=Path, default=Path('quality-out/grid_slam'))
    parser.add_argument('--domain', type=int, default=100, help='ROS_DOMAIN_ID of the runs')
    parser.add_argument('--seed', type=int, default=0, help="the simulator's noise seed")
    args = parser.parse_args(argv)
    results: list[WorldResult] = []
    figures: dict[str, dict[str, Any]] = {}
    for world in args.worlds:
        measured, figure = run_world(world, args.out / world, domain_id=args.domain,
                                     seed=args.seed)
        results.append(measured)
        figures[world] = figure
        draw(world, figure, args.out / f'{world}.png')
        print(f'{world}: done', file=sys.stderr, flush=True)
    draw_errors(figures, args.out / 'errors.png')
    (args.out / 'results.json').write_text(
        json.dumps([asdict(r) for r in results], indent=2) + '\n')
    print(HEADER)
    for r in results:
        print(r.row())
    print(FOOTNOTE)
    print(f'figures: {args.out}/<world>.png, {args.out}/errors.png')
    return 0


if __name__ == '__main__':
    sys.exit(main())
