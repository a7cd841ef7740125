"""``rory sim ...`` (also ``python -m sim``): run a world, write its map, draw it, describe it.

Subcommands:
  run     the simulator in real time, bridged to ROS 2 (optionally with the route driver)
  route   drive a world's route synchronously without ROS (fast, deterministic); a summary
  map     write the ground-truth map (map.pgm + map.yaml, map_server convention)
  render  a top-down PNG of a world, optionally with recorded paths and a map
  info    a world's start, route, goals, frames, sensor specs as JSON
  list    the worlds
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from .worlds import WORLDS, World, get_world


def describe(world: World, seed: int | None = None) -> dict[str, Any]:
    """Everything a target or the evaluation needs to know about a world and the robot."""
    from .robot import LIMITS, ROBOT
    from .sensors import DEPTH, LIDAR

    def pose(p: Any) -> dict[str, float]:
        return {'x': p.x, 'y': p.y, 'yaw': round(p.yaw, 6)}

    return {
        'world': world.name,
        'description': world.description,
        'seed': seed,
        'bounds': list(world.bounds),
        'start': pose(world.start),
        'route': [list(p) for p in world.route],
        'route_length': round(world.route_length(), 3),
        'goals': {k: pose(v) for k, v in world.goals.items()},
        'default_goal': world.default_goal,
        'frames': {
            'map': 'world frame; ground truth, maps, goals',
            'odom': "the robot's start pose in map; /odom's parent",
            'base_link': 'on the floor between the wheels; x forward, y left, z up',
            ROBOT.lidar.frame_id: [ROBOT.lidar.x, ROBOT.lidar.y, ROBOT.lidar.z],
            ROBOT.camera.frame_id: [ROBOT.camera.x, ROBOT.camera.y, ROBOT.camera.z],
            'camera_optical_axes': 'z forward, x right, y down (base_link x = optical z)',
        },
        'robot': {
            'footprint': [2 * ROBOT.chassis_half[0], 2 * ROBOT.chassis_half[1]],
            'footprint_radius': round(ROBOT.footprint_radius, 4),
            'wheel_radius': ROBOT.wheel_radius,
            'wheel_separation': ROBOT.wheel_separation,
            'limits': asdict(LIMITS),
        },
        'lidar': {
            'beams': LIDAR.beams, 'angle_min': LIDAR.angle_min, 'angle_max': LIDAR.angle_max,
            'angle_increment': LIDAR.angle_increment, 'range_min': LIDAR.range_min,
            'range_max': LIDAR.range_max, 'rate': LIDAR.rate,
        },
        'depth': {
            'width': DEPTH.width, 'height': DEPTH.height, 'fx': DEPTH.fx, 'fy': DEPTH.fx,
            'cx': DEPTH.cx, 'cy': DEPTH.cy, 'hfov_deg': DEPTH.hfov_deg,
            'vfov_deg': DEPTH.vfov_deg, 'range_min': DEPTH.range_min,
            'range_max': DEPTH.range_max, 'rate': DEPTH.rate,
            # The noise's standard deviation is this times z^2 (m); DepthSpec.depth_rms.
            'depth_rms_per_z2': float(DEPTH.depth_rms(1.0)),
        },
        'noise': asdict(world.noise),
    }


def _cmd_list(args: argparse.Namespace) -> int:
    for w in WORLDS.values():
        print(f'{w.name:14s} {w.description} (route {w.route_length():.1f} m, '
              f'goals: {", ".join(w.goals)})')
    return 0


def _cmd_info(args: argparse.Namespace) -> int:
    print(json.dumps(describe(get_world(args.world)), indent=2))
    return 0


def _cmd_map(args: argparse.Namespace) -> int:
    from .maps import ground_truth_map, write_map

    world = get_world(args.world)
    grid = ground_truth_map(world, args.resolution)
    pgm, yml = write_map(grid, Path(args.out), args.name)
    print(f'{world.name}: {grid.width} x {grid.height} cells of {grid.resolution} m '
          f'-> {yml}, {pgm}')
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from .maps import load_map
    from .render import read_path, render_world

    world = get_world(args.world)
    paths: dict[str, Any] = {}
    for csv_path in args.path or []:
        recorded = read_path(Path(csv_path))
        label = Path(csv_path).parent.name or 'path'
        paths[f'{label}: ground truth'] = recorded['ground_truth']
        if args.odometry:
            paths[f'{label}: odometry'] = recorded['odometry']
    grid = load_map(Path(args.map)) if args.map else None
    out = render_world(world, Path(args.out), paths=paths, grid=grid,
                       show_route=not args.no_route, title=args.title)
    print(out)
    return 0


def _cmd_route(args: argparse.Namespace) -> int:
    from .driver import run_offline

    t0 = time.monotonic()
    summary = run_offline(args.world, args.seed, cruise=args.speed, sensors=args.sensors)
    path_csv = summary.pop('path_csv')
    summary['wall_seconds'] = round(time.monotonic() - t0, 3)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / 'path.csv').write_text(path_csv)
        (out / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')
        if args.png:
            from .render import read_path, render_world

            rec = read_path(out / 'path.csv')
            render_world(get_world(args.world), out / 'path.png',
                         paths={'ground truth': rec['ground_truth'],
                                'odometry': rec['odometry']})
    print(json.dumps(summary))
    return 0 if summary['completed'] and summary['collisions'] == 0 else 1


def _parse_wait(items: Sequence[str]) -> dict[str, int]:
    needs: dict[str, int] = {}
    for item in items:
        topic, _, count = item.partition('=')
        try:
            needs[topic] = int(count) if count else 1
        except ValueError:
            raise SystemExit(f'sim run: --wait-for {item!r}: expected TOPIC or TOPIC=N') from None
    return needs


def _cmd_run(args: argparse.Namespace) -> int:
    import signal

    import rclpy
    import rclpy.utilities
    from rclpy.signals import SignalHandlerOptions

    from .bridge import SimBridge
    from .driver import RouteFollower
    from .maps import ground_truth_map
    from .simulation import Simulation

    world = get_world(args.world)
    sim = Simulation(world, args.seed, lidar=not args.no_lidar, depth=not args.no_depth)
    grid = ground_truth_map(world)
    internal = RouteFollower(world.route, cruise=args.speed) if args.driver == 'internal' else None
    # Our own SIGINT/SIGTERM handling: finish the tick, then shut down and write the summary
    # (rclpy's handlers would invalidate the context under a publish).
    rclpy.init(args=['rory-sim', '--ros-args', *args.ros_args],
               signal_handler_options=SignalHandlerOptions.NO)
    bridge = SimBridge(sim, grid=grid, info=describe(world, args.seed), driver=internal)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: bridge.request_stop())
    log = bridge.node.get_logger()
    driver_proc: subprocess.Popen[bytes] | None = None
    driver_done_at: list[float] = []
    exit_code = 0
    try:
        if args.wait_for:
            needs = _parse_wait(args.wait_for)
            if not bridge.wait_for(needs, args.wait_timeout):
                log.warning(f'--wait-for {needs}: not all there after {args.wait_timeout} s; '
                            'starting anyway')
        if args.start_delay:
            # Latched data (the map, /sim/info) reaches late readers asynchronously: give it
            # time, so that every run's nodes see the map before the first scan.
            time.sleep(args.start_delay)
        if args.driver == 'route':
            driver_proc = subprocess.Popen(
                [sys.executable, '-m', 'sim.driver', '--world', world.name,
                 '--speed', str(args.speed)])
        log.info(f'{world.name}: running (seed {args.seed}, driver {args.driver}, '
                 f'duration {args.duration if args.duration else "until done"})')

        def should_stop() -> bool:
            # Without --duration, stop one second after the route is done.
            if args.duration is not None:
                return False
            finished = (
                (internal is not None and internal.done)
                or (driver_proc is not None and driver_proc.poll() is not None)
            )
            if finished and not driver_done_at:
                driver_done_at.append(sim.time)
            return bool(driver_done_at) and sim.time >= driver_done_at[0] + 1.0

        stats = bridge.run(args.duration, should_stop)
    finally:
        driver_finished = driver_proc is not None and driver_proc.poll() is not None
        if driver_proc is not None:
            _reap(driver_proc)
        bridge.close()
        rclpy.utilities.try_shutdown()
    summary = sim.summary()
    summary.update({
        'driver': args.driver,
        'cpu_seconds': round(stats.cpu_seconds, 4),
        'wall_seconds': round(stats.wall_seconds, 4),
        'cpu_per_sim_second': round(stats.cpu_seconds / max(stats.sim_seconds, 1e-9), 4),
        'real_time_factor': round(stats.sim_seconds / max(stats.wall_seconds, 1e-9), 4),
        'lag_resets': stats.lag_resets,
        'cmd_vel_received': stats.cmd_vel_received,
        'e_stop_received': stats.e_stop_received,
        'published': stats.published,
    })
    if internal is not None:
        summary['completed'] = internal.done
    elif driver_proc is not None:
        # A driver still running at the end (--duration) was stopped by us: not a failure.
        summary['completed'] = driver_finished and driver_proc.returncode == 0
        summary['driver_exit'] = driver_proc.returncode if driver_finished else None
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / 'path.csv').write_text(sim.path_csv())
        (out / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')
        if args.png:
            from .render import read_path, render_world

            rec = read_path(out / 'path.csv')
            render_world(world, out / 'path.png',
                         paths={'ground truth': rec['ground_truth'], 'odometry': rec['odometry']})
    print(json.dumps(summary), flush=True)
    if summary.get('driver_exit') not in (None, 0):
        exit_code = 1  # the route driver gave up on its own
    return exit_code


def _reap(proc: subprocess.Popen[bytes]) -> None:
    """Stop a child politely (SIGINT, then SIGTERM, then SIGKILL) and wait for it."""
    import signal

    for sig, wait in ((signal.SIGINT, 3.0), (signal.SIGTERM, 2.0), (signal.SIGKILL, 2.0)):
        if proc.poll() is not None:
            return
        proc.send_signal(sig)
        try:
            proc.wait(timeout=wait)
            return
        except subprocess.TimeoutExpired:
            continue


def _positive(text: str) -> float:
    value = float(text)
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f'expected a positive number, got {text!r}')
    return value


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (``prog`` is ``rory sim``)."""
    parser = argparse.ArgumentParser(prog='rory sim', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', required=True)
    worlds = sorted(WORLDS)

    run = sub.add_parser('run', help='run the simulator in real time, bridged to ROS 2')
    run.add_argument('--world', required=True, choices=worlds)
    run.add_argument('--driver', choices=('none', 'route', 'internal'), default='none',
                     help='route: the route driver as a ROS node publishing /cmd_vel; internal: '
                          'the same control law inside the simulator (deterministic for a seed)')
    run.add_argument('--duration', type=_positive, default=None,
                     help='sim seconds to run (default: until the route is done, or forever)')
    run.add_argument('--seed', type=int, default=0, help='noise seed (default 0)')
    run.add_argument('--speed', type=_positive, default=0.3, help='driver cruise speed (m/s)')
    run.add_argument('--out', help='folder for summary.json and path.csv')
    run.add_argument('--png', action='store_true', help='also draw the path into OUT/path.png')
    run.add_argument('--no-depth', action='store_true', help='no depth camera')
    run.add_argument('--no-lidar', action='store_true', help='no lidar')
    run.add_argument('--wait-for', action='append', metavar='TOPIC[=N]',
                     help='hold the clock at 0 until TOPIC has N subscribers (repeatable)')
    run.add_argument('--wait-timeout', type=_positive, default=30.0)
    run.add_argument('--start-delay', type=float, default=0.0, metavar='S',
                     help='after --wait-for, hold the clock at 0 this many more seconds')
    run.set_defaults(run=_cmd_run)

    route = sub.add_parser('route', help="drive a world's route without ROS (synchronous)")
    route.add_argument('--world', required=True, choices=worlds)
    route.add_argument('--seed', type=int, default=0)
    route.add_argument('--speed', type=_positive, default=0.3)
    route.add_argument('--sensors', action='store_true', help='also compute lidar and depth')
    route.add_argument('--out', help='folder for summary.json and path.csv')
    route.add_argument('--png', action='store_true', help='also draw OUT/path.png')
    route.set_defaults(run=_cmd_route)

    map_ = sub.add_parser('map', help='write the ground-truth map (map_server convention)')
    map_.add_argument('--world', required=True, choices=worlds)
    map_.add_argument('--out', required=True, help='folder to write NAME.pgm and NAME.yaml into')
    map_.add_argument('--name', default='map')
    map_.add_argument('--resolution', type=_positive, default=0.05)
    map_.set_defaults(run=_cmd_map)

    render = sub.add_parser('render', help='a top-down PNG of a world (matplotlib)')
    render.add_argument('--world', required=True, choices=worlds)
    render.add_argument('--out', required=True, help='PNG file to write')
    render.add_argument('--path', action='append', help='path.csv from run/route (repeatable)')
    render.add_argument('--odometry', action='store_true', help="also draw each path's odometry")
    render.add_argument('--map', help='a map.yaml to draw underneath')
    render.add_argument('--no-route', action='store_true', help="do not draw the driver's route")
    render.add_argument('--title')
    render.set_defaults(run=_cmd_render)

    info = sub.add_parser('info', help="a world's description as JSON")
    info.add_argument('--world', required=True, choices=worlds)
    info.set_defaults(run=_cmd_info)

    lst = sub.add_parser('list', help='the worlds')
    lst.set_defaults(run=_cmd_list)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point: ``rory sim ARGS`` calls this with ARGS.

    ``run`` is the default subcommand: ``rory sim --world office_small --driver route`` is
    ``rory sim run --world office_small --driver route``.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0].startswith('-') and argv[0] not in ('-h', '--help'):
        argv.insert(0, 'run')
    # ROS arguments (a namespace per robot, remaps) go to the simulator's node, as for any node.
    ros_args: list[str] = []
    if '--ros-args' in argv:
        at = argv.index('--ros-args')
        argv, ros_args = argv[:at], [a for a in argv[at + 1:] if a != '--']
    args = build_parser().parse_args(argv)
    args.ros_args = ros_args
    try:
        code: int = args.run(args)
    except (KeyError, ValueError, OSError) as err:
        print(f'rory sim: error: {err.args[0] if err.args else err}', file=sys.stderr)
        return 2
    return code


if __name__ == '__main__':
    sys.exit(main())
