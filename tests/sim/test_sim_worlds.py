"""The worlds as data and as MuJoCo models: names, clearances, routes, goals."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from sim.model import compile_world
from sim.robot import ROBOT
from sim.worlds import WORLDS, Box, Cylinder, get_world, walls

NAMES = sorted(WORLDS)


def test_the_three_worlds_exist() -> None:
    assert NAMES == ['office_small', 'real_room', 'workshop']
    with pytest.raises(KeyError, match=r'unknown world .*known: office_small, real_room'):
        get_world('office')


@pytest.mark.parametrize('name', NAMES)
def test_model_compiles_with_every_obstacle_named(name: str) -> None:
    world = get_world(name)
    compiled = compile_world(world)
    names = [o.name for o in world.obstacles]
    assert len(names) == len(set(names)), 'obstacle names must be unique'
    for n in names:
        assert mujoco.mj_name2id(compiled.model, mujoco.mjtObj.mjOBJ_GEOM, n) >= 0, n
    # Every obstacle is tall enough for the lidar (0.18 m) to see it.
    assert min(o.height for o in world.obstacles) > ROBOT.lidar.z + 0.1
    assert compiled.model.nu == 3


@pytest.mark.parametrize('name', NAMES)
def test_start_route_and_goals_leave_room_for_the_robot(name: str) -> None:
    world = get_world(name)
    margin = ROBOT.footprint_radius + 0.1
    assert world.route_clearance() >= margin
    for goal_name, goal in world.goals.items():
        clearance = float(world.clearance(np.array(goal.x), np.array(goal.y)))
        assert clearance >= margin, goal_name
    assert world.default_goal in world.goals


def test_route_lengths_map_a_good_part_in_60_to_130_s_at_0_3_m_s() -> None:
    for world in WORLDS.values():
        assert 15.0 <= world.route_length() <= 38.0, world.name


def test_workshop_goal_lies_behind_nine_pillars() -> None:
    world = get_world('workshop')
    pillars = [o for o in world.obstacles if isinstance(o, Cylinder) and o.kind == 'pillar']
    assert len(pillars) == 9
    start, goal = world.start, world.goals['behind_pillars']
    # The straight line from start to goal runs into a pillar: reaching it takes planning.
    s = np.linspace(0.0, 1.0, 400)
    line = world.clearance(start.x + s * (goal.x - start.x), start.y + s * (goal.y - start.y))
    assert float(line.min()) < ROBOT.footprint_radius
    xs = sorted({p.x for p in pillars})
    assert xs[0] > start.x and xs[-1] < goal.x


def test_real_room_has_one_obstacle_and_noisier_sensors() -> None:
    world = get_world('real_room')
    furniture = [o for o in world.obstacles if o.kind != 'wall']
    assert [o.name for o in furniture] == ['obstacle']
    noise = world.noise
    assert noise.lidar_dropout > 0 and noise.slip_mean > 0
    assert noise.lidar_sigma > get_world('office_small').noise.lidar_sigma


def test_walls_are_cut_by_doors_and_close_corners() -> None:
    pieces = walls('w', (0.0, 0.0), (4.0, 0.0), doors=[(2.0, 1.0)])
    assert [(round(p.x - p.sx / 2, 3), round(p.x + p.sx / 2, 3)) for p in pieces] == [
        (-0.05, 1.5), (2.5, 4.05)]
    assert all(isinstance(p, Box) and p.kind == 'wall' for p in pieces)
    with pytest.raises(ValueError, match=r"wall 'v'.*not axis-aligned"):
        walls('v', (0.0, 0.0), (1.0, 1.0))
    with pytest.raises(ValueError, match='does not fit'):
        walls('d', (0.0, 0.0), (1.0, 0.0), doors=[(0.9, 0.5)])


def test_box_and_cylinder_distances() -> None:
    box = Box('b', 1.0, 1.0, 2.0, 1.0, 1.0, yaw=math.pi / 2)  # 1 wide along x, 2 along y
    assert float(box.distance(np.array(1.0), np.array(1.0))) == pytest.approx(-0.5)
    assert float(box.distance(np.array(2.0), np.array(1.0))) == pytest.approx(0.5)
    assert float(box.distance(np.array(1.0), np.array(2.5))) == pytest.approx(0.5)
    cyl = Cylinder('c', 0.0, 0.0, 0.5, 1.0)
    assert float(cyl.distance(np.array(3.0), np.array(4.0))) == pytest.approx(4.5)
