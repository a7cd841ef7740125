"""The chassis: limits, command timeout, e-stop, collisions (synchronous, no ROS)."""

from __future__ import annotations

import math

import pytest

from sim.robot import LIMITS, Chassis
from sim.simulation import TICK, Simulation
from sim.worlds import Pose2D, get_world


def _sim(pose: Pose2D | None = None) -> Simulation:
    # office_small has no wheel slip: commanded and actual speeds agree.
    return Simulation(get_world('office_small'), lidar=False, depth=False, start=pose)


def _run(sim: Simulation, seconds: float, cmd: tuple[float, float] | None = None) -> None:
    for k in range(round(seconds / TICK)):
        if cmd is not None and k % 5 == 0:
            sim.command(*cmd)
        sim.step()


def test_cmd_vel_moves_the_robot_as_commanded() -> None:
    sim = _sim()
    _run(sim, 2.0, (0.25, 0.0))
    v, lateral, w = sim.body_velocity()
    assert v == pytest.approx(0.25, abs=0.005)
    assert abs(lateral) < 1e-3 and abs(w) < 1e-3
    start = sim.world.start
    p = sim.pose()
    assert p.x - start.x == pytest.approx(0.25 * 2.0 - 0.25 ** 2 / 2, abs=0.01)
    _run(sim, 1.0, (0.0, 1.0))
    assert sim.body_velocity()[2] == pytest.approx(1.0, abs=0.01)


def test_speed_and_acceleration_limits() -> None:
    sim = _sim()
    _run(sim, 0.2, (5.0, 0.0))
    assert sim.body_velocity()[0] == pytest.approx(LIMITS.linear_accel * 0.2, abs=0.03)
    _run(sim, 1.0, (5.0, 0.0))
    assert sim.body_velocity()[0] == pytest.approx(LIMITS.max_linear, abs=0.01)
    sim2 = _sim()
    _run(sim2, 2.0, (0.0, 9.0))
    assert sim2.body_velocity()[2] == pytest.approx(LIMITS.max_angular, abs=0.02)


def test_command_timeout_stops_the_robot() -> None:
    sim = _sim()
    sim.command(0.3, 0.0)
    _run(sim, LIMITS.cmd_timeout - 0.05)
    assert sim.body_velocity()[0] > 0.25
    _run(sim, 0.5)
    assert abs(sim.body_velocity()[0]) < 1e-3


def test_e_stop_stops_within_0_2_s_holds_and_needs_a_new_command() -> None:
    sim = _sim()
    _run(sim, 2.0, (LIMITS.max_linear, 0.0))
    assert sim.body_velocity()[0] == pytest.approx(LIMITS.max_linear, abs=0.01)
    sim.set_estop(True)
    t0 = sim.time
    while abs(sim.body_velocity()[0]) > 0.005:
        sim.command(LIMITS.max_linear, 0.0)  # ignored while the stop is on
        sim.step()
        assert sim.time - t0 <= 0.2, 'still moving 0.2 s after the e-stop'
    held = sim.pose()
    _run(sim, 2.0, (0.3, 0.5))
    assert math.hypot(sim.pose().x - held.x, sim.pose().y - held.y) < 1e-3
    sim.set_estop(False)
    _run(sim, 0.5)  # released, but the old command is gone
    assert abs(sim.body_velocity()[0]) < 1e-3
    _run(sim, 0.5, (0.2, 0.0))
    assert sim.body_velocity()[0] == pytest.approx(0.2, abs=0.01)
    assert sim.estops == 1


def test_nan_commands_are_ignored() -> None:
    chassis = Chassis()
    chassis.command(0.2, 0.0, 0.0)
    chassis.command(math.nan, 0.0, 0.01)
    assert chassis.cmd == (0.2, 0.0)


def test_driving_into_a_wall_is_one_collision_and_the_wall_holds() -> None:
    sim = Simulation(get_world('real_room'), lidar=False, depth=False,
                     start=Pose2D(0.8, 0.8, math.pi))
    _run(sim, 5.0, (0.3, 0.0))  # the west wall's face is 0.6 m behind the chassis front
    events = sim.collisions.events
    assert [e.obstacle for e in events] == ['wall_west_0']
    assert events[0].speed == pytest.approx(0.3, abs=0.05)
    assert events[0].x == pytest.approx(0.05, abs=0.02)
    # Pushed against the wall the whole time, it never went through.
    assert sim.pose().x > 0.05 + 0.14 - 0.02
    assert sim.summary()['collisions'] == 1
    _run(sim, 2.0, (-0.2, 0.0))  # back off, come back: a second collision
    _run(sim, 3.0, (0.3, 0.0))
    assert len(sim.collisions.events) == 2
