"""amcl offline: the algorithm's parts, and whole routes against the simulator's ground truth.

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

from amcl_filter import FilterConfig, ParticleFilter, kld_sample_count
from amcl_localizer import AmclConfig, AmclLocalizer, ScanSkipped
from amcl_motion_model import MotionNoise, sample_motion_model_odometry
from amcl_sensor_model import LikelihoodField, SensorModelConfig, select_beams
from planar_geometry import compose, relative, wrap_angle
from planar_map import GridMap
from rory_eval.metrics import position_errors
from rory_runtime import codec
from sim.driver import CONTROL_RATE, RouteFollower
from sim.maps import ground_truth_map
from sim.sensors import LIDAR
from sim.simulation import TICK, Simulation
from sim.worlds import get_world

KEYVARS = Path(__file__).resolve().parents[2] / 'targets' / 'amcl' / 'keyvars.yaml'
START_COV = np.diag([0.25, 0.25, (math.pi / 12) ** 2])  # the node's defaults


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


def make_localizer(world_name: str, seed: int = 0, config: AmclConfig | None = None,
                   offset: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> AmclLocalizer:
    s = get_world(world_name).start
    loc = AmclLocalizer(config or AmclConfig(), np.random.default_rng(seed),
                        (s.x + offset[0], s.y + offset[1], s.yaw + offset[2]), START_COV)
    loc.set_map(world_grid(world_name))
    return loc


def feed(loc: AmclLocalizer, events: list[tuple[Any, ...]]) -> Iterator[tuple[float, ...]]:
    """Play events into the localizer; yield (t, x, y, yaw) per scan."""
    for event in events:
        if event[0] == 'odom':
            loc.add_odometry(event[1], event[2:5])
        else:
            est = loc.process_scan(event[1], event[2], LIDAR.angle_min, LIDAR.angle_increment,
                                   LIDAR.range_min, LIDAR.range_max)
            yield (event[1] / 1e9, *est.pose)


def yaw_errors(estimates: list[tuple[float, ...]],
               truth: list[tuple[float, float, float, float]]) -> np.ndarray:
    t = np.array([r[0] for r in truth])
    yaw = np.unwrap([r[3] for r in truth])
    est = np.array(estimates)
    return np.abs((est[:, 3] - np.interp(est[:, 0], t, yaw) + np.pi) % (2 * np.pi) - np.pi)


# -- parts -----------------------------------------------------------------------------------

def test_motion_model_without_noise_moves_every_particle_by_the_odometry() -> None:
    particles = np.array([[0.0, 0.0, 0.0], [2.0, 1.0, math.pi / 2]])
    before, after = (5.0, 5.0, 0.3), (5.4, 5.3, 0.8)
    moved = sample_motion_model_odometry(particles, before, after, MotionNoise(0, 0, 0, 0),
                                         np.random.default_rng(0))
    delta = relative(before, after)
    for p, m in zip(particles, moved, strict=True):
        assert tuple(m) == pytest.approx(compose(tuple(p), delta))


def test_motion_model_noise_grows_with_motion_and_reversing_is_not_a_half_turn() -> None:
    rng = np.random.default_rng(1)
    start = np.zeros((4000, 3))
    noise = MotionNoise()
    short = sample_motion_model_odometry(start, (0, 0, 0), (0.1, 0, 0), noise, rng)
    long = sample_motion_model_odometry(start, (0, 0, 0), (1.0, 0, 0), noise, rng)
    assert short[:, 0].mean() == pytest.approx(0.1, abs=0.005)
    assert long[:, 0].std() > 5 * short[:, 0].std()
    back = sample_motion_model_odometry(start, (0, 0, 0), (-0.5, 0, 0), noise, rng)
    assert back[:, 0].mean() == pytest.approx(-0.5, abs=0.01)
    assert np.abs(back[:, 2]).mean() < 0.5  # heading noise as for a short turn, not pi


def test_kld_bound_follows_fox_2003() -> None:
    n = kld_sample_count([1, 2, 10, 50, 200], 0.05, 2.3263)
    assert n[0] == 0
    assert list(n) == sorted(n)
    # Fox 2003, fig. 3 scale: ~ (k - 1) / (2 eps) for large k
    assert 190 < n[2] < 240 and n[4] == pytest.approx(199 / 0.1, rel=0.25)


def test_resampling_adapts_the_particle_count() -> None:
    config = FilterConfig(min_particles=100, max_particles=3000)
    pf = ParticleFilter(config, np.random.default_rng(2))
    # a tight cloud in the middle of one 0.5 m x 0.5 m x 10 deg bin: the minimum
    pf.initialize_gaussian((0.25, 0.25, math.radians(5)), np.diag([1e-4, 1e-4, 1e-4]))
    pf.resample()
    assert pf.particles.shape[0] == 100
    pf.initialize_gaussian((0.0, 0.0, 0.0), np.diag([4.0, 4.0, 1.0]))  # hundreds of bins
    pf.resample()
    assert 1000 < pf.particles.shape[0] <= 3000
    assert pf.weights.sum() == pytest.approx(1.0)


def test_low_variance_resampling_copies_in_proportion_to_weight() -> None:
    pf = ParticleFilter(FilterConfig(min_particles=400, max_particles=400),
                        np.random.default_rng(4))
    pf.particles = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    pf.weights = np.array([0.5, 0.25, 0.125, 0.125])
    pf.resample()
    counts = np.bincount(pf.particles[:, 0].astype(int), minlength=4)
    # systematic resampling: each count within one of n * w
    assert np.all(np.abs(counts - 400 * np.array([0.5, 0.25, 0.125, 0.125])) <= 1)


def test_estimate_is_the_heavier_cluster() -> None:
    pf = ParticleFilter(FilterConfig(), np.random.default_rng(5))
    rng = np.random.default_rng(6)
    a = np.column_stack([rng.normal(1.0, 0.1, 600), rng.normal(1.0, 0.1, 600),
                         rng.normal(3.1, 0.05, 600)])
    b = np.column_stack([rng.normal(5.0, 0.1, 400), rng.normal(5.0, 0.1, 400),
                         np.zeros(400)])
    pf.particles = np.vstack([a, b])
    pf.weights = np.full(1000, 1e-3)
    pf.estimate()
    assert pf.pose[:2] == pytest.approx([1.0, 1.0], abs=0.02)
    assert abs(wrap_angle(float(pf.pose[2]) - 3.1)) < 0.01  # a cluster across +-pi holds
    assert pf.covariance[0, 0] == pytest.approx(0.01, rel=0.2)
    assert pf.covariance[2, 2] == pytest.approx(0.0025, rel=0.2)


def test_likelihood_field_prefers_the_true_pose_and_skips_bad_beams() -> None:
    world = get_world('office_small')
    sim = Simulation(world, 0, depth=False)
    for _ in range(10):
        frame = sim.step()
    assert frame.scan is not None
    config = SensorModelConfig()
    ranges = frame.scan.astype(np.float64)
    ranges[::7] = np.nan
    ranges[1::11] = np.inf
    ranges[2::13] = 0.01  # below range_min
    beams = select_beams(ranges, LIDAR.angle_min, LIDAR.angle_increment, LIDAR.range_min,
                         LIDAR.range_max, config)
    assert 40 <= beams.count < 60
    model = LikelihoodField(world_grid('office_small'), config)
    s = world.start
    poses = np.array([[s.x, s.y, s.yaw], [s.x + 0.1, s.y, s.yaw], [s.x, s.y - 0.1, s.yaw],
                      [s.x, s.y, s.yaw + 0.1], [-50.0, -50.0, 0.0]])
    scores = model.log_likelihood(poses, beams)
    assert np.all(np.isfinite(scores)) and int(np.argmax(scores)) == 0
    with pytest.raises(ValueError, match='no ranges'):
        select_beams([], 0.0, 0.1, 0.1, 10.0, config)
    with pytest.raises(ValueError, match='bad angles'):
        select_beams([1.0, 2.0], 0.0, 0.0, 0.1, 10.0, config)
    assert select_beams([math.nan] * 360, -math.pi, LIDAR.angle_increment, 0.12, 10.0,
                        config).count == 0


def test_bad_input_is_skipped_with_a_reason() -> None:
    loc = AmclLocalizer(AmclConfig(), np.random.default_rng(0), (0.8, 0.8, 0.0), START_COV)
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
    # all NaN: the filter runs on odometry alone, nothing breaks
    est = loc.process_scan(100, np.full(360, np.nan, np.float32), -math.pi,
                           LIDAR.angle_increment, 0.12, 10.0)
    assert est.updated and est.beams == 0 and np.all(np.isfinite(est.pose))
    assert loc.add_odometry(100 + 5 * 10**9, (0.0, 0.0, 0.0))
    assert loc.add_odometry(10, (0.0, 0.0, 0.0))  # a clock reset: history starts over
    assert len(loc.odometry) == 1


# -- whole routes --------------------------------------------------------------------------------

@pytest.mark.parametrize('world_name', ['office_small', 'workshop', 'real_room'])
def test_tracks_the_whole_route(world_name: str) -> None:
    stream = route_stream(world_name)
    loc = make_localizer(world_name)
    estimates = list(feed(loc, stream.events))
    errors = position_errors([e[:3] for e in estimates], stream.truth)
    assert errors.size > 700
    # Measured (seed 0): median 1.4-2.1 cm, p95 3-4 cm, max 4.5-6.1 cm, yaw median < 0.5 deg.
    assert float(np.median(errors)) <= 0.05
    assert float(np.percentile(errors, 95)) <= 0.10
    assert float(errors.max()) <= 0.20
    assert math.degrees(float(np.median(yaw_errors(estimates, stream.truth)))) <= 2.0
    assert 500 <= loc.pf.particles.shape[0] <= 2000


def test_converges_from_a_wrong_initial_pose() -> None:
    stream = route_stream('office_small', duration=30.0)
    loc = make_localizer('office_small', offset=(0.35, -0.3, 0.2))
    estimates = list(feed(loc, stream.events))
    errors = position_errors([e[:3] for e in estimates], stream.truth)
    late = errors[len(errors) // 3:]
    assert float(np.median(late)) <= 0.05


def test_global_localization_with_augmented_mcl() -> None:
    # Bonus: particles over all the free space of office_small, recovery on.
    stream = route_stream('office_small', duration=20.0)
    config = AmclConfig(filter=FilterConfig(max_particles=5000, alpha_slow=0.001,
                                            alpha_fast=0.1))
    loc = make_localizer('office_small', config=config)
    loc.add_odometry(0, (0.0, 0.0, 0.0))
    loc.set_pose_uniform()
    assert loc.pf.particles.shape[0] == 5000
    estimates = list(feed(loc, stream.events))
    errors = position_errors([e[:3] for e in estimates], stream.truth)
    assert float(np.median(errors[-50:])) <= 0.10


def _keyvar_paths() -> list[str]:
    nodes = yaml.safe_load(KEYVARS.read_text())['nodes']
    assert len(nodes) == 1 and nodes[0]['class'] == 'AmclNode'
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


def test_keyvars_restore_the_filter_exactly() -> None:
    # A checkpoint is keyvars.yaml's variables, round-tripped through RORY's codec. Restored
    # into a fresh node (other seed, other initial pose, no map), replaying the same messages
    # must give bit-identical particles and poses: nothing else carries state.
    stream = route_stream('real_room', duration=25.0)
    cut = len(stream.events) // 2
    original = SimpleNamespace(localizer=make_localizer('real_room', seed=7),
                               waiting_scans=deque())
    list(feed(original.localizer, stream.events[:cut]))
    paths = _keyvar_paths()
    checkpoint = codec.encode_vars({p: _get(original, p) for p in paths})
    restored = SimpleNamespace(waiting_scans=deque(), localizer=AmclLocalizer(
        AmclConfig(), np.random.default_rng(99), (3.0, 2.0, 1.0), START_COV))
    for path, value in codec.decode_vars(checkpoint).items():
        _set(restored, path, value)
    after_original = list(feed(original.localizer, stream.events[cut:]))
    after_restored = list(feed(restored.localizer, stream.events[cut:]))
    assert after_restored == after_original
    assert np.array_equal(restored.localizer.pf.particles, original.localizer.pf.particles)
    # and without the checkpoint a fresh node does not get there
    fresh = make_localizer('real_room', seed=99)
    assert list(feed(fresh, stream.events[cut:])) != after_original


def test_same_seed_same_run() -> None:
    stream = route_stream('real_room', duration=10.0)
    a = list(feed(make_localizer('real_room', seed=3), stream.events))
    b = list(feed(make_localizer('real_room', seed=3), stream.events))
    assert a == b
