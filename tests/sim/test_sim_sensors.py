"""Lidar, depth camera and odometry, checked against geometry computed independently."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.robot import ROBOT
from sim.sensors import DEPTH, LIDAR
from sim.simulation import Simulation
from sim.worlds import Box, Cylinder, Pose2D, World, get_world


def _ray_2d(world: World, ox: float, oy: float, angle: float) -> float:
    """Distance along a horizontal ray to the first footprint edge (slab / circle test)."""
    dx, dy = math.cos(angle), math.sin(angle)
    best = math.inf
    for o in world.obstacles:
        if isinstance(o, Cylinder):
            fx, fy = ox - o.x, oy - o.y
            b = fx * dx + fy * dy
            c = fx * fx + fy * fy - o.radius ** 2
            disc = b * b - c
            if disc >= 0:
                t = -b - math.sqrt(disc)
                if t >= 0:
                    best = min(best, t)
            continue
        assert isinstance(o, Box)
        cy, sy = math.cos(o.yaw), math.sin(o.yaw)
        lx, ly = cy * (ox - o.x) + sy * (oy - o.y), -sy * (ox - o.x) + cy * (oy - o.y)
        ldx, ldy = cy * dx + sy * dy, -sy * dx + cy * dy
        t0, t1 = -math.inf, math.inf
        for p, d, h in ((lx, ldx, o.sx / 2), (ly, ldy, o.sy / 2)):
            if abs(d) < 1e-12:
                if abs(p) > h:
                    t0, t1 = math.inf, -math.inf
                continue
            a, b2 = (-h - p) / d, (h - p) / d
            t0, t1 = max(t0, min(a, b2)), min(t1, max(a, b2))
        if t0 <= t1 and t0 >= 0:
            best = min(best, t0)
    return best


@pytest.mark.parametrize('name, pose', [
    ('office_small', Pose2D(3.0, 4.25, 0.3)),
    ('office_small', Pose2D(9.0, 6.0, -2.0)),
    ('workshop', Pose2D(5.0, 6.25, 0.1)),
    ('real_room', Pose2D(1.0, 3.0, 2.5)),
])
def test_every_lidar_beam_matches_the_geometry(name: str, pose: Pose2D) -> None:
    world = get_world(name)
    sim = Simulation(world, start=pose)
    true = sim.lidar.true_ranges(pose.x, pose.y, pose.yaw)
    mx = pose.x + math.cos(pose.yaw) * ROBOT.lidar.x
    my = pose.y + math.sin(pose.yaw) * ROBOT.lidar.x
    for i, a in enumerate(sim.lidar.angles):
        expected = _ray_2d(world, mx, my, pose.yaw + a)
        if expected > LIDAR.range_max:
            # mj_multiRay's cutoff skips far geoms but may still report a far hit;
            # Lidar.measure turns both into +inf.
            assert true[i] < 0 or true[i] > LIDAR.range_max, f'beam {i}'
        else:
            assert true[i] == pytest.approx(expected, abs=1e-6), f'beam {i}'


def test_a_beam_toward_a_wall_reads_its_distance_within_the_noise() -> None:
    # office_small, in the corridor at (1.5, 4.25) facing +x: the beam at +pi/2 (index 270)
    # meets the corridor's north wall face (y = 4.95) at 0.70 m. sigma = 1 cm here.
    world = get_world('office_small')
    sim = Simulation(world, seed=5, start=Pose2D(1.5, 4.25, 0.0), depth=False)
    readings = []
    for _ in range(400):  # 40 scans, standing still
        frame = sim.step()
        if frame.scan is not None:
            readings.append(float(frame.scan[270]))
    r = np.array(readings)
    assert r.size == 40
    assert np.abs(r - 0.70).max() < 4 * 0.01
    assert abs(r.mean() - 0.70) < 0.005
    assert 0.006 < r.std() < 0.014


def test_real_room_lidar_drops_beams_and_the_hall_has_misses() -> None:
    sim = Simulation(get_world('real_room'), seed=1, depth=False)
    scans = [f.scan for f in (sim.step() for _ in range(200)) if f.scan is not None]
    dropped = np.mean([np.isnan(s).mean() for s in scans])
    assert 0.015 < dropped < 0.05
    hall = Simulation(get_world('workshop'), start=Pose2D(2.0, 7.0, 0.0), depth=False)
    scan = hall.lidar.measure(2.0, 7.0, 0.0)
    assert np.isinf(scan).any(), 'beyond 10 m the lidar reports +inf'
    assert not np.isnan(scan).any(), 'no dropouts in the simulated worlds'
    assert scan.dtype == np.float32 and scan.shape == (360,)


def test_depth_camera_sees_a_wall_ahead_and_the_floor_below() -> None:
    # real_room at (3.0, 1.0) facing +x: the camera (12 cm ahead, 25 cm up) looks at the
    # east wall's face (x = 4.95), less the corner column which is off to the left.
    pose = Pose2D(3.0, 1.0, 0.0)
    sim = Simulation(get_world('real_room'), start=pose)
    cloud = sim.camera.measure(pose.x, pose.y, pose.yaw)
    assert cloud.shape == (DEPTH.height, DEPTH.width, 3) and cloud.dtype == np.float32
    wall = 4.95 - (pose.x + ROBOT.camera.x)
    rows = slice(DEPTH.height // 2 - 1, DEPTH.height // 2 + 1)
    cols = slice(DEPTH.width // 2 - 1, DEPTH.width // 2 + 1)
    true = sim.camera.true_depth(pose.x, pose.y, pose.yaw).reshape(DEPTH.height, DEPTH.width)
    assert np.allclose(true[rows, cols], wall, atol=1e-6)  # z forward, depth in metres
    centre = cloud[rows, cols]
    returned = ~np.isnan(centre[..., 2])  # real_room drops 2 % of the pixels
    assert returned.sum() >= 3
    # Within 4 sigma of the D435's noise at that depth (1.2 cm at 1.83 m).
    assert np.allclose(centre[returned, 2], wall, atol=4 * float(DEPTH.depth_rms(wall)))
    assert np.allclose(centre[returned, :2], 0.0, atol=0.02)
    # The bottom rows see the floor: y (down) equals the camera's height above it.
    bottom = cloud[-1]
    ok = ~np.isnan(bottom[:, 2])
    assert ok.any()
    assert np.allclose(bottom[ok, 1], ROBOT.camera.z, atol=0.03)
    # Right of the image is the robot's right (optical x right = -base_link y).
    assert (true[DEPTH.height // 2] > 0).all()


def test_depth_camera_has_the_d435_field_of_view() -> None:
    # 87 deg across (the D435's depth stream); square pixels give about its 58 deg down.
    assert DEPTH.hfov_deg == 87.0
    assert DEPTH.vfov_deg == pytest.approx(58.0, abs=0.5)
    assert 2 * math.degrees(math.atan((DEPTH.width / 2) / DEPTH.fx)) == pytest.approx(87.0)
    # The edge pixels' rays, half a pixel inside the image's edge, agree.
    pose = Pose2D(2.5, 2.0, 0.0)
    sim = Simulation(get_world('real_room'), start=pose)
    xo = sim.camera._xo.reshape(DEPTH.height, DEPTH.width)
    yo = sim.camera._yo.reshape(DEPTH.height, DEPTH.width)
    half_px = 0.5 / DEPTH.fx
    assert math.degrees(2 * math.atan(xo[0, -1] + half_px)) == pytest.approx(87.0)
    assert math.degrees(2 * math.atan(yo[-1, 0] + half_px)) == pytest.approx(DEPTH.vfov_deg)


def test_depth_noise_is_the_d435_stereo_error() -> None:
    # Intel's RMS(z) = z^2 * subpixel / (f_px * baseline), f_px of the 848-pixel stream.
    assert DEPTH.native_fx == pytest.approx(447.0, abs=0.5)
    assert float(DEPTH.depth_rms(2.0)) <= 0.02 * 2.0  # the datasheet: under 2 % at 2 m
    assert float(DEPTH.depth_rms(2.0)) == pytest.approx(2.0**2 * 0.08 / (DEPTH.native_fx * 0.05))
    for z in (0.5, 1.0, 3.0, 7.0):
        assert float(DEPTH.depth_rms(2 * z)) == pytest.approx(4 * float(DEPTH.depth_rms(z)))
    # The camera draws it: residuals over many frames, scaled by RMS(z), have unit spread.
    pose = Pose2D(1.0, 2.0, 0.0)
    sim = Simulation(get_world('real_room'), seed=3, start=pose)
    true = sim.camera.true_depth(pose.x, pose.y, pose.yaw)
    scaled = []
    for _ in range(20):
        z = sim.camera.measure(pose.x, pose.y, pose.yaw)[..., 2].reshape(-1).astype(np.float64)
        ok = ~np.isnan(z)
        scaled.append((z[ok] - true[ok]) / DEPTH.depth_rms(true[ok]))
    r = np.concatenate(scaled)
    assert r.size > 10 * DEPTH.width * DEPTH.height
    assert abs(r.mean()) < 0.02
    # float32 rounding of a near point is ~1e-7 m, far below its RMS: the spread is the noise.
    assert r.std() == pytest.approx(1.0, abs=0.03)


def test_depth_outside_0_2_to_10_m_is_nan() -> None:
    sim = Simulation(get_world('office_small'), seed=4)
    camera = sim.camera
    # True depths from none (-1) to 14 m: what the camera reports lies in its range.
    true = np.concatenate([[-1.0, 0.05, 0.1, 0.19], np.linspace(0.0, 14.0, 20000)])
    for _ in range(5):
        z = camera.measured_depth(true)
        finite = ~np.isnan(z)
        assert (z[finite] >= DEPTH.range_min).all() and (z[finite] <= DEPTH.range_max).all()
        # Nearer than 0.2 m (the noise there is under a millimetre) or far beyond 10 m
        # (12 m is 4.6 sigma out): nothing.
        assert np.isnan(z[(true < 0.199) | (true > 12.0)]).all()
        # Well inside the range (no dropouts in office_small): every pixel returns.
        assert finite[(true > 0.21) & (true < 8.5)].all()
    # A wall 15 cm ahead of the camera fills the image: every pixel too near, all NaN.
    pose = Pose2D(4.95 - 0.15 - ROBOT.camera.x, 1.0, 0.0)
    near = Simulation(get_world('real_room'), start=pose)
    assert np.allclose(near.camera.true_depth(pose.x, pose.y, pose.yaw), 0.15, atol=1e-6)
    assert np.isnan(near.camera.measure(pose.x, pose.y, pose.yaw)).all()


def test_camera_points_beyond_range_are_nan() -> None:
    hall = get_world('workshop')
    pose = Pose2D(2.0, 7.0, 0.0)  # looking down the hall: the far wall is 18 m away
    sim = Simulation(hall, start=pose)
    true = sim.camera.true_depth(pose.x, pose.y, pose.yaw).reshape(DEPTH.height, DEPTH.width)
    cloud = sim.camera.measure(pose.x, pose.y, pose.yaw)
    z = cloud[..., 2]
    assert np.isnan(z).any()
    assert np.isnan(z[true > 12.0]).all() and (true > 12.0).any()
    assert np.nanmax(z) <= DEPTH.range_max
    assert np.nanmin(z) >= DEPTH.range_min


def test_odometry_tracks_a_short_drive_and_drifts_over_the_route() -> None:
    world = get_world('office_small')
    sim = Simulation(world, seed=2, lidar=False, depth=False)
    for _ in range(300):  # 3 s at 0.3 m/s
        sim.command(0.3, 0.0)
        sim.step()
    for _ in range(100):
        sim.step()
    odom, truth = sim.odometry, sim.pose()
    travelled = truth.x - world.start.x
    # 3 s commanded + 0.5 s until the command times out; the ramps up and down cancel.
    assert travelled == pytest.approx(0.3 * 3.5, abs=0.02)
    assert odom.x == pytest.approx(travelled, rel=0.02)
    # At rest nothing changes.
    before = (odom.x, odom.y, odom.yaw)
    for _ in range(100):
        sim.step()
    assert (odom.x, odom.y, odom.yaw) == before


def test_same_seed_same_noise_other_seed_other_noise() -> None:
    world = get_world('real_room')

    def record(seed: int) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float]]:
        sim = Simulation(world, seed=seed)
        scans, clouds = [], []
        for k in range(300):
            if k % 5 == 0:
                sim.command(0.25, 0.4)
            frame = sim.step()
            if frame.scan is not None:
                scans.append(frame.scan)
            if frame.cloud is not None:
                clouds.append(frame.cloud)
        o = sim.odometry
        return np.array(scans), np.array(clouds), (o.x, o.y, o.yaw)

    a, b, c = record(11), record(11), record(12)
    assert np.array_equal(a[0], b[0], equal_nan=True)
    assert np.array_equal(a[1], b[1], equal_nan=True)
    assert a[2] == b[2]
    assert not np.array_equal(a[0], c[0], equal_nan=True)
    assert a[2] != c[2]
