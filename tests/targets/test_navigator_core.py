"""targets/navigator offline: costmap, A*, pose tracking and whole runs in the simulator.

No ROS: ``sim.simulation.Simulation`` is stepped synchronously, its odometry, scans and a noisy,
late localization (ground truth + noise at 10 Hz, 40 ms late, as AMCL delivers it) are fed to
``NavigatorCore``, and its commands drive the robot. Collisions are the simulator's.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from navigator_controller import ControllerParams, arc_collides
from navigator_core import Command, NavigatorCore, NavigatorParams, Status
from navigator_costmap import GridMap, InflationParams, build_costmap, distance_transform
from navigator_geometry import Pose2D, compose, path_length
from navigator_localization import PoseTracker
from navigator_planner import astar, cells_to_points
from rory_runtime.codec import decode_vars, encode_vars
from sim.maps import ground_truth_map
from sim.simulation import Simulation
from sim.worlds import World, get_world

KEYVARS = Path(__file__).resolve().parents[2] / 'targets' / 'navigator' / 'keyvars.yaml'
ALL_GOALS = [(w, g) for w in ('office_small', 'workshop', 'real_room')
             for g in get_world(w).goals]


def grid_of(world: World) -> GridMap:
    truth = ground_truth_map(world)
    return GridMap(truth.data, truth.resolution, truth.origin_x, truth.origin_y, 0)


def without(world_name: str, *names: str) -> World:
    """The world minus some obstacles (for a map that lacks them)."""
    world = get_world(world_name)
    return dataclasses.replace(
        world, obstacles=tuple(o for o in world.obstacles if o.name not in names))


@dataclass
class Drive:
    """What an offline run left."""

    core: NavigatorCore
    sim: Simulation
    statuses: list[Status]
    reached_at: float | None
    estimate_errors: list[float]  # navigator's pose vs ground truth, per control step
    events: list[tuple[str, tuple[Any, ...], Any]] = field(default_factory=list)


def drive(world_name: str, goal_name: str, *, seed: int = 0, map_world: World | None = None,
          goal: Pose2D | None = None, time_limit: float = 90.0, noise: float = 0.02,
          localization_every: int = 1, record: bool = False,
          params: NavigatorParams | None = None,
          new_goal: tuple[float, Pose2D] | None = None) -> Drive:
    """Navigate in a synchronous simulation until REACHED/FAILED (+1 s) or the time limit.

    ``localization_every`` n: only every n-th localization pose is delivered (odometry alone
    carries the pose in between). ``record`` keeps every input and its output, in order.
    ``new_goal`` (t, goal): a second goal sent at sim time t.
    """
    world = get_world(world_name)
    sim = Simulation(world, seed, depth=False)
    spec = sim.lidar.spec
    core = NavigatorCore(params or NavigatorParams())
    target = goal or Pose2D(*dataclasses.astuple(world.goals[goal_name]))
    events: list[tuple[str, tuple[Any, ...], Any]] = []

    def feed(kind: str, *args: Any) -> Any:
        out = getattr(core, kind)(*args)
        if record:
            events.append((kind, args, out))
        return out

    feed('on_map', grid_of(map_world or world))
    feed('on_goal', 0, target)
    rng = np.random.default_rng(seed + 100)
    pending: list[tuple[int, int, Pose2D]] = []
    statuses = [core.status]
    errors: list[float] = []
    reached_at: float | None = None
    scans = 0
    while sim.time < time_limit:
        frame = sim.step()
        if new_goal is not None and sim.time >= new_goal[0]:
            feed('on_goal', frame.stamp_ns, new_goal[1])
            new_goal = None
        if frame.odom_due:
            o = sim.odometry
            command = feed('on_odometry', frame.stamp_ns, Pose2D(o.x, o.y, o.yaw))
            if command is not None:
                sim.command(command.linear, command.angular)
                estimate, truth = core.pose(), sim.pose()
                if estimate is not None:
                    errors.append(math.hypot(estimate.x - truth.x, estimate.y - truth.y))
        if frame.scan is not None:
            feed('on_scan', frame.stamp_ns, frame.scan, spec.angle_min, spec.angle_increment,
                 spec.range_min, spec.range_max)
            scans += 1
            p = sim.pose()
            noisy = Pose2D(p.x + rng.normal(0, noise), p.y + rng.normal(0, noise),
                           p.yaw + rng.normal(0, noise / 2))
            if scans == 1 or scans % localization_every == 0:
                pending.append((sim.ticks + 4, frame.stamp_ns, noisy))  # 40 ms late
        while pending and pending[0][0] <= sim.ticks:
            _, stamp, pose = pending.pop(0)
            feed('on_localization', stamp, pose)
        core.notes.clear()
        if core.status != statuses[-1]:
            statuses.append(core.status)
        if core.status in (Status.REACHED, Status.FAILED):
            reached_at = sim.time if reached_at is None else reached_at
            if sim.time > reached_at + 1.0:
                break
    return Drive(core, sim, statuses, reached_at, errors, events)


# -- costmap and planner -----------------------------------------------------------------------

def test_distance_transform_is_exact_within_its_range() -> None:
    rng = np.random.default_rng(3)
    obstacles = rng.random((40, 50)) < 0.02
    got = distance_transform(obstacles, 8)
    rows, cols = np.nonzero(obstacles)
    rr, cc = np.mgrid[0:40, 0:50]
    brute = np.hypot(rr[..., None] - rows, cc[..., None] - cols).min(axis=-1)
    expected = np.minimum(brute, 9.0)
    assert np.allclose(got, expected, atol=1e-5)


@pytest.mark.parametrize('world_name', ['office_small', 'workshop', 'real_room'])
def test_plans_keep_the_footprint_clear_of_the_true_geometry(world_name: str) -> None:
    world = get_world(world_name)
    costmap = build_costmap(grid_of(world), InflationParams())
    for goal in world.goals.values():
        cells = astar(costmap, costmap.cell_of(world.start.x, world.start.y),
                      costmap.cell_of(goal.x, goal.y))
        assert cells is not None
        points = cells_to_points(costmap, cells)
        clearance = world.clearance(points[:, 0], points[:, 1])
        assert clearance.min() > 0.205  # the footprint circle never touches anything
        straight = math.dist((world.start.x, world.start.y), (goal.x, goal.y))
        assert straight <= path_length(points) < 1.6 * straight + 2.0


def test_behind_the_pillars_the_plan_goes_around_them() -> None:
    world = get_world('workshop')
    costmap = build_costmap(grid_of(world), InflationParams())
    goal = world.goals['behind_pillars']
    straight = np.linspace((world.start.x, world.start.y), (goal.x, goal.y), 200)
    assert costmap.lethal_at(straight).any()  # the straight line runs into a pillar
    cells = astar(costmap, costmap.cell_of(world.start.x, world.start.y),
                  costmap.cell_of(goal.x, goal.y))
    assert cells is not None and not costmap.lethal_at(cells_to_points(costmap, cells)).any()
    # The same inputs, the same plan.
    assert astar(costmap, cells[0], cells[-1]) == cells


def test_no_path_into_a_closed_space() -> None:
    world = get_world('real_room')
    costmap = build_costmap(grid_of(world), InflationParams())
    inside_obstacle = costmap.cell_of(2.5, 2.0)
    assert costmap.lethal[inside_obstacle]
    assert astar(costmap, costmap.cell_of(0.8, 0.8), inside_obstacle) is None


# -- pose between localization updates ---------------------------------------------------------

def test_the_correction_follows_drifting_odometry() -> None:
    # Odometry that is off by a fixed transform and drifts: the tracker's pose must equal the
    # truth at the localization stamp and follow the odometry's relative motion after it.
    offset = Pose2D(0.7, -0.3, 0.4)
    tracker = PoseTracker()
    truth = [Pose2D(1.0 + 0.01 * k, 2.0 + 0.002 * k * k / 10, 0.01 * k) for k in range(100)]
    for k, pose in enumerate(truth):
        drift = Pose2D(0.001 * k, 0.0, 0.0005 * k)
        tracker.add_odometry(k * 20_000_000, compose(compose(offset, pose), drift))
        if k == 60:
            # a localization pose for the stamp 10 samples back, arriving late
            assert tracker.add_localization(50 * 20_000_000, truth[50])
    estimate, odometry = tracker.pose(), tracker.latest_odom
    assert estimate is not None and odometry is not None
    # What is left is the drift since the stamp used (~5 cm), not the odometry's offset.
    assert math.hypot(estimate.x - truth[-1].x, estimate.y - truth[-1].y) < 0.08
    assert math.hypot(odometry.x - truth[-1].x, odometry.y - truth[-1].y) > 0.5
    # An older pose than the one used is refused; exactly at a sample it is exact.
    assert not tracker.add_localization(40 * 20_000_000, truth[40])
    assert tracker.add_localization(99 * 20_000_000, truth[99])
    estimate = tracker.pose()
    assert estimate is not None
    assert math.hypot(estimate.x - truth[99].x, estimate.y - truth[99].y) < 1e-9


def test_rotating_in_place_is_never_a_collision_but_driving_into_a_wall_is() -> None:
    params = ControllerParams()
    wall = np.column_stack([np.full(20, 0.35), np.linspace(-0.5, 0.5, 20)])
    assert arc_collides(0.3, 0.0, wall, params)
    assert not arc_collides(0.0, 1.0, wall, params)
    assert not arc_collides(-0.1, 0.0, wall, params)


# -- whole runs --------------------------------------------------------------------------------

@pytest.mark.parametrize(('world_name', 'goal_name'), ALL_GOALS)
def test_every_goal_is_reached_without_collision(world_name: str, goal_name: str) -> None:
    run = drive(world_name, goal_name)
    goal = get_world(world_name).goals[goal_name]
    pose = run.sim.pose()
    assert run.core.status == Status.REACHED, run.statuses
    assert run.sim.collisions.events == []
    assert math.hypot(pose.x - goal.x, pose.y - goal.y) < 0.15
    assert abs(math.remainder(pose.yaw - goal.yaw, 2 * math.pi)) < 0.15
    # It drives the plan: no detours beyond the A* length, at a sensible speed.
    assert run.sim.distance < 1.1 * run.core.first_plan_length
    assert run.reached_at is not None
    assert run.reached_at < run.core.first_plan_length / 0.3 + 5.0
    assert run.core.total_recoveries == 0


def test_drifting_odometry_is_corrected_by_localization() -> None:
    # In the workshop the odometry is 0.7 m and 7 degrees off by the goal. Given a localization
    # pose only every 2 s, the navigator's pose follows the odometry in between and each pose
    # removes the drift: it stays within a few centimetres all the way.
    run = drive('workshop', 'behind_pillars', localization_every=20)
    assert run.core.status == Status.REACHED and run.sim.collisions.events == []
    odometry_error, _ = run.sim.odometry_error()
    assert odometry_error > 0.5
    errors = np.array(run.estimate_errors)
    assert float(np.median(errors)) < 0.05 and float(errors.max()) < 0.1


def test_an_obstacle_missing_from_the_map_is_seen_and_planned_around() -> None:
    # The map lacks all nine pillars: the first plan runs through them, the scan sees them.
    pillars = [f'pillar_{k}' for k in range(1, 10)]
    run = drive('workshop', 'behind_pillars', map_world=without('workshop', *pillars))
    assert run.core.status == Status.REACHED, run.statuses
    assert run.sim.collisions.events == []
    assert run.core.plans_made >= 2
    assert len(run.core.seen_cells) > 0


def test_a_new_goal_on_the_way_is_planned_to_and_reached() -> None:
    world = get_world('office_small')
    second = world.goals['open_office']
    run = drive('office_small', 'storage', new_goal=(8.0, Pose2D(second.x, second.y, second.yaw)))
    assert run.core.status == Status.REACHED and run.core.plans_made == 2
    assert run.core.goal == Pose2D(second.x, second.y, second.yaw)
    pose = run.sim.pose()
    assert math.hypot(pose.x - second.x, pose.y - second.y) < 0.15
    assert run.sim.collisions.events == []


def test_an_unreachable_goal_fails_after_recoveries_and_stops() -> None:
    # A goal inside the obstacle in the middle of the room: no path, recoveries, FAILED.
    run = drive('real_room', '', goal=Pose2D(2.5, 2.0, 0.0), time_limit=60.0)
    assert run.core.status == Status.FAILED
    assert Status.RECOVERING in run.statuses
    assert run.core.total_recoveries == NavigatorParams().max_recoveries + 1
    assert run.sim.collisions.events == []
    v, w, _ = run.sim.body_velocity()
    assert abs(v) < 0.01 and abs(w) < 0.01


def test_bad_scans_and_a_repeated_goal_change_nothing() -> None:
    core = NavigatorCore(NavigatorParams())
    core.on_odometry(0, Pose2D(0.0, 0.0, 0.0))
    nan_scan = np.full(360, np.nan, dtype=np.float32)
    assert core.on_scan(0, nan_scan, -math.pi, 2 * math.pi / 360, 0.12, 10.0) == 0
    inf_scan = np.full(360, np.inf, dtype=np.float32)
    assert core.on_scan(0, inf_scan, -math.pi, 2 * math.pi / 360, 0.12, 10.0) == 0
    assert core.on_scan(0, np.zeros(0, np.float32), -math.pi, 0.01, 0.12, 10.0) == 0
    assert core.on_goal(5, Pose2D(1.0, 2.0, 0.0))
    assert not core.on_goal(5, Pose2D(1.0, 2.0, 0.0))  # the latched goal delivered again
    grid = grid_of(get_world('real_room'))
    assert core.on_map(grid)
    assert not core.on_map(dataclasses.replace(grid, data=grid.data.copy()))
    # No localization yet: no command, and no crash.
    assert core.on_odometry(100_000_000, Pose2D(0.0, 0.0, 0.0)) is None
    assert core.status == Status.PLANNING


# -- state: what keyvars.yaml lists is all a restart loses -------------------------------------

def _keyvar_paths() -> list[str]:
    spec = yaml.safe_load(KEYVARS.read_text())
    (node,) = spec['nodes']
    return list(node['vars'])


def _get(obj: Any, path: str) -> Any:
    for name in path.split('.'):
        obj = getattr(obj, name)
    return obj


def _set(obj: Any, path: str, value: Any) -> None:
    *parents, last = path.split('.')
    for name in parents:
        obj = getattr(obj, name)
    setattr(obj, last, value)


def test_restoring_the_key_variables_mid_run_continues_exactly() -> None:
    """A fresh navigator given only the key variables, through RORY's checkpoint codec, and
    then the same messages sends exactly the same commands as the one that never stopped."""
    paths = _keyvar_paths()
    assert all(p.startswith('core.') for p in paths)
    pillars = [f'pillar_{k}' for k in range(1, 10)]
    reference = drive('workshop', 'behind_pillars', record=True, time_limit=40.0,
                      map_world=without('workshop', *pillars))
    assert reference.core.status == Status.REACHED
    assert reference.core.plans_made >= 2  # the restore point lies in a run with a replan
    # Replay from the start up to several cut points; restore there; continue.
    for cut in (len(reference.events) // 5, len(reference.events) // 2):
        original = NavigatorCore(NavigatorParams())
        for kind, args, _ in reference.events[:cut]:
            getattr(original, kind)(*args)
        checkpoint = encode_vars({p: _get(original, p.removeprefix('core.')) for p in paths})
        restored = NavigatorCore(NavigatorParams())
        for path, value in decode_vars(checkpoint).items():
            _set(restored, path.removeprefix('core.'), value)
        for kind, args, expected in reference.events[cut:]:
            got = getattr(restored, kind)(*args)
            if isinstance(expected, Command):
                assert got == expected, (kind, args[0])
            else:
                assert got == expected
        assert restored.status == reference.core.status
        assert np.array_equal(restored.plan, reference.core.plan)


def test_node_logs_core_notes_of_every_severity_from_one_place(ros_domain: int) -> None:
    # rclpy refuses a logging call site whose severity changes between calls; the node
    # relays notes of all levels (a run of 'no path' recoveries crashed it once).
    import rclpy
    from rclpy.context import Context

    import navigator_node

    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    try:
        node = navigator_node.Navigator(context=context)
        for level in ('info', 'warn', 'error', 'info', 'warn'):
            node.core.notes.append((level, f'a {level} note'))
            node._after()
        node.destroy_node()
    finally:
        context.try_shutdown()


def test_odometry_at_a_sample_stamp_does_not_depend_on_later_odometry() -> None:
    samples = [(k * 20, Pose2D(0.1 * k + 0.013, 0.2 * k, 1.29 + 0.0137 * k)) for k in range(8)]
    for k in range(7):
        early, late = PoseTracker(), PoseTracker()
        for stamp, pose in samples[:k + 1]:
            early.add_odometry(stamp, pose)
        for stamp, pose in samples:
            late.add_odometry(stamp, pose)
        assert late.odom_at(k * 20) == early.odom_at(k * 20) == samples[k][1]
