"""grid_slam's algorithm offline: scans from the simulator stepped synchronously, no ROS.

The quality assertions live here: over each world's whole route (the same deterministic
trajectory as ``--driver internal``), the map built from scans alone agrees with the
ground-truth map and the pose stays on the true path.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from functools import cache

import numpy as np
import pytest

from grid_slam_grid import GridGeometry, interpolate, ray_cells, update
from grid_slam_mapper import GridMapper, MapperConfig, body_velocity, predict
from grid_slam_matcher import match
from grid_slam_occupancy import known_extent, occupancy_values
from grid_slam_scan import LaserMount, ScanError, scan_to_points
from rory_eval.metrics import MapScore, map_score, position_errors
from rory_runtime.codec import decode_vars, encode_vars
from sim.driver import CONTROL_RATE, RouteFollower
from sim.maps import OccupancyMap, ground_truth_map
from sim.sensors import LIDAR
from sim.simulation import TICK, Simulation
from sim.worlds import get_world

MOUNT = LaserMount()  # the simulator's base_scan in base_link
KEY_STATE = ('log_odds', 'pose', 'last_update_pose', 'velocity', 'last_stamp_ns',
             'scans_matched', 'map_updates')  # keyvars.yaml, below mapper.


@dataclass(frozen=True)
class Recording:
    """One route driven offline: every scan with its stamp and the true pose at it."""

    stamps_ns: list[int]
    scans: list[np.ndarray]
    truth: list[tuple[float, float, float, float]]  # (t, x, y, yaw) at each scan


@cache
def drive(world_name: str, seed: int = 0, limit: float = 1e9) -> Recording:
    """The world's route as ``--driver internal`` drives it (same control law, same ticks)."""
    world = get_world(world_name)
    sim = Simulation(world, seed, depth=False)
    follower = RouteFollower(world.route)
    every = round(1.0 / (CONTROL_RATE * TICK))
    stamps, scans, truth = [], [], []
    while not follower.done and sim.time < limit:
        if sim.ticks % every == 0:
            p = sim.pose()
            sim.command(*follower.command(p.x, p.y, p.yaw))
        frame = sim.step()
        if frame.scan is not None:
            p = sim.pose()
            stamps.append(frame.stamp_ns)
            scans.append(frame.scan.copy())
            truth.append((frame.stamp_ns * 1e-9, p.x, p.y, p.yaw))
    return Recording(stamps, scans, truth)


def mapper_for(world_name: str) -> GridMapper:
    """A mapper started at the world's start pose, as the node is with map_start_*."""
    start = get_world(world_name).start
    return GridMapper(MapperConfig(map_start_x=start.x, map_start_y=start.y,
                                   map_start_yaw=start.yaw))


def feed(mapper: GridMapper, rec: Recording, start: int = 0,
         stop: int | None = None) -> list[tuple[float, float, float, float]]:
    """Process scans [start, stop) as the node does; the pose after each as (t, x, y, yaw)."""
    poses = []
    for stamp, ranges in zip(rec.stamps_ns[start:stop], rec.scans[start:stop], strict=True):
        points = scan_to_points(ranges, LIDAR.angle_min, LIDAR.angle_increment,
                                LIDAR.range_min, LIDAR.range_max, MOUNT)
        mapper.process(points, (MOUNT.x, MOUNT.y), stamp)
        poses.append((stamp * 1e-9, *(float(v) for v in mapper.pose)))
    return poses


@cache
def whole_route(world_name: str) -> tuple[GridMapper, list[tuple[float, float, float, float]]]:
    """The mapper after the world's whole route and its pose after each scan (shared by
    tests; do not change it)."""
    mapper = mapper_for(world_name)
    return mapper, feed(mapper, drive(world_name))


def score(mapper: GridMapper, world_name: str) -> MapScore:
    g = mapper.geometry[0]
    estimate = OccupancyMap(occupancy_values(mapper.log_odds[0]), g.resolution, g.origin_x,
                            g.origin_y)
    return map_score(estimate, ground_truth_map(get_world(world_name)), tolerance=1)


# -- scans ------------------------------------------------------------------------------------


def test_scan_points_drop_dropouts_misses_and_out_of_range_beams() -> None:
    ranges = [1.0, float('nan'), float('inf'), 0.05, 2.0, 11.0, -1.0]
    pts = scan_to_points(ranges, 0.0, math.pi / 2, 0.12, 10.0, LaserMount(-0.064, 0.0, 0.0))
    # beams 0 (1 m at 0 rad) and 4 (2 m at 2 pi = 0 rad) survive, shifted by the mount
    assert pts == pytest.approx(np.array([[0.936, 0.0], [1.936, 0.0]]), abs=1e-9)


def test_scan_points_apply_the_mount_yaw() -> None:
    pts = scan_to_points([1.0], 0.0, 0.1, 0.1, 5.0, LaserMount(0.5, 0.25, math.pi / 2))
    assert pts == pytest.approx(np.array([[0.5, 1.25]]), abs=1e-9)


@pytest.mark.parametrize(('angle_min', 'increment'),
                         [(float('nan'), 0.01), (0.0, 0.0), (0.0, float('inf'))])
def test_scan_with_unusable_angles_is_refused(angle_min: float, increment: float) -> None:
    with pytest.raises(ScanError, match='bad beam angles'):
        scan_to_points([1.0, 2.0], angle_min, increment, 0.1, 5.0, MOUNT)


def test_an_empty_scan_has_no_points() -> None:
    assert scan_to_points([], -math.pi, 0.1, 0.1, 5.0, MOUNT).shape == (0, 2)


# -- the grid ---------------------------------------------------------------------------------

GEOMETRY = GridGeometry(0.1, -1.0, -2.0, 20, 30)


def test_interpolation_is_exact_at_cell_centres_and_its_gradient_is_the_slope() -> None:
    rng = np.random.default_rng(7)
    log_odds = rng.normal(0.0, 2.0, (30, 20)).astype(np.float32)
    # the centre of cell (row 5, col 3)
    m, _, _ = interpolate(log_odds, GEOMETRY, np.array([[-1.0 + 0.35, -2.0 + 0.55]]))
    assert m[0] == pytest.approx(1 / (1 + math.exp(-float(log_odds[5, 3]))))
    xy = np.array([[-0.33, -1.21], [0.41, 0.07]])
    m, gx, gy = interpolate(log_odds, GEOMETRY, xy)
    h = 1e-6
    mx, _, _ = interpolate(log_odds, GEOMETRY, xy + np.array([h, 0.0]))
    my, _, _ = interpolate(log_odds, GEOMETRY, xy + np.array([0.0, h]))
    assert gx == pytest.approx((mx - m) / h, rel=1e-4)
    assert gy == pytest.approx((my - m) / h, rel=1e-4)


def test_points_off_the_grid_contribute_nothing() -> None:
    log_odds = np.ones((30, 20), np.float32)
    m, gx, gy = interpolate(log_odds, GEOMETRY, np.array([[-5.0, 0.0], [0.9, 0.9]]))
    assert (m[0], gx[0], gy[0]) == (0.0, 0.0, 0.0)
    assert m[1] > 0.7


def reference_line(start: tuple[int, int], end: tuple[int, int]) -> list[tuple[int, int]]:
    """The same DDA line, one cell at a time (the end excluded)."""
    dc, dr = end[0] - start[0], end[1] - start[1]
    n = max(abs(dc), abs(dr))
    return [(start[0] + round(k * dc / n), start[1] + round(k * dr / n)) for k in range(n)]


def test_ray_cells_are_a_connected_line_without_its_end() -> None:
    ends = np.array([[7, 3], [-4, 9], [0, -6], [5, 5], [0, 0]])
    cols, rows = ray_cells((0, 0), ends)
    expected = [c for e in ends.tolist() if e != [0, 0] for c in reference_line((0, 0), e)]
    assert list(zip(cols.tolist(), rows.tolist(), strict=True)) == expected
    # 8-connected: consecutive cells of one ray are neighbours
    first = reference_line((0, 0), (-4, 9))
    assert all(max(abs(a[0] - b[0]), abs(a[1] - b[1])) == 1
               for a, b in itertools.pairwise(first))


def test_an_update_marks_each_cell_once_and_occupied_wins() -> None:
    log_odds = np.zeros((30, 20), np.float32)
    origin = (-0.95, -1.95)  # centre of cell (0, 0)
    # Two beams along row 0 ending in cols 5 and 8: cols 1..4 are crossed twice, col 5 is
    # one beam's end and the other's crossing.
    ends = np.array([[-1.0 + 0.55, -1.95], [-1.0 + 0.85, -1.95]])
    update(log_odds, GEOMETRY, origin, ends, free_delta=-0.4, occupied_delta=2.2, clamp=3.0)
    assert log_odds[0, :5] == pytest.approx([-0.4] * 5)
    assert log_odds[0, 5] == pytest.approx(2.2)
    assert log_odds[0, 6:8] == pytest.approx([-0.4, -0.4])
    assert log_odds[0, 8] == pytest.approx(2.2)
    assert np.count_nonzero(log_odds) == 9
    for _ in range(3):
        update(log_odds, GEOMETRY, origin, ends, -0.4, 2.2, clamp=3.0)
    assert log_odds[0, 5] == pytest.approx(3.0)  # clamped
    for _ in range(20):
        update(log_odds, GEOMETRY, origin, ends[1:], -0.4, 2.2, clamp=3.0)
    assert log_odds[0, 5] == pytest.approx(-3.0)  # the map can still change its mind


def test_beams_leaving_the_grid_update_only_the_cells_inside() -> None:
    log_odds = np.zeros((30, 20), np.float32)
    update(log_odds, GEOMETRY, (-0.95, -1.95), np.array([[5.0, -1.95]]), -0.4, 2.2, 3.0)
    assert log_odds[0] == pytest.approx([-0.4] * 20)
    assert np.count_nonzero(log_odds) == 20


def test_occupancy_values_and_the_known_extent() -> None:
    log_odds = np.zeros((6, 8), np.float32)
    log_odds[2, 3], log_odds[4, 5] = 1.5, -0.3
    values = occupancy_values(log_odds)
    assert values[2, 3] == 100 and values[4, 5] == 0 and values[0, 0] == -1
    assert known_extent(values) == (2, 5, 3, 6)
    assert known_extent(occupancy_values(np.zeros((3, 3), np.float32))) is None


# -- matching ---------------------------------------------------------------------------------


def test_a_scan_is_matched_back_to_its_pose_from_a_wrong_guess() -> None:
    rec = drive('office_small', limit=0.5)
    mapper = mapper_for('office_small')
    feed(mapper, rec, 0, 1)  # the map of the first scan, at the true start
    points = scan_to_points(rec.scans[0], LIDAR.angle_min, LIDAR.angle_increment,
                            LIDAR.range_min, LIDAR.range_max, MOUNT)
    levels = list(zip(mapper.log_odds, mapper.geometry, strict=True))
    truth = mapper.pose.copy()
    for offset in ([0.12, -0.08, 0.06], [-0.1, 0.1, -0.08], [0.0, 0.15, 0.1]):
        found = match(levels, points, truth + offset, [5, 3, 3])
        assert math.hypot(*(found[:2] - truth[:2])) < 0.02, offset
        assert abs(found[2] - truth[2]) < math.radians(0.5), offset


def test_constant_velocity_prediction_inverts_the_velocity_estimate() -> None:
    before = np.array([1.0, 2.0, 3.0])
    after = np.array([1.02, 2.05, 2.9])
    v = body_velocity(before, after, 0.1)
    assert predict(before, v, 0.1) == pytest.approx(after, abs=1e-3)


# -- quality over whole routes ----------------------------------------------------------------


@pytest.mark.parametrize(('world_name', 'max_median_error', 'max_error'), [
    ('office_small', 0.05, 0.08),
    # The first scan is at t = 0.1 s, when the driver has already turned the robot 0.66 deg
    # away from the start heading the map is anchored to: 10 m on, that is 11 cm.
    ('workshop', 0.12, 0.2),
    ('real_room', 0.05, 0.1),
])
def test_a_whole_route_maps_the_world_and_tracks_the_pose(
        world_name: str, max_median_error: float, max_error: float) -> None:
    rec = drive(world_name)
    mapper, poses = whole_route(world_name)
    result = score(mapper, world_name)
    assert result.agreement >= 0.90
    assert result.iou_occupied >= 0.45  # walls come out two cells thick: see the README
    assert result.observed_fraction >= 0.6
    errors = position_errors([p[:3] for p in poses], rec.truth)
    assert len(errors) == len(rec.scans)
    assert float(np.median(errors)) <= max_median_error
    assert float(errors.max()) <= max_error
    assert mapper.scans_matched == len(rec.scans)
    # hector's thresholds: the map is updated on a small fraction of the scans
    assert 0.05 * len(rec.scans) < mapper.map_updates < 0.35 * len(rec.scans)


def test_the_workshop_error_is_the_start_heading_not_drift_in_the_hall() -> None:
    rec = drive('workshop')
    _, poses = whole_route('workshop')
    # The map is anchored at the start heading; the robot had turned by the first scan.
    offset = poses[0][3] - rec.truth[0][3]
    assert math.degrees(abs(offset)) == pytest.approx(0.66, abs=0.05)
    x0, y0 = poses[0][1], poses[0][2]
    c, s = math.cos(-offset), math.sin(-offset)
    rotated = [(t, x0 + c * (x - x0) - s * (y - y0), y0 + s * (x - x0) + c * (y - y0))
               for t, x, y, _ in poses]
    errors = position_errors(rotated, rec.truth)
    # Without that offset, the pose stays within a few cm over the whole 35 m route.
    assert float(np.median(errors)) <= 0.03
    assert float(errors.max()) <= 0.05


def test_restoring_the_key_state_and_replaying_gives_the_same_state() -> None:
    rec = drive('real_room')
    original = mapper_for('real_room')
    feed(original, rec, 0, 150)
    # A checkpoint as RORY writes it (its codec: data, never pickles), read back.
    checkpoint = encode_vars({name: getattr(original, name) for name in KEY_STATE})
    feed(original, rec, 150, 300)
    restored = mapper_for('real_room')  # a new process, from the same parameters
    for name, value in decode_vars(checkpoint).items():
        setattr(restored, name, value)
    feed(restored, rec, 150, 300)
    for name in KEY_STATE:
        a, b = getattr(original, name), getattr(restored, name)
        if name == 'log_odds':
            assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
        else:
            assert np.array_equal(a, b), name


def test_a_gap_in_the_scans_drops_the_velocity_prediction() -> None:
    rec = drive('real_room', limit=20.0)
    mapper = mapper_for('real_room')
    feed(mapper, rec, 0, 60)
    assert np.any(mapper.velocity != 0)
    # Scans 60..79 lost (2 s): the robot moved on 0.6 m. Matching starts from the last pose
    # (no prediction over a gap) and the scan-to-map match pulls it back within a few scans.
    poses = feed(mapper, rec, 80, 81)
    assert not np.any(mapper.velocity)
    poses += feed(mapper, rec, 81, 120)
    errors = position_errors([p[:3] for p in poses], rec.truth)
    assert float(errors[3:].max()) < 0.06
