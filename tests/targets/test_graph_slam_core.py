"""graph_slam's algorithm offline: odometry and scans from the simulator stepped synchronously,
no ROS.

The quality assertions live here: over each world's whole route (the trajectory of
``--driver internal``), the map assembled from the keyframes agrees with the ground-truth map,
the pose stays on the true path, office_small's loop closes at the door, and loop closures
pull an odometry-only front end back onto the path. Then the parts: SE(2) and the optimiser's
Jacobians, ICP and its corridor check, the grid, bad input, and a checkpoint of keyvars.yaml's
variables restoring the state exactly.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, replace
from functools import cache
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from graph_slam_core import (
    GraphSlam,
    GraphSlamConfig,
    OutOfOrderError,
    ScanOutcome,
)
from graph_slam_graph import Edge, EdgeKind, chi2, edge_errors, information, optimise
from graph_slam_grid import OccupancyCounts, rebuild, scan_in_map
from graph_slam_matcher import build_reference, estimate_normals, icp
from graph_slam_scan import ScanError, scan_to_points, thin_points
from graph_slam_se2 import between, compose, inverse, pose, transform_points
from rory_eval.metrics import MapScore, map_score, position_errors
from rory_runtime import codec
from sim.driver import CONTROL_RATE, RouteFollower
from sim.maps import OccupancyMap, ground_truth_map
from sim.sensors import LIDAR
from sim.simulation import TICK, Simulation
from sim.worlds import get_world

LASER = np.array([-0.064, 0.0, 0.0])  # the simulator's base_scan in base_link
KEYVARS = Path(__file__).resolve().parents[2] / 'targets' / 'graph_slam' / 'keyvars.yaml'


# -- recordings and runs ---------------------------------------------------------------------


@dataclass(frozen=True)
class Event:
    """One message as the simulator publishes it: odometry (odom frame) or a scan."""

    stamp_ns: int
    odometry: tuple[float, float, float] | None = None
    ranges: np.ndarray | None = None


@dataclass(frozen=True)
class Recording:
    """A route driven offline: the messages in publication order, and ground truth at 50 Hz."""

    events: list[Event]
    truth: list[tuple[float, float, float, float]]  # (t, x, y, yaw)


@cache
def drive(world_name: str, seed: int = 0) -> Recording:
    """The world's route as ``--driver internal`` drives it (same control law, same ticks),
    odometry before the scan of the same tick, as the bridge publishes them."""
    world = get_world(world_name)
    sim = Simulation(world, seed, depth=False)
    follower = RouteFollower(world.route)
    every = round(1.0 / (CONTROL_RATE * TICK))
    events: list[Event] = []
    truth = []
    while not follower.done:
        if sim.ticks % every == 0:
            p = sim.pose()
            sim.command(*follower.command(p.x, p.y, p.yaw))
        frame = sim.step()
        if frame.odom_due:
            o = sim.odometry
            events.append(Event(frame.stamp_ns, odometry=(o.x, o.y, o.yaw)))
            p = sim.pose()
            truth.append((frame.stamp_ns * 1e-9, p.x, p.y, p.yaw))
        if frame.scan is not None:
            events.append(Event(frame.stamp_ns, ranges=frame.scan.copy()))
    return Recording(events, truth)


def config_for(world_name: str, **changes: Any) -> GraphSlamConfig:
    """The node's defaults, started at the world's start pose (as with map_start_*)."""
    start = get_world(world_name).start
    return replace(GraphSlamConfig(map_start=(start.x, start.y, start.yaw),
                                   laser_pose=tuple(LASER)), **changes)


def feed(slam: GraphSlam, events: Iterable[Event]) -> list[ScanOutcome]:
    """Deliver messages as the node's callbacks do; the outcome of every scan processed."""
    outcomes = []
    for event in events:
        if event.odometry is not None:
            outcomes += slam.add_odometry(event.stamp_ns, *event.odometry)
        else:
            assert event.ranges is not None
            points = scan_to_points(event.ranges, LIDAR.angle_min, LIDAR.angle_increment,
                                    LIDAR.range_min, LIDAR.range_max, LASER)
            outcomes += slam.add_scan(event.stamp_ns, points)
    return outcomes


RESTORE_END_NS = 55_000_000_000  # test_keyvars_restore_the_graph_exactly replays up to 55 s


@dataclass(frozen=True)
class RestorePoint:
    """The run at the checkpoint (8/11 of the messages up to 55 s: at 40 s in real_room, after
    the first loop closures) and what it gave from there to 55 s."""

    checkpoint: bytes  # keyvars.yaml's variables through RORY's codec, at the cut
    loop_closures: int  # at the cut
    tail: list[Event]  # the messages after the cut, up to 55 s
    after: list[tuple[Any, ...]]  # _summary of what the tail gave
    hits: np.ndarray  # the grid's hits at 55 s
    edges: list[tuple[int, int, EdgeKind, np.ndarray]]  # at 55 s


@dataclass(frozen=True)
class RouteRun:
    """What a whole route gave."""

    slam: GraphSlam
    outcomes: list[ScanOutcome]
    errors: np.ndarray  # position error per scan (m)
    score: MapScore
    restore: RestorePoint


def estimated_map(slam: GraphSlam) -> OccupancyMap:
    grid = slam.grid
    return OccupancyMap(slam.occupancy(), grid.resolution, grid.origin_x, grid.origin_y)


@cache
def route_run(world_name: str, **changes: Any) -> RouteRun:
    rec = drive(world_name)
    slam = GraphSlam(config_for(world_name, **changes))
    # Fed in three parts, the same messages in the same order as at once: the restore test
    # checkpoints this run at the cut instead of driving its first 55 s again.
    end = sum(1 for e in rec.events if e.stamp_ns <= RESTORE_END_NS)
    cut = end * 8 // 11
    outcomes = feed(slam, rec.events[:cut])
    holder = SimpleNamespace(slam=slam)
    checkpoint = codec.encode_vars({p: _get(holder, p) for p in _keyvar_paths()})
    loop_closures = slam.loop_closure_count()
    tail_outcomes = feed(slam, rec.events[cut:end])
    restore = RestorePoint(checkpoint, loop_closures, rec.events[cut:end],
                           _summary(tail_outcomes), slam.grid.hits.copy(),
                           [(e.source, e.target, e.kind, e.measurement.copy())
                            for e in slam.edges])
    outcomes += tail_outcomes
    outcomes += feed(slam, rec.events[end:])
    assert [o.stamp_ns for o in outcomes] == [e.stamp_ns for e in rec.events
                                              if e.ranges is not None]
    assert all(o.pose is not None for o in outcomes)
    estimates = [(o.stamp_ns * 1e-9, float(o.pose[0]), float(o.pose[1]))
                 for o in outcomes if o.pose is not None]
    errors = position_errors(estimates, rec.truth)
    score = map_score(estimated_map(slam), ground_truth_map(get_world(world_name)), tolerance=1)
    return RouteRun(slam, outcomes, errors, score, restore)


# -- quality over the routes -----------------------------------------------------------------


@pytest.mark.parametrize(('world_name', 'min_iou', 'max_median'), [
    ('office_small', 0.85, 0.05),
    ('workshop', 0.85, 0.06),
    ('real_room', 0.85, 0.05),
])
def test_route_map_and_pose_against_ground_truth(world_name: str, min_iou: float,
                                                 max_median: float) -> None:
    run = route_run(world_name)
    assert run.score.agreement >= 0.95, run.score
    assert run.score.iou_occupied >= min_iou, run.score
    assert run.score.observed_fraction >= 0.5, run.score
    assert float(np.median(run.errors)) <= max_median
    assert float(run.errors.max()) <= 0.15
    assert sum(o.matched for o in run.outcomes) >= 0.99 * len(run.outcomes)
    # the graph: one keyframe per ~0.3 m or 0.3 rad, chained by scan-matched edges
    slam = run.slam
    chain = [e for e in slam.edges if e.kind is not EdgeKind.LOOP]
    assert [(e.source, e.target) for e in chain] == [(k, k + 1) for k in
                                                     range(len(slam.keyframes) - 1)]
    assert all(e.kind is EdgeKind.SCAN_MATCH for e in chain)
    route = get_world(world_name).route_length()
    assert route / 0.3 * 0.8 <= len(slam.keyframes) <= route / 0.3 * 1.6


@pytest.mark.parametrize('world_name', ['office_small', 'workshop', 'real_room'])
def test_odometry_alone_is_far_worse(world_name: str) -> None:
    slam_run = route_run(world_name)
    odometry = route_run(world_name, scan_matching=False, loop_closure=False)
    assert odometry.score.iou_occupied < slam_run.score.iou_occupied - 0.5
    assert float(np.median(odometry.errors)) > 4 * float(np.median(slam_run.errors))


def test_office_loop_closes_at_the_door() -> None:
    # The route goes through room D's door at (3.0, 6.1), around the desk island and back
    # through the door (sim/worlds.py): a keyframe there is linked to one from the first pass.
    run = route_run('office_small')
    keyframes = run.slam.keyframes
    loops = [e for e in run.slam.edges if e.kind is EdgeKind.LOOP]
    assert len(loops) >= 5
    at_door = [e for e in loops
               if all(math.hypot(keyframes[k].pose[0] - 3.0, keyframes[k].pose[1] - 6.1) < 1.0
                      for k in (e.source, e.target))
               and keyframes[e.target].travelled - keyframes[e.source].travelled > 8.0]
    assert at_door, 'no loop closure at the door of room D'
    # each loop edge agrees with the optimised graph (what the residual check enforces)
    residual = edge_errors(np.array([k.pose for k in keyframes]), loops)
    assert float(np.hypot(residual[:, 0], residual[:, 1]).max()) < 0.05
    optimised = [o for o in run.outcomes if o.optimisation is not None]
    assert optimised and all(o.optimisation.final_error <= o.optimisation.initial_error + 1e-9
                             for o in optimised if o.optimisation is not None)


def test_loop_closures_pull_odometry_drift_back() -> None:
    # With the front end off (keyframes at odometry poses), real_room's two laps drift by more
    # than a metre; loop closures against the first lap bring the end back to centimetres.
    drift = route_run('real_room', scan_matching=False, loop_closure=False)
    closed = route_run('real_room', scan_matching=False)
    assert float(drift.errors[-1]) > 0.8
    assert closed.slam.loop_closure_count() >= 20
    assert float(closed.errors[-1]) < 0.1
    assert closed.score.iou_occupied > drift.score.iou_occupied + 0.3


# -- SE(2) and the pose graph ----------------------------------------------------------------


def test_se2_compose_between_inverse() -> None:
    a, b = pose(1.0, 2.0, 0.7), pose(-0.5, 0.3, -2.9)
    assert np.allclose(compose(a, between(a, b)), b)
    assert np.allclose(compose(a, inverse(a)), 0.0, atol=1e-12)
    pts = np.array([[1.0, 0.0], [0.0, 2.0]])
    assert np.allclose(transform_points(compose(a, b), pts),
                       transform_points(a, transform_points(b, pts)))
    assert compose(pose(0, 0, 3.0), pose(0, 0, 0.5))[2] == pytest.approx(3.5 - 2 * math.pi)


def _square(noise: float, bias: float,
            rng: np.random.Generator) -> tuple[np.ndarray, list[Edge]]:
    """Truth around a 4 x 4 m square (1 m steps), odometry edges with a heading bias and
    noise, and one loop edge from the last pose back to the first."""
    truth = [pose(0, 0, 0)]
    for k in range(15):
        turn = math.pi / 2 if k % 4 == 3 else 0.0
        truth.append(compose(truth[-1], pose(1.0, 0.0, turn)))
    edges = []
    for k in range(15):
        z = between(truth[k], truth[k + 1]) + np.array([*rng.normal(0, noise, 2), bias])
        edges.append(Edge(k, k + 1, z, information(0.1, 0.05), EdgeKind.ODOMETRY))
    edges.append(Edge(0, 15, between(truth[0], truth[15]), information(0.02, 0.01),
                      EdgeKind.LOOP))
    return np.array(truth), edges


def test_optimiser_closes_a_drifting_square() -> None:
    truth, edges = _square(0.01, 0.03, np.random.default_rng(0))
    dead_reckoning = [truth[0]]
    for e in edges[:-1]:
        dead_reckoning.append(compose(dead_reckoning[-1], e.measurement))
    start = np.array(dead_reckoning)
    assert np.hypot(*(start[15, :2] - truth[15, :2])) > 0.8  # the drift to undo
    optimised, result = optimise(start, edges)
    assert result.final_error < 0.01 * result.initial_error
    assert np.array_equal(optimised[0], start[0])  # the gauge stays put
    assert float(np.hypot(*(optimised[:, :2] - truth[:, :2]).T).max()) < 0.15
    assert float(chi2(optimised, edges).sum()) == pytest.approx(result.final_error)


def test_one_gauss_newton_step_converges_quadratically() -> None:
    # Consistent edges, poses off by ~1 mm: with the right Jacobians one step leaves an error
    # of the order of the perturbation squared (a wrong derivative leaves it first order).
    rng = np.random.default_rng(1)
    truth, edges = _square(0.0, 0.0, rng)
    start = truth + np.column_stack([rng.normal(0, 1e-3, (16, 2)), rng.normal(0, 1e-3, 16)])
    start[0] = truth[0]
    optimised, result = optimise(start, edges, iterations=1)
    assert result.iterations == 1 and result.initial_error > 1e-4
    assert result.final_error < 1e-5 * result.initial_error
    assert np.allclose(optimised, truth, atol=1e-5)


# -- scan matching ---------------------------------------------------------------------------


def _true_scan(world_name: str, x: float, y: float, yaw: float) -> np.ndarray:
    sim = Simulation(get_world(world_name), 0, depth=False)
    ranges = sim.lidar.measure(x, y, yaw)
    return scan_to_points(ranges, LIDAR.angle_min, LIDAR.angle_increment, LIDAR.range_min,
                          LIDAR.range_max, LASER)


def _reference_from(points: np.ndarray, at: np.ndarray) -> Any:
    normals, valid = estimate_normals(points)
    c, s = math.cos(at[2]), math.sin(at[2])
    return build_reference(transform_points(at, points[valid]),
                           normals[valid] @ np.array([[c, -s], [s, c]]).T)


def test_icp_recovers_an_offset_in_the_office() -> None:
    truth_a, truth_b = pose(2.0, 4.25, 0.0), pose(2.3, 4.3, 0.1)
    reference = _reference_from(_true_scan('office_small', *truth_a), truth_a)
    scan = thin_points(_true_scan('office_small', *truth_b), 0.025)
    match = icp(reference, scan, truth_b + np.array([0.08, -0.06, 0.04]))
    assert np.hypot(*(match.pose[:2] - truth_b[:2])) < 0.01
    assert abs(match.pose[2] - truth_b[2]) < 0.005
    assert match.inliers > 0.75


def test_a_corridor_does_not_pin_the_pose_down() -> None:
    # Two long parallel walls: ICP fits, but nothing fixes the position along them; a room's
    # corner does. The loop-closure check refuses the first.
    along = np.linspace(-6, 6, 300)
    corridor = np.concatenate([np.column_stack([along, np.full(300, 0.75)]),
                               np.column_stack([along, np.full(300, -0.75)])])
    normals = np.concatenate([np.tile([0.0, -1.0], (300, 1)), np.tile([0.0, 1.0], (300, 1))])
    reference = build_reference(corridor, normals)
    scan = corridor[np.abs(corridor[:, 0]) < 4][::3]
    match = icp(reference, scan, pose(0.1, 0.05, 0.0))
    assert match.inliers > 0.95
    assert match.weakest_translation < GraphSlamConfig().loop_min_constraint / 10
    corner = np.concatenate([corridor[:300], np.column_stack([np.full(150, 2.0),
                                                              np.linspace(-0.75, 0.75, 150)])])
    corner_normals = np.concatenate([normals[:300], np.tile([-1.0, 0.0], (150, 1))])
    boxed = icp(build_reference(corner, corner_normals), corner[::3], pose(0.05, 0.05, 0.0))
    assert boxed.weakest_translation > 2 * GraphSlamConfig().loop_min_constraint
    assert np.hypot(*boxed.pose[:2]) < 1e-3


def test_normals_of_a_wall_and_a_corner() -> None:
    wall = np.column_stack([np.linspace(0, 1, 21), np.full(21, 2.0)])
    normals, valid = estimate_normals(wall)
    assert valid[2:-2].all()
    assert np.allclose(np.abs(normals[valid, 1]), 1.0)
    corner = np.concatenate([wall, np.column_stack([np.full(20, 1.0), np.linspace(1.95, 1.0, 20)])])
    normals, valid = estimate_normals(corner)
    assert not valid[20] and valid[17] and valid[24]  # the corner point has no normal
    assert np.allclose(np.abs(normals[24]), [1.0, 0.0])


# -- the grid --------------------------------------------------------------------------------


def test_grid_rebuilt_equals_grid_added_one_by_one() -> None:
    run = route_run('real_room')
    slam = run.slam
    scans = [(k.pose, k.points) for k in slam.keyframes]
    rebuilt = rebuild(0.05, scans, LASER[:2], slam.config.hit_depth)
    incremental = OccupancyCounts.empty(0.05)
    for p, pts in scans:
        incremental.add_scans([scan_in_map(p, LASER[:2], pts)], slam.config.hit_depth)
    rows, cols = rebuilt.shape
    dr = round((rebuilt.origin_y - incremental.origin_y) / 0.05)
    dc = round((rebuilt.origin_x - incremental.origin_x) / 0.05)
    assert np.array_equal(incremental.hits[dr:dr + rows, dc:dc + cols], rebuilt.hits)
    assert np.array_equal(incremental.passes[dr:dr + rows, dc:dc + cols], rebuilt.passes)
    assert incremental.hits.sum() == rebuilt.hits.sum()


def test_grid_counts_a_wall_in_the_wall_cell_and_grows() -> None:
    grid = OccupancyCounts.empty(0.05)
    # a wall face exactly on a cell boundary (x = 2.0), seen head-on from the origin
    ends = np.column_stack([np.full(11, 2.0), np.linspace(-0.25, 0.25, 11)])
    grid.add_scans([(np.zeros(2), ends)], hit_depth=0.02)
    row = math.floor((0.0 - grid.origin_y) / 0.05)
    wall_col = math.floor((2.0 - grid.origin_x) / 0.05)
    assert grid.hits[row, wall_col] == 1 and grid.hits[row, wall_col - 1] == 0
    assert grid.passes[row, wall_col - 1] >= 1 and grid.passes[row, wall_col] == 0
    occupancy = grid.occupancy(0.6, -0.4, 0.65, 0.25)
    assert occupancy[row, wall_col] == occupancy[row, wall_col - 1] == -1  # one beam: undecided
    grid.add_scans([(np.zeros(2), ends), (np.zeros(2), ends)], hit_depth=0.02)
    occupancy = grid.occupancy(0.6, -0.4, 0.65, 0.25)
    assert occupancy[row, wall_col] == 100 and occupancy[row, wall_col - 1] == 0
    assert occupancy[row + 20, wall_col] == -1  # never seen
    shape = grid.shape
    grid.add_scans([(np.zeros(2), np.array([[-7.0, 5.0]]))], hit_depth=0.02)
    assert grid.shape[0] > shape[0] and grid.shape[1] > shape[1]
    assert grid.origin_x <= -7.0 and grid.hits.sum() == 34


# -- bad input and odometry ------------------------------------------------------------------


def test_scan_conversion_drops_bad_beams_and_refuses_bad_geometry() -> None:
    ranges = np.array([1.0, np.nan, np.inf, -np.inf, 0.05, 20.0, 2.0])
    points = scan_to_points(ranges, 0.0, math.pi / 2, 0.12, 10.0, np.zeros(3))
    assert points.shape == (2, 2)
    assert np.allclose(points, [[1.0, 0.0], [-2.0, 0.0]], atol=1e-6)  # beam 6: 3 pi
    for bad in ({'ranges': []}, {'angle_increment': 0.0}, {'angle_min': math.nan}):
        args = {'ranges': [1.0], 'angle_min': 0.0, 'angle_increment': 0.1, **bad}
        with pytest.raises(ScanError):
            scan_to_points(args['ranges'], args['angle_min'], args['angle_increment'], 0.1,
                           10.0, np.zeros(3))


def test_scans_wait_for_their_odometry_and_bad_order_is_refused() -> None:
    slam = GraphSlam(config_for('real_room', max_waiting_scans=3))
    points = _true_scan('real_room', 0.8, 0.8, 0.0)
    assert slam.add_scan(100_000_000, points) == []  # no odometry yet: it waits
    assert slam.pose is None and len(slam.waiting_scans) == 1
    with pytest.raises(OutOfOrderError):
        slam.add_scan(100_000_000, points)  # the same stamp again
    (first,) = slam.add_odometry(100_000_000, 0.0, 0.0, 0.0)  # its odometry: processed
    assert first.stamp_ns == 100_000_000 and first.keyframe == 0
    assert first.pose is not None and np.allclose(first.pose, [0.8, 0.8, 0.0])
    with pytest.raises(OutOfOrderError):
        slam.add_odometry(100_000_000, 5.0, 0.0, 0.0)
    # three scans ahead of the odometry wait; a fourth pushes the oldest out
    for k in range(2, 5):
        assert slam.add_scan(k * 100_000_000, points) == []
    (dropped,) = slam.add_scan(500_000_000, points)
    assert dropped.stamp_ns == 200_000_000 and dropped.pose is None
    assert 'no odometry up to its stamp' in dropped.skipped
    done = slam.add_odometry(420_000_000, 0.0, 0.0, 0.0)
    assert [o.stamp_ns for o in done] == [300_000_000, 400_000_000]
    assert [s for s, _ in slam.waiting_scans] == [500_000_000]
    # a hole in the odometry: a scan near one end of it is used, one far from both skipped
    assert slam.add_scan(1_000_000_000, points) == []
    near, far = slam.add_odometry(2_000_000_000, 0.0, 0.0, 0.0)
    assert near.stamp_ns == 500_000_000 and near.pose is not None
    assert far.pose is None and far.skipped == 'nearest odometry is 0.580 s from the scan'
    assert len(slam.keyframes) == 1 and not slam.waiting_scans


def test_scans_ahead_of_their_odometry_give_the_same_map() -> None:
    # After a stall the executor may hand over a burst of scans before the odometry of the
    # same period: the scans wait, and the result is the same as in publication order.
    events = [e for e in drive('office_small').events if e.stamp_ns <= 20_000_000_000]
    scans_first = []
    for k in range(0, len(events), 150):  # 3 s bursts, each scan before its odometry
        burst = events[k:k + 150]
        scans_first += [e for e in burst if e.ranges is not None]
        scans_first += [e for e in burst if e.ranges is None]
    in_order, reordered = GraphSlam(config_for('office_small')), GraphSlam(
        config_for('office_small'))
    a, b = feed(in_order, events), feed(reordered, scans_first)
    assert [(o.stamp_ns, tuple(o.pose)) for o in a if o.pose is not None] == [
        (o.stamp_ns, tuple(o.pose)) for o in b if o.pose is not None]
    assert np.array_equal(in_order.grid.hits, reordered.grid.hits)


def test_odometry_is_interpolated_at_the_scan_stamp() -> None:
    slam = GraphSlam(GraphSlamConfig())
    slam.add_odometry(1_000_000_000, 0.0, 0.0, 3.1)
    slam.add_odometry(1_020_000_000, 0.02, 0.0, -3.1)  # across the ±pi seam
    mid = slam.odometry_at(1_010_000_000)
    assert mid[0] == pytest.approx(0.01)
    assert abs(mid[2]) == pytest.approx(math.pi, abs=1e-9)
    assert slam.odometry_at(1_100_000_000)[0] == pytest.approx(0.02)  # newest, within the gap


# -- checkpoint and restore ------------------------------------------------------------------


def _keyvar_paths() -> list[str]:
    nodes = yaml.safe_load(KEYVARS.read_text())['nodes']
    assert len(nodes) == 1 and nodes[0]['class'] == 'GraphSlamNode'
    return list(nodes[0]['vars'])


def _get(root: object, path: str) -> Any:
    for part in path.split('.'):
        root = getattr(root, part)
    return root


def _set(root: object, path: str, value: Any) -> None:
    *parents, last = path.split('.')
    for part in parents:
        root = getattr(root, part)
    setattr(root, last, value)


def _summary(outcomes: list[ScanOutcome]) -> list[tuple[Any, ...]]:
    return [(o.stamp_ns, tuple(o.pose if o.pose is not None else ()), o.matched, o.keyframe,
             tuple((c.source, c.target) for c in o.loop_closures)) for o in outcomes]


def test_keyvars_restore_the_graph_exactly() -> None:
    # A checkpoint is keyvars.yaml's variables through RORY's codec. Restored into a fresh
    # node mid-route (after loop closures), replaying the rest must give identical poses,
    # keyframes, edges and grid: the ICP reference cache is rebuilt from the keyframes.
    # The original is real_room's route run, checkpointed at 40 s (RestorePoint), compared
    # at 55 s.
    original = route_run('real_room').restore
    assert original.loop_closures > 0  # the first loop closures come from 34 s
    cfg = config_for('real_room')
    restored = SimpleNamespace(slam=GraphSlam(cfg))
    for path, value in codec.decode_vars(original.checkpoint).items():
        _set(restored, path, value)
    tail = original.tail
    after_original = original.after
    after_restored = _summary(feed(restored.slam, tail))
    assert after_restored == after_original
    assert np.array_equal(restored.slam.grid.hits, original.hits)
    assert len(restored.slam.edges) == len(original.edges)
    for a, (source, target, kind, measurement) in zip(restored.slam.edges, original.edges,
                                                       strict=True):
        assert (a.source, a.target, a.kind) == (source, target, kind)
        assert np.array_equal(a.measurement, measurement)
    # without the checkpoint a fresh node ends up elsewhere
    fresh = GraphSlam(cfg)
    assert _summary(feed(fresh, tail)) != after_original
