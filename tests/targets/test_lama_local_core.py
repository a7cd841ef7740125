"""lama_local offline: the matcher's parts, and whole routes against the simulator's ground truth.

No ROS: ``sim.simulation.Simulation`` driven by the route follower gives scans and odometry
exactly as the ROS bridge would publish them (same stamps, same noise for a seed).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from lama_local_localizer import LamaConfig, LamaLocalizer, PoseEstimate, ScanSkipped
from lama_local_matcher import DistanceMap, MatcherConfig, match
from lama_local_scan import scan_points
from planar_geometry import wrap_angle
from planar_map import GridMap
from rory_eval.metrics import position_errors
from rory_runtime import codec
from sim.driver import CONTROL_RATE, RouteFollower
from sim.maps import ground_truth_map
from sim.sensors import LIDAR
from sim.simulation import TICK, Simulation
from sim.worlds import Pose2D, get_world

KEYVARS = Path(__file__).resolve().parents[2] / 'targets' / 'lama_local' / 'keyvars.yaml'
START_COV = np.diag([0.25, 0.25, (math.pi / 12) ** 2])  # the node's defaults
LASER = (-0.064, 0.0, 0.0)


# -- a route's sensor stream, offline ----------------------------------------------------------

@dataclass(frozen=True)
class Stream:
    """What the robot's sensors said along a route, in publishing order, and ground truth."""

    events: list[tuple[Any, ...]]  # ('odom', ns, x, y, yaw) or ('scan', ns, ranges)
    truth: list[tuple[float, float, float, float]]  # (t, x, y, yaw) at 50 Hz


@cache
def route_stream(world_name: str, seed: int = 0, duration: float | None = None) -> Stream:
    """Drive the world's route synchronously; odometry at 50 Hz, scans at 10 Hz."""
    world = get_world(world_name)
    sim = Simulation(world, seed, depth=False)
    follower = RouteFollower(world.route)
    every = round(1.0 / (CONTROL_RATE * TICK))
    events: list[tuple[Any, ...]] = []
    truth: list[tuple[float, float, float, float]] = []
    while not follower.done and (duration is None or sim.time < duration):
        if sim.ticks % every == 0:
            p = sim.pose()
            sim.command(*follower.command(p.x, p.y, p.yaw))
        frame = sim.step()
        if frame.odom_due:  # the bridge publishes odometry before the scan of the same tick
            o = sim.odometry
            events.append(('odom', frame.stamp_ns, o.x, o.y, o.yaw))
            p = sim.pose()
            truth.append((frame.stamp_ns / 1e9, p.x, p.y, p.yaw))
        if frame.scan is not None:
            events.append(('scan', frame.stamp_ns, frame.scan))
    return Stream(events, truth)


def world_grid(world_name: str) -> GridMap:
    g = ground_truth_map(get_world(world_name))
    return GridMap(g.data.copy(), g.resolution, g.origin_x, g.origin_y)


def make_localizer(world_name: str, config: LamaConfig | None = None,
                   offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> LamaLocalizer:
    s = get_world(world_name).start
    loc = LamaLocalizer(config or LamaConfig(),
                        (s.x + offset[0], s.y + offset[1], s.yaw + offset[2]), START_COV)
    loc.set_map(world_grid(world_name))
    return loc


def feed(loc: LamaLocalizer, events: list[tuple[Any, ...]]) -> Iterator[PoseEstimate]:
    """Play events into the localizer; one estimate per scan."""
    for event in events:
        if event[0] == 'odom':
            loc.add_odometry(event[1], event[2:5])
        else:
            yield loc.process_scan(event[1], event[2], LIDAR.angle_min, LIDAR.angle_increment,
                                   LIDAR.range_min, LIDAR.range_max)


def errors_of(estimates: list[PoseEstimate],
              truth: list[tuple[float, float, float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Position errors (m) and yaw errors (rad) against ground truth."""
    est = [(e.stamp_ns / 1e9, *e.pose) for e in estimates]
    position = position_errors([e[:3] for e in est], truth)
    t = np.array([r[0] for r in truth])
    yaw = np.unwrap([r[3] for r in truth])
    arr = np.array(est)
    yaw_err = np.abs((arr[:, 3] - np.interp(arr[:, 0], t, yaw) + np.pi) % (2 * np.pi) - np.pi)
    return position, yaw_err


def scan_at(world_name: str, pose: Pose2D) -> np.ndarray:
    sim = Simulation(get_world(world_name), 0, depth=False, start=pose)
    for _ in range(10):
        frame = sim.step()
    assert frame.scan is not None
    return frame.scan


# -- parts -----------------------------------------------------------------------------------

def test_distance_map_gradient_matches_finite_differences() -> None:
    dm = DistanceMap(world_grid('office_small'), 0.5)
    rng = np.random.default_rng(0)
    x = rng.uniform(0.5, 11.0, 400)
    y = rng.uniform(0.5, 8.5, 400)
    d, gx, gy = dm.sample(x, y)
    h = 1e-5
    fx = (dm.sample(x + h, y)[0] - dm.sample(x - h, y)[0]) / (2 * h)
    fy = (dm.sample(x, y + h)[0] - dm.sample(x, y - h)[0]) / (2 * h)
    smooth = (d > 0.0) & (d < 0.5)  # away from cell edges the bilinear patch is smooth
    assert np.allclose(gx[smooth], fx[smooth], atol=1e-3)
    assert np.allclose(gy[smooth], fy[smooth], atol=1e-3)
    off_d, off_gx, _ = dm.sample(np.array([-100.0]), np.array([0.0]))
    assert off_d[0] == 0.5 and off_gx[0] == 0.0


def test_scan_points_drop_nan_inf_and_short_ranges() -> None:
    ranges = np.array([1.0, np.nan, np.inf, 0.05, 10.0, 2.0])
    px, py = scan_points(ranges, 0.0, math.pi / 2, 0.12, 10.0, (0.0, 0.0, 0.0))
    assert px == pytest.approx([1.0, 2.0 * math.cos(5 * math.pi / 2)], abs=1e-9)
    assert py == pytest.approx([0.0, 2.0], abs=1e-9)
    with pytest.raises(ValueError, match='no ranges'):
        scan_points([], 0.0, 0.1, 0.1, 10.0, LASER)
    with pytest.raises(ValueError, match='bad angles'):
        scan_points([1.0], math.nan, 0.1, 0.1, 10.0, LASER)
    with pytest.raises(ValueError, match='bad range'):
        scan_points([1.0], 0.0, 0.1, 0.1, math.inf, LASER)


@pytest.mark.parametrize('offset', [(0.2, -0.15, 0.1), (-0.25, 0.1, -0.15), (0.0, 0.0, 0.0)])
def test_gauss_newton_pulls_an_offset_guess_onto_the_true_pose(
        offset: tuple[float, float, float]) -> None:
    truth = Pose2D(5.0, 4.3, 0.4)
    ranges = scan_at('office_small', truth)
    px, py = scan_points(ranges, LIDAR.angle_min, LIDAR.angle_increment, LIDAR.range_min,
                         LIDAR.range_max, LASER)
    dm = DistanceMap(world_grid('office_small'), 0.5)
    guess = (truth.x + offset[0], truth.y + offset[1], truth.yaw + offset[2])
    result = match(dm, px, py, guess, MatcherConfig())
    assert result.ok and result.covariance is not None
    assert math.hypot(result.pose[0] - truth.x, result.pose[1] - truth.y) < 0.02
    assert abs(wrap_angle(result.pose[2] - truth.yaw)) < math.radians(0.5)
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0)
    assert result.rms < 0.05


def test_too_few_points_is_no_match_and_the_covariance_grows() -> None:
    dm = DistanceMap(world_grid('real_room'), 0.5)
    px, py = np.array([0.5, 0.6]), np.array([0.0, 0.1])
    assert not match(dm, px, py, (2.0, 2.0, 0.0), MatcherConfig()).ok
    loc = make_localizer('real_room')
    loc.add_odometry(0, (0.0, 0.0, 0.0))
    loc.add_odometry(10**9, (0.5, 0.0, 0.0))
    nothing = np.full(360, np.inf, np.float32)  # no return at all
    est = loc.process_scan(10**9, nothing, LIDAR.angle_min, LIDAR.angle_increment, 0.12, 10.0)
    assert est.updated and not est.matched
    assert est.pose[0] == pytest.approx(0.8 + 0.0)  # first scan: the initial pose
    loc.add_odometry(2 * 10**9, (1.0, 0.0, 0.0))
    est = loc.process_scan(2 * 10**9, nothing, LIDAR.angle_min, LIDAR.angle_increment, 0.12,
                           10.0)
    assert est.pose[0] == pytest.approx(0.8 + 0.5)  # on odometry alone
    assert est.covariance[0, 0] > START_COV[0, 0]


def test_bad_input_is_skipped_with_a_reason() -> None:
    loc = LamaLocalizer(LamaConfig(), (0.8, 0.8, 0.0), START_COV)
    scan = np.full(360, 2.0, np.float32)
    with pytest.raises(ScanSkipped, match='no map'):
        loc.process_scan(0, scan, -math.pi, LIDAR.angle_increment, 0.12, 10.0)
    loc.set_map(world_grid('real_room'))
    with pytest.raises(ScanSkipped, match='no odometry'):
        loc.process_scan(0, scan, -math.pi, LIDAR.angle_increment, 0.12, 10.0)
    assert loc.add_odometry(100, (0.0, 0.0, 0.0))
    assert not loc.add_odometry(50, (1.0, 0.0, 0.0))  # out of order: ignored
    with pytest.raises(ScanSkipped, match='unusable scan'):
        loc.process_scan(100, np.zeros(0, np.float32), -math.pi, 0.1, 0.12, 10.0)
    est = loc.process_scan(100, np.full(360, np.nan, np.float32), -math.pi,
                           LIDAR.angle_increment, 0.12, 10.0)
    assert est.updated and not est.matched and np.all(np.isfinite(est.pose))


# -- whole routes --------------------------------------------------------------------------------

@pytest.mark.parametrize('world_name', ['office_small', 'workshop', 'real_room'])
def test_tracks_the_whole_route(world_name: str) -> None:
    stream = route_stream(world_name)
    estimates = list(feed(make_localizer(world_name), stream.events))
    position, yaw = errors_of(estimates, stream.truth)
    assert position.size > 700
    # Measured (seed 0): median 0.5-1.7 cm, p95 1.6-2.6 cm, max 1.9-3.2 cm.
    assert float(np.median(position)) <= 0.05
    assert float(np.percentile(position, 95)) <= 0.08
    assert float(position.max()) <= 0.15
    assert math.degrees(float(np.median(yaw))) <= 1.0
    matched = [e for e in estimates if e.updated]
    assert sum(e.matched for e in matched) >= 0.99 * len(matched)


def test_converges_from_a_wrong_initial_pose() -> None:
    stream = route_stream('office_small', duration=20.0)
    loc = make_localizer('office_small', offset=(0.25, -0.2, 0.15))
    position, _ = errors_of(list(feed(loc, stream.events)), stream.truth)
    assert float(np.median(position[20:])) <= 0.03


def _keyvar_paths() -> list[str]:
    nodes = yaml.safe_load(KEYVARS.read_text())['nodes']
    assert len(nodes) == 1 and nodes[0]['class'] == 'LamaLocalNode'
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


def test_keyvars_restore_the_localizer_exactly() -> None:
    # A checkpoint is keyvars.yaml's variables, round-tripped through RORY's codec. Restored
    # into a fresh node (other initial pose, no map), replaying the same messages must give
    # identical poses: nothing else carries state.
    stream = route_stream('real_room', duration=25.0)
    cut = len(stream.events) // 2
    original = SimpleNamespace(localizer=make_localizer('real_room'), waiting_scans=deque())
    list(feed(original.localizer, stream.events[:cut]))
    checkpoint = codec.encode_vars({p: _get(original, p) for p in _keyvar_paths()})
    restored = SimpleNamespace(
        waiting_scans=deque(),
        localizer=LamaLocalizer(LamaConfig(), (3.0, 2.0, 1.0), START_COV))
    for path, value in codec.decode_vars(checkpoint).items():
        _set(restored, path, value)
    after_original = [e.pose for e in feed(original.localizer, stream.events[cut:])]
    after_restored = [e.pose for e in feed(restored.localizer, stream.events[cut:])]
    assert after_restored == after_original
    fresh = LamaLocalizer(LamaConfig(), (3.0, 2.0, 1.0), START_COV)
    fresh.set_map(world_grid('real_room'))
    assert [e.pose for e in feed(fresh, stream.events[cut:])] != after_original
