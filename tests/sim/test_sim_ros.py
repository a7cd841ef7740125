"""The simulator as a real ROS 2 process: /cmd_vel moves it, /e_stop stops it, /scan reads walls."""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Callable

import pytest
from conftest import Probe, SimProcess

pytestmark = pytest.mark.ros

WALL_WAIT = 40.0  # wall seconds allowed for start-up and discovery on a loaded 2-core machine


def _first_pose(probe: Probe) -> tuple[float, float, float, float]:
    probe.wait_until(lambda: len(probe.poses) > 0, WALL_WAIT, '/ground_truth/pose')
    with probe.lock:
        return probe.poses[-1]


def test_cmd_vel_moves_the_robot_as_commanded(
    sim_world: Callable[..., tuple[SimProcess, Probe]],
) -> None:
    proc, probe = sim_world('--world', 'real_room', '--duration', '60', '--no-depth')
    # The probe's own writer matched with the simulator's reader, not only the reader seen in
    # the graph: on a loaded machine the graph showed it while the match was not made yet,
    # and every twist sent was lost (the robot moved 0.7 mm in 2 s).
    probe.wait_until(lambda: probe.cmd_vel.get_subscription_count() > 0, WALL_WAIT,
                     'the simulator to match /cmd_vel')
    _t0, x0, y0, yaw0 = _first_pose(probe)
    assert (x0, y0) == pytest.approx((0.8, 0.8), abs=1e-3)
    probe.drive(0.2, 0.0, 2.0)
    with probe.lock:
        _t1, x1, y1, yaw1 = probe.poses[-1]
    # 0.2 m/s reached within 0.2 s (1 m/s^2 ramp): about 0.38 m in 2 s, straight ahead.
    assert x1 - x0 == pytest.approx(0.38, abs=0.06), proc.output()
    assert abs(y1 - y0) < 0.01
    assert abs(yaw1 - yaw0) < 0.01
    # Turning: 0.5 rad/s for 2 s is about 0.93 rad (3 rad/s^2 ramp), on the spot.
    probe.drive(0.0, 0.5, 2.0)
    with probe.lock:
        _, x2, y2, yaw2 = probe.poses[-1]
    assert math.remainder(yaw2 - yaw1, 2 * math.pi) == pytest.approx(0.95, abs=0.1)
    # It only rolls on while braking from 0.2 m/s at 1 m/s^2: 2 cm.
    assert math.hypot(x2 - x1, y2 - y1) < 0.03
    # No more commands: the 0.5 s timeout stops it.
    probe.send_twist(0.3, 0.0)
    with probe.lock:
        t_last = probe.clock
    probe.wait_until(lambda: probe.clock > t_last + 1.5, WALL_WAIT, 'sim time to advance')
    with probe.lock:
        recent = [p for p in probe.poses if p[0] > t_last + 1.0]
    assert recent and math.hypot(recent[-1][1] - recent[0][1], recent[-1][2] - recent[0][2]) < 1e-3


def _speeds(poses: list[tuple[float, float, float, float]]) -> list[tuple[float, float]]:
    """(stamp, ground-truth speed) of each pair of consecutive poses."""
    return [
        (b[0], math.hypot(b[1] - a[1], b[2] - a[2]) / (b[0] - a[0]))
        for a, b in itertools.pairwise(poses)
    ]


def _command_until(probe: Probe, v: float, cond: Callable[[], bool], what: str) -> None:
    """Send (v, 0) on /cmd_vel at 20 Hz until ``cond()`` (called under the probe's lock)."""
    import time

    deadline = time.monotonic() + WALL_WAIT
    while True:
        with probe.lock:
            if cond():
                return
        if time.monotonic() > deadline:
            raise AssertionError(f'timed out after {WALL_WAIT} s waiting for {what}')
        probe.send_twist(v, 0.0)
        time.sleep(0.05)


def test_e_stop_stops_the_robot_within_0_2_s_and_holds_it(
    sim_world: Callable[..., tuple[SimProcess, Probe]],
) -> None:
    """Engaged at full speed, /e_stop stops the robot within 0.2 s of sim time and holds it.

    Issue 35: this failed under load with "not moving before the stop: 0.238 m/s" (0.247 in a full
    run). The 0.25 m/s bound is right: commanded 0.3 m/s, the robot's true speed in real_room (seed
    0) is 0.3 x (1 - wheel slip) = 0.262-0.300 m/s over the whole 60 s run (sim.robot.WheelSlip:
    mean 3 %, sigma 3 %), and it gets there 0.3 s after the first command (1 m/s^2). Nor was it sim
    time running slower than real time: the old wait was already counted in sim time. What was wrong
    was what it counted: "1.5 s" on the probe's copy of /clock from when the probe first saw a pose,
    assumed to be 1.5 s of the robot obeying /cmd_vel. 0.238 and 0.247 m/s are values of the ramp
    (about 0.35 s after the first command obeyed): the robot had obeyed for about 0.55 s, not 1.5 s,
    when the stop was applied. Two ways that happens on a loaded machine (which one it was is not
    known: 31 runs here under load never reproduced it): the simulator's reader matches the probe's
    /cmd_vel writer later than the probe sees the simulator's /e_stop reader (the wait above), and a
    reliable, volatile sample sent before the match is lost; or the probe's /clock lags the
    simulator's (a pose stream delivered 1 s late is recorded in 8827209). Measured with the old
    wait, the first 0.9, 1.0 and 1.05 s of /cmd_vel withheld give 0.286, 0.265 and 0.220 m/s at
    t_stop - 0.2. Now the test commands until the ground truth (its stamps are sim time) shows the
    robot above 0.25 m/s for the last 0.3 s, which passes with 1.05 s and 2 s withheld; after the
    stop, until the ground truth covers the second after the sim time the simulator logs for it;
    after the release, until the robot has moved 0.1 m.
    """
    proc, probe = sim_world('--world', 'real_room', '--duration', '60', '--no-depth')
    probe.wait_until(lambda: probe.node.count_subscribers('/e_stop') > 0, WALL_WAIT,
                     'the simulator to subscribe /e_stop')
    _first_pose(probe)

    def at_speed() -> bool:
        recent = [p for p in probe.poses if p[0] >= probe.poses[-1][0] - 0.3]
        return (len(recent) > 1 and recent[-1][0] - recent[0][0] >= 0.29
                and all(v > 0.25 for _, v in _speeds(recent)))

    _command_until(probe, 0.3, at_speed, 'the robot at 0.3 m/s (ground truth above 0.25 m/s)')
    import time

    sent = time.monotonic()
    probe.send_e_stop(True)

    # Keep commanding (the stop must hold anyway) until the simulator has logged applying the
    # e-stop and the probe has the ground truth of the second after it.
    def engaged() -> list[str]:
        return [line for line in proc.output().splitlines() if 'e-stop ENGAGED' in line]

    def stop_time() -> float:
        return float(engaged()[0].rsplit('at t=', 1)[1].split()[0])

    _command_until(probe, 0.3, lambda: bool(engaged()) and probe.poses[-1][0] >= stop_time() + 1.0,
                   'the e-stop applied and 1 s of ground truth after it')
    # Measured from the sim time at which the simulator applied the e-stop (it logs it): the
    # probe's own estimate of "now" in sim time was once 1 s early on a loaded machine, its
    # pose stream delivered late, which made a robot at full speed look still accelerating.
    assert len(engaged()) == 1, proc.output()
    t_stop = stop_time()
    assert t_stop >= probe.sim_time_at(sent) - 0.05  # applied after it was sent, not before
    with probe.lock:
        poses = [p for p in probe.poses if p[0] >= t_stop - 0.2]
    speeds = _speeds(poses)
    assert speeds[0][1] > 0.25, f'not moving before the stop: {speeds[:3]}'
    stopped_at = next((t for t, v in speeds if t > t_stop and v < 0.01), math.inf)
    assert stopped_at - t_stop <= 0.2, (
        f'stopped {stopped_at - t_stop:.3f} s after the simulator applied /e_stop at sim '
        f't={t_stop:.3f}; speeds {[(round(t, 2), round(v, 3)) for t, v in speeds]}')
    held = [p for p in poses if p[0] >= stopped_at]
    assert math.hypot(held[-1][1] - held[0][1], held[-1][2] - held[0][2]) < 0.005
    # Released: a fresh /cmd_vel moves it again.
    probe.send_e_stop(False)
    with probe.lock:
        x_before = probe.poses[-1][1]
    _command_until(probe, 0.3, lambda: probe.poses[-1][1] - x_before > 0.1,
                   'the robot to move 0.1 m after the release')
    assert 'e-stop released' in proc.output(), proc.output()


def test_scan_beam_reads_the_wall_and_stamps_follow_the_clock(
    sim_world: Callable[..., tuple[SimProcess, Probe]],
) -> None:
    _proc, probe = sim_world('--world', 'real_room', '--duration', '60', '--seed', '3')
    probe.wait_until(lambda: len(probe.scans) >= 5, WALL_WAIT, '/scan')
    probe.wait_until(lambda: len(probe.latched) == 2, WALL_WAIT, '/sim/info and the map')
    with probe.lock:
        scan = probe.scans[-1]
        clock_count = probe.clock_count
        info = json.loads(probe.latched['/sim/info'].data)
        grid = probe.latched['/ground_truth/map']
    assert scan.header.frame_id == 'base_scan'
    assert len(scan.ranges) == 360
    assert scan.angle_increment == pytest.approx(2 * math.pi / 360)
    stamp = scan.header.stamp.sec + scan.header.stamp.nanosec * 1e-9
    assert stamp > 0 and round(stamp * 100) == pytest.approx(stamp * 100, abs=1e-6)  # on a tick
    assert clock_count > 10
    # The robot stands at (0.8, 0.8) facing +x; its lidar is 6.4 cm behind base_link. The beam
    # pointing backwards (-pi, index 0) meets the west wall's face (x = 0.05) at 0.686 m, the
    # one pointing right (-pi/2, index 90) the south wall's face (y = 0.05) at 0.75 m. Noise in
    # this world: sigma 2 cm + 1 % of range, 3 % dropouts (NaN).
    for index, expected in ((0, 0.686), (90, 0.75)):
        readings = [s.ranges[index] for s in probe.scans if not math.isnan(s.ranges[index])]
        assert readings, f'beam {index} dropped out in every scan'
        for r in readings:
            assert r == pytest.approx(expected, abs=4 * (0.02 + 0.01 * expected))
    assert info['world'] == 'real_room' and info['seed'] == 3
    assert info['start'] == {'x': 0.8, 'y': 0.8, 'yaw': 0.0}
    assert grid.header.frame_id == 'map' and grid.info.resolution == pytest.approx(0.05)
    # Sim time runs at real time: compare /clock with the wall clock over a second.
    import time

    with probe.lock:
        c0, w0 = probe.clock, time.monotonic()
    time.sleep(1.0)
    with probe.lock:
        c1, w1 = probe.clock, time.monotonic()
    assert (c1 - c0) / (w1 - w0) == pytest.approx(1.0, abs=0.1)
