"""Quality of targets/depth_mapper: its camera trajectory and its 3D model, against ground truth.

Each run is the simulator driving a world's whole route (``--driver internal``: the same
trajectory and depth frames every time for a seed) and the depth_mapper node started at the
world's start pose. It prints, per world: the model's size and the fraction of its points within
5 cm of the geometry (``distance_to_geometry``), also counting only the points above the floor
(the floor is easy: any point near z = 0 is within 5 cm of it); the online pose's median / max /
final position error (base_link, from the published camera pose) and largest heading error;
the same for the wheel odometry alone, and the ratio of the two medians; the keyframe
trajectory's median / max error after the last loop closure; the loop closures; and the node's
CPU% and peak RSS. It draws each world's model (points coloured by their distance to the
geometry) with the paths, and the position error over time.

    python -m rory_eval.quality.depth_mapper [--worlds W ...] [--out DIR] [--domain N] [--seed S]
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from rory_eval.harness.simrun import LATCHED, SimRun
from rory_eval.metrics import distance_to_geometry, position_errors
from rory_eval.targets import TARGETS
from sim.worlds import Box, get_world

FloatArray = npt.NDArray[np.float64]

TARGET = TARGETS['depth_mapper']
WORLDS = ('office_small', 'workshop', 'real_room')
# Sim seconds per world: the internal driver's route (sim/README.md) plus a little.
DURATIONS = {'office_small': 107.0, 'workshop': 127.0, 'real_room': 82.0}
CAMERA_X = 0.12  # camera_depth_optical_frame ahead of base_link (the node's default)
WITHIN = 0.05  # m: the tolerance for a model point
FLOOR = 0.05  # m: points below this height count as floor


@dataclass
class WorldResult:
    """What one full-route run gave."""

    world: str
    duration: float  # sim s
    frames: int  # /depth_mapper/pose messages (one per tracked depth frame)
    points: int  # model points published (voxels seen in >= 2 keyframes)
    within: float  # fraction of them within 5 cm of the geometry
    within_above_floor: float  # the same, of the points above the floor
    median_error: float  # m, online pose (base_link)
    max_error: float
    final_error: float
    max_yaw_error: float  # deg
    odom_median_error: float  # m, wheel odometry alone
    odom_max_error: float
    keyframe_median_error: float  # m, keyframe poses after the last loop closure
    keyframe_max_error: float
    loops: int
    cpu_percent: float
    peak_rss_mb: float

    @property
    def improvement(self) -> float:
        """How many times smaller the median position error is than the odometry's."""
        return self.odom_median_error / max(self.median_error, 1e-9)

    def row(self) -> str:
        """One line of the table."""
        return (f'{self.world:12s} {self.frames:6d} {self.points:7d} {self.within:6.3f} '
                f'{self.within_above_floor:6.3f} {self.median_error:6.3f} {self.max_error:6.3f} '
                f'{self.final_error:6.3f} {self.max_yaw_error:5.2f} {self.odom_median_error:6.3f} '
                f'{self.odom_max_error:6.3f} {self.improvement:5.1f} '
                f'{self.keyframe_median_error:6.3f} {self.keyframe_max_error:6.3f} '
                f'{self.loops:5d} {self.cpu_percent:5.1f} {self.peak_rss_mb:6.0f}')


HEADER = (f'{"world":12s} {"frames":>6s} {"points":>7s} {"<5cm":>6s} {"<5cm*":>6s} '
          f'{"med m":>6s} {"max m":>6s} {"end m":>6s} {"yaw°":>5s} {"odo md":>6s} '
          f'{"odo mx":>6s} {"gain":>5s} {"kf md":>6s} {"kf mx":>6s} {"loops":>5s} '
          f'{"CPU%":>5s} {"RSS MB":>6s}')
FOOTNOTE = ('<5cm: model points within 5 cm of the geometry; <5cm*: of those above the floor '
            '(z > 5 cm); med/max/end: online pose error; odo: wheel odometry alone; gain: '
            'odometry median / pose median; kf: keyframe poses after the last loop closure')


def base_poses(camera_poses: Sequence[Any]) -> list[tuple[float, float, float, float]]:
    """(t, x, y, yaw) of base_link from the published camera (optical frame) poses."""
    out = []
    for p in camera_poses:
        q = p.pose.orientation
        # The optical z axis (where the camera looks) is the rotation's third column.
        yaw = math.atan2(2.0 * (q.y * q.z - q.w * q.x), 2.0 * (q.x * q.z + q.w * q.y))
        out.append((_stamp(p), p.pose.position.x - CAMERA_X * math.cos(yaw),
                    p.pose.position.y - CAMERA_X * math.sin(yaw), yaw))
    return out


def run_world(world: str, out: Path, *, domain_id: int, seed: int = 0,
              duration: float | None = None) -> tuple[WorldResult, dict[str, Any]]:
    """One full-route run; its result and what the figures need (model, paths, errors)."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path as PathMsg
    from sensor_msgs.msg import PointCloud2

    seconds = duration or DURATIONS[world]
    run = SimRun(world, out, domain_id=domain_id, duration=seconds, seed=seed,
                 wait_for={'/camera/depth/points': 1, '/odom': 1})
    run.add_node('depth_mapper', TARGET.argv(world))
    run.record('/depth_mapper/pose', PoseStamped)
    run.record('/depth_mapper/cloud', PointCloud2, qos=LATCHED, keep_last=True)
    run.record('/depth_mapper/keyframes', PathMsg, qos=LATCHED, keep_last=True)
    result = run.run()

    truth = result.ground_truth
    poses = base_poses(result.messages['/depth_mapper/pose'])
    errors = position_errors([p[:3] for p in poses], truth)
    yaw_errors = _yaw_errors(poses, truth)
    odometry = _odometry(out / 'path.csv')
    odom_errors = position_errors(odometry, truth)
    keyframes = [(_stamp(p), p.pose.position.x, p.pose.position.y)
                 for p in result.last('/depth_mapper/keyframes').poses]
    kf_errors = position_errors(keyframes, truth)
    cloud = result.last('/depth_mapper/cloud')
    points = np.frombuffer(bytes(cloud.data), dtype=np.float32).reshape(-1, 3).astype(np.float64)
    distance = distance_to_geometry(get_world(world), points)
    above = points[:, 2] > FLOOR
    usage = result.usage['depth_mapper']
    measured = WorldResult(
        world=world, duration=seconds, frames=len(poses), points=len(points),
        within=float(np.mean(distance < WITHIN)),
        within_above_floor=float(np.mean(distance[above] < WITHIN)),
        median_error=float(np.median(errors)), max_error=float(errors.max()),
        final_error=float(errors[-1]), max_yaw_error=float(np.abs(yaw_errors).max()),
        odom_median_error=float(np.median(odom_errors)), odom_max_error=float(odom_errors.max()),
        keyframe_median_error=float(np.median(kf_errors)),
        keyframe_max_error=float(kf_errors.max()), loops=_loops(result.log('depth_mapper')),
        cpu_percent=usage.cpu_percent, peak_rss_mb=usage.peak_rss_mb)
    (out / 'errors.json').write_text(json.dumps({
        't': [p[0] for p in poses][:len(errors)], 'position': errors.tolist(),
        'yaw_deg': yaw_errors.tolist()}) + '\n')
    figure = {'points': points, 'distance': distance,
              'estimate': [(p[1], p[2]) for p in poses],
              'odometry': [(p[1], p[2]) for p in odometry],
              'truth': [(r[1], r[2]) for r in truth],
              'times': [p[0] for p in poses][:len(errors)], 'errors': errors,
              'odom_times': [p[0] for p in odometry][:len(odom_errors)],
              'odom_errors': odom_errors}
    return measured, figure


def _stamp(msg: Any) -> float:
    return float(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)


def _odometry(path_csv: Path) -> list[tuple[float, float, float]]:
    """(t, x, y) of the wheel odometry in ``map`` (the odom frame placed at the start)."""
    lines = path_csv.read_text().splitlines()
    header = lines[0].split(',')
    col = {name: header.index(name) for name in
           ('t', 'odom_x', 'odom_y', 'start_x', 'start_y', 'start_yaw')}
    out = []
    for line in lines[1:]:
        if not line or line.startswith('#'):
            continue
        v = [float(c) for c in line.split(',')]
        c, s = math.cos(v[col['start_yaw']]), math.sin(v[col['start_yaw']])
        ox, oy = v[col['odom_x']], v[col['odom_y']]
        out.append((v[col['t']], v[col['start_x']] + c * ox - s * oy,
                    v[col['start_y']] + s * ox + c * oy))
    return out


def _loops(log: str) -> int:
    """Loop closures, from the node's log (a line each)."""
    return len(re.findall(r'loop closure at t=', log))


def _yaw_errors(poses: Sequence[tuple[float, float, float, float]],
                truth: Sequence[tuple[float, float, float, float]]) -> FloatArray:
    """Heading error (deg) of each pose against the nearest ground-truth row (10 Hz; the
    5 Hz frames fall on its rows)."""
    times = np.array([r[0] for r in truth])
    yaws = np.array([r[3] for r in truth])
    stamps = np.array([p[0] for p in poses])
    nearest = np.clip(np.searchsorted(times, stamps), 0, len(times) - 1)
    earlier = np.clip(nearest - 1, 0, len(times) - 1)
    nearest = np.where(np.abs(times[earlier] - stamps) < np.abs(times[nearest] - stamps),
                       earlier, nearest)
    diff = np.array([p[3] for p in poses]) - yaws[nearest]
    return np.asarray(np.degrees(np.arctan2(np.sin(diff), np.cos(diff))), dtype=np.float64)


def draw(world: str, figure: dict[str, Any], out: Path) -> Path:
    """Top view: the geometry, the model's points above the floor coloured by their distance
    to it, and the paths (ground truth, odometry, depth_mapper)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.patches import Circle, Polygon

    w = get_world(world)
    xmin, ymin, xmax, ymax = w.bounds
    scale = 8.0 / max(xmax - xmin, ymax - ymin)
    fig, ax = plt.subplots(figsize=((xmax - xmin) * scale + 2.5, (ymax - ymin) * scale + 1.0))
    try:
        for o in w.obstacles:
            if isinstance(o, Box):
                ax.add_patch(Polygon(o.corners(), closed=True, facecolor='#d8d8d8',
                                     edgecolor='#909090', lw=0.5))
            else:
                ax.add_patch(Circle((o.x, o.y), o.radius, facecolor='#d8d8d8',
                                    edgecolor='#909090', lw=0.5))
        points, distance = figure['points'], figure['distance']
        above = points[:, 2] > FLOOR
        order = np.argsort(points[above, 2])  # higher points drawn last
        shown = ax.scatter(points[above, 0][order], points[above, 1][order], s=0.4,
                           c=np.minimum(distance[above][order] * 100.0, 10.0), cmap='RdYlGn_r',
                           vmin=0.0, vmax=10.0, linewidths=0)
        fig.colorbar(shown, ax=ax, shrink=0.7, label='model point to geometry (cm, capped)')
        for name, colour, style in (('truth', '#000000', '-'), ('odometry', '#d02020', ':'),
                                    ('estimate', '#1060d0', '--')):
            path = figure[name]
            label = {'truth': 'ground truth', 'estimate': 'depth_mapper'}.get(name, name)
            ax.plot([p[0] for p in path], [p[1] for p in path], style, color=colour, lw=1.0,
                    label=label)
        ax.set_xlim(xmin - 0.3, xmax + 0.3)
        ax.set_ylim(ymin - 0.3, ymax + 0.3)
        ax.set_aspect('equal')
        ax.set_xlabel('x (m, map frame)')
        ax.set_ylabel('y (m)')
        ax.set_title(f'{world}: depth_mapper model above the floor, and paths', fontsize=9)
        ax.legend(loc='upper left', fontsize=7)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(out, dpi=130)
    finally:
        plt.close(fig)
    return out


def draw_errors(figures: dict[str, dict[str, Any]], out: Path) -> Path:
    """Position error over time, depth_mapper (solid) and odometry (dotted), per world."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.0, 3.5))
    try:
        for k, (world, figure) in enumerate(figures.items()):
            colour = f'C{k}'
            ax.plot(figure['times'], np.asarray(figure['errors']) * 100.0, lw=1.0,
                    color=colour, label=f'{world}: depth_mapper')
            ax.plot(figure['odom_times'], np.asarray(figure['odom_errors']) * 100.0, ':',
                    lw=1.0, color=colour, label=f'{world}: odometry')
        ax.set_yscale('log')
        ax.set_xlabel('sim time (s)')
        ax.set_ylabel('position error (cm)')
        ax.set_title('depth_mapper: pose against ground truth over the route', fontsize=9)
        ax.grid(True, lw=0.3, alpha=0.5)
        ax.legend(fontsize=7, ncol=2)
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.tight_layout()
        fig.savefig(out, dpi=120)
    finally:
        plt.close(fig)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Run the worlds, print the table, write figures and results.json under --out.

    Returns:
        0 if every world's model has >= 90 % of its points within 5 cm of the geometry.
    """
    parser = argparse.ArgumentParser(prog='python -m rory_eval.quality.depth_mapper',
                                     description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument('--worlds', nargs='+', default=list(WORLDS), choices=WORLDS)
    parser.add_argument('--out', type=Path, default=Path('quality-out/depth_mapper'))
    parser.add_argument('--domain', type=int, default=145, help='ROS_DOMAIN_ID of the runs')
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
    (args.out / 'results.json').write_text(json.dumps(
        [{**asdict(r), 'improvement': r.improvement} for r in results], indent=2) + '\n')
    print(HEADER)
    for r in results:
        print(r.row())
    print(FOOTNOTE)
    print(f'figures: {args.out}/<world>.png, {args.out}/errors.png')
    return 0 if all(r.within >= 0.9 for r in results) else 1


if __name__ == '__main__':
    sys.exit(main())
