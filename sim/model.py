"""MJCF for a world with the robot in it, and the compiled MuJoCo model."""

from __future__ import annotations

from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

import mujoco

from .robot import ROBOT, RobotSpec
from .worlds import Box, World

TIMESTEP = 0.002  # s; 500 Hz physics

_RGBA = {
    'wall': '0.75 0.75 0.72 1',
    'furniture': '0.69 0.53 0.31 1',
    'machine': '0.31 0.47 0.63 1',
    'pillar': '0.75 0.25 0.25 1',
}

# Response time of the velocity actuators (s): short enough that the set-point, not the
# actuator, is what limits acceleration; long enough to stay stable at the 2 ms step.
_ACTUATOR_TAU = 0.02


def _f(*values: float) -> str:
    return ' '.join(f'{v:.6g}' for v in values)


def world_mjcf(world: World, robot: RobotSpec = ROBOT) -> str:
    """The MJCF text of ``world`` with the robot at the world's start pose.

    Obstacles keep their names from ``sim.worlds`` (they are what ``/collisions`` reports).
    The robot's body is ``robot``; its planar joints are ``x``, ``y``, ``yaw``, so that
    ``qpos`` is exactly (x, y, yaw) in the map frame.
    """
    xmin, ymin, xmax, ymax = world.bounds
    geoms = []
    for o in world.obstacles:
        rgba = _RGBA.get(o.kind, '0.6 0.6 0.6 1')
        if isinstance(o, Box):
            geoms.append(
                f'    <geom name={quoteattr(o.name)} type="box" '
                f'pos="{_f(o.x, o.y, o.height / 2)}" size="{_f(o.sx / 2, o.sy / 2, o.height / 2)}" '
                f'euler="{_f(0, 0, o.yaw)}" rgba="{rgba}"/>'
            )
        else:
            geoms.append(
                f'    <geom name={quoteattr(o.name)} type="cylinder" '
                f'pos="{_f(o.x, o.y, o.height / 2)}" size="{_f(o.radius, o.height / 2)}" '
                f'rgba="{rgba}"/>'
            )
    hx, hy, hz = robot.chassis_half
    inertia_z = robot.mass * ((2 * hx) ** 2 + (2 * hy) ** 2) / 12
    kv_linear = robot.mass / _ACTUATOR_TAU
    kv_yaw = inertia_z / _ACTUATOR_TAU
    wr, ws = robot.wheel_radius, robot.wheel_separation
    lid, cam = robot.lidar, robot.camera
    floor_half = (max(xmax - xmin, ymax - ymin) / 2) + 2.0
    return f"""<mujoco model={quoteattr('rory_sim_' + world.name)}>
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{TIMESTEP}" integrator="implicitfast"/>
  <worldbody>
    <light pos="{_f((xmin + xmax) / 2, (ymin + ymax) / 2, 8)}" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" pos="{_f((xmin + xmax) / 2, (ymin + ymax) / 2, 0)}"
          size="{_f(floor_half, floor_half, 0.1)}" rgba="0.9 0.9 0.88 1"
          contype="0" conaffinity="0"/>
{chr(10).join(geoms)}
    <body name="robot">
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="y" type="slide" axis="0 1 0"/>
      <joint name="yaw" type="hinge" axis="0 0 1"/>
      <inertial pos="0 0 {robot.chassis_z}" mass="{robot.mass}"
                diaginertia="{_f(inertia_z / 2, inertia_z / 2, inertia_z)}"/>
      <geom name="chassis" type="box" pos="0 0 {robot.chassis_z}" size="{_f(hx, hy, hz)}"
            rgba="0.2 0.2 0.22 1" mass="0" friction="0.3 0.005 0.0001"/>
      <geom name="wheel_left" type="cylinder" pos="{_f(0, ws / 2, wr)}" euler="1.5708 0 0"
            size="{_f(wr, 0.009)}" rgba="0.1 0.1 0.1 1" contype="0" conaffinity="0" mass="0"/>
      <geom name="wheel_right" type="cylinder" pos="{_f(0, -ws / 2, wr)}" euler="1.5708 0 0"
            size="{_f(wr, 0.009)}" rgba="0.1 0.1 0.1 1" contype="0" conaffinity="0" mass="0"/>
      <geom name="lidar" type="cylinder" pos="{_f(lid.x, lid.y, lid.z - 0.02)}"
            size="0.035 0.02" rgba="0.1 0.1 0.1 1" contype="0" conaffinity="0" mass="0"/>
      <geom name="camera" type="box" pos="{_f(cam.x - 0.01, cam.y, cam.z)}"
            size="0.01 0.045 0.012" rgba="0.1 0.1 0.1 1" contype="0" conaffinity="0" mass="0"/>
      <site name="base_link" pos="0 0 0"/>
      <site name="{lid.frame_id}" pos="{_f(lid.x, lid.y, lid.z)}"/>
      <site name="{cam.frame_id}" pos="{_f(cam.x, cam.y, cam.z)}"/>
    </body>
  </worldbody>
  <actuator>
    <velocity name="drive" site="base_link" gear="1 0 0 0 0 0" kv="{kv_linear:.6g}"
              forcerange="-25 25"/>
    <velocity name="grip" site="base_link" gear="0 1 0 0 0 0" kv="{3 * kv_linear:.6g}"
              forcerange="-15 15"/>
    <velocity name="turn" site="base_link" gear="0 0 0 0 0 1" kv="{kv_yaw:.6g}"
              forcerange="-1 1"/>
  </actuator>
</mujoco>
"""


@dataclass
class CompiledWorld:
    """A compiled model with the ids the simulation needs."""

    model: mujoco.MjModel
    robot_body: int
    robot_geoms: frozenset[int]
    floor_geom: int


def compile_world(world: World, robot: RobotSpec = ROBOT) -> CompiledWorld:
    """Compile ``world`` into a MuJoCo model.

    Raises:
        ValueError: MuJoCo rejected the generated MJCF (the message names the world).
    """
    try:
        model = mujoco.MjModel.from_xml_string(world_mjcf(world, robot))
    except Exception as err:  # mujoco raises plain ValueError/Exception subclasses
        raise ValueError(f'world {world.name!r}: MuJoCo rejected the model: {err}') from err
    body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, 'robot')
    geoms = frozenset(g for g in range(model.ngeom) if int(model.geom_bodyid[g]) == body)
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, 'floor')
    return CompiledWorld(model, body, geoms, floor)
