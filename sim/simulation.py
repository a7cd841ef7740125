"""The simulation without ROS: physics, chassis, sensors, collisions, recorded path.

``Simulation.step()`` advances one control tick (10 ms, five 2 ms physics steps) and says which
outputs fell due on it. The ROS bridge (``sim.bridge``) calls it in real time and publishes;
tests and ``sim route`` call it as fast as they like with the driver's control law in the same
process, which is deterministic for a given seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from .model import TIMESTEP, compile_world
from .robot import LIMITS, ROBOT, Chassis, Limits, RobotSpec, WheelSlip
from .sensors import (
    DEPTH,
    F32,
    LIDAR,
    DepthCamera,
    DepthSpec,
    Lidar,
    LidarSpec,
    WheelOdometry,
    wrap,
)
from .worlds import Pose2D, World

TICK_NS = 10_000_000  # control tick: 10 ms
TICK = TICK_NS / 1e9
ODOM_EVERY = 2  # 50 Hz odometry and ground truth
CLOCK_EVERY = 2  # 50 Hz /clock: every sensor stamp falls on a published clock tick
PATH_EVERY = 10  # 10 Hz recorded path


@dataclass(frozen=True)
class CollisionEvent:
    """The robot started touching an obstacle.

    Attributes:
        time: sim time (s).
        obstacle: the obstacle's name (as in ``sim.worlds``).
        x: contact point x in the map frame.
        y: contact point y.
        speed: the robot's speed when it hit (m/s).
    """

    time: float
    obstacle: str
    x: float
    y: float
    speed: float


@dataclass
class Frame:
    """What one tick produced. ``scan``/``cloud`` are None when not due (or switched off)."""

    stamp_ns: int
    clock_due: bool = False
    odom_due: bool = False
    scan: F32 | None = None
    cloud: F32 | None = None
    collisions: list[CollisionEvent] = field(default_factory=list)


class CollisionMonitor:
    """Turns MuJoCo contacts of the robot into collision events.

    A contact with an obstacle counts as one collision until the robot has been clear of that
    obstacle for ``release_after`` seconds (grinding along a wall is one collision, not 100).
    """

    def __init__(self, model: mujoco.MjModel, robot_geoms: frozenset[int],
                 release_after: float = 0.5) -> None:
        self.model = model
        self.robot_geoms = robot_geoms
        self.release_after = release_after
        self._last_touch: dict[str, float] = {}
        self.events: list[CollisionEvent] = []

    def check(self, data: mujoco.MjData, now: float, speed: float) -> list[CollisionEvent]:
        """New collision events at sim time ``now``."""
        new: list[CollisionEvent] = []
        for k in range(data.ncon):
            contact = data.contact[k]
            g1, g2 = int(contact.geom1), int(contact.geom2)
            other = g2 if g1 in self.robot_geoms else g1
            if other in self.robot_geoms:
                continue
            name = mujoco.mj_id2name(self.model, mujoco.mjtObj.mjOBJ_GEOM, other) or f'geom{other}'
            last = self._last_touch.get(name)
            if last is None or now - last > self.release_after:
                event = CollisionEvent(now, name, float(contact.pos[0]), float(contact.pos[1]),
                                       speed)
                new.append(event)
                self.events.append(event)
            self._last_touch[name] = now
        return new


class Simulation:
    """One world with the robot in it.

    Args:
        world: the world.
        seed: seeds every noise stream (lidar, depth, odometry, slip), independently.
        lidar: compute scans (10 Hz).
        depth: compute depth clouds (5 Hz).
        robot: robot dimensions and sensor mounts.
        limits: chassis limits.
        start: start pose (default: the world's).
    """

    def __init__(
        self,
        world: World,
        seed: int = 0,
        *,
        lidar: bool = True,
        depth: bool = True,
        robot: RobotSpec = ROBOT,
        limits: Limits = LIMITS,
        start: Pose2D | None = None,
        lidar_spec: LidarSpec = LIDAR,
        depth_spec: DepthSpec = DEPTH,
    ) -> None:
        self.world = world
        self.seed = seed
        self.robot = robot
        compiled = compile_world(world, robot)
        self.model = compiled.model
        self.data = mujoco.MjData(self.model)
        self.start = start or world.start
        self.data.qpos[:3] = (self.start.x, self.start.y, self.start.yaw)
        mujoco.mj_forward(self.model, self.data)
        streams = np.random.SeedSequence(seed).spawn(4)
        rng_lidar, rng_depth, rng_odom, rng_slip = (np.random.default_rng(s) for s in streams)
        noise = world.noise
        self.chassis = Chassis(limits)
        self.slip = WheelSlip(noise.slip_mean, noise.slip_sigma, noise.slip_tau, rng_slip)
        self.odometry = WheelOdometry(self.start.x, self.start.y, self.start.yaw, robot, noise,
                                      rng_odom)
        self.lidar = Lidar(self.model, self.data, compiled.robot_body, robot.lidar, noise,
                           rng_lidar, lidar_spec)
        self.camera = DepthCamera(self.model, self.data, compiled.robot_body, robot.camera, noise,
                                  rng_depth, depth_spec)
        self.lidar_on = lidar
        self.depth_on = depth
        self.collisions = CollisionMonitor(self.model, compiled.robot_geoms)
        self.ticks = 0
        self._substeps = round(TICK / TIMESTEP)
        self._scan_every = round(1.0 / (lidar_spec.rate * TICK))
        self._depth_every = round(1.0 / (depth_spec.rate * TICK))
        self.path: list[tuple[float, ...]] = []
        self.estops = 0
        self.distance = 0.0
        self._record()

    # -- inputs -------------------------------------------------------------------------------

    @property
    def time(self) -> float:
        """Sim time (s)."""
        return self.ticks * TICK

    @property
    def stamp_ns(self) -> int:
        """Sim time (ns), exact."""
        return self.ticks * TICK_NS

    def command(self, v: float, w: float) -> None:
        """A velocity command (``/cmd_vel``: linear.x, angular.z) at the current sim time."""
        self.chassis.command(v, w, self.time)

    def set_estop(self, on: bool) -> None:
        """Engage or release the emergency stop."""
        if on and not self.chassis.estop:
            self.estops += 1
        self.chassis.set_estop(on)

    # -- state ----------------------------------------------------------------------------------

    def pose(self) -> Pose2D:
        """Ground-truth pose of base_link in the map frame (yaw wrapped)."""
        q = self.data.qpos
        return Pose2D(float(q[0]), float(q[1]), wrap(float(q[2])))

    def body_velocity(self) -> tuple[float, float, float]:
        """Ground-truth (forward, lateral, yaw rate) velocity in base_link."""
        q, qd = self.data.qpos, self.data.qvel
        c, s = math.cos(q[2]), math.sin(q[2])
        return (float(c * qd[0] + s * qd[1]), float(-s * qd[0] + c * qd[1]), float(qd[2]))

    # -- stepping -------------------------------------------------------------------------------

    def step(self) -> Frame:
        """Advance one tick (10 ms); the outputs that fell due."""
        v, w = self.chassis.update(self.time, TICK)
        slip = self.slip.update(TICK, self.chassis.accel)
        ctrl = self.data.ctrl
        ctrl[0] = v * (1.0 - slip)
        ctrl[1] = 0.0
        ctrl[2] = w * (1.0 - slip)
        q, qd = self.data.qpos, self.data.qvel
        x0, y0 = float(q[0]), float(q[1])
        speed0 = math.hypot(float(qd[0]), float(qd[1]))  # before a contact slows it
        mujoco.mj_step(self.model, self.data, nstep=self._substeps)
        self.ticks += 1
        x, y, yaw = float(q[0]), float(q[1]), float(q[2])
        self.distance += math.hypot(x - x0, y - y0)
        self.odometry.update(x, y, yaw, slip, TICK)
        frame = Frame(self.stamp_ns)
        if self.data.ncon:
            frame.collisions = self.collisions.check(self.data, self.time, speed0)
        t = self.ticks
        frame.clock_due = t % CLOCK_EVERY == 0
        frame.odom_due = t % ODOM_EVERY == 0
        if self.lidar_on and t % self._scan_every == 0:
            frame.scan = self.lidar.measure(x, y, yaw)
        if self.depth_on and t % self._depth_every == 0:
            frame.cloud = self.camera.measure(x, y, yaw)
        if t % PATH_EVERY == 0:
            self._record()
        return frame

    def _record(self) -> None:
        p, o = self.pose(), self.odometry
        self.path.append((self.time, p.x, p.y, p.yaw, o.x, o.y, o.yaw))

    # -- results --------------------------------------------------------------------------------

    def odometry_error(self) -> tuple[float, float]:
        """(position error (m), heading error (rad)) of the odometry against ground truth."""
        p, o = self.pose(), self.odometry
        s = self.start
        c, sn = math.cos(s.yaw), math.sin(s.yaw)
        ox, oy = s.x + c * o.x - sn * o.y, s.y + sn * o.x + c * o.y
        return math.hypot(ox - p.x, oy - p.y), abs(wrap(s.yaw + o.yaw - p.yaw))

    def summary(self) -> dict[str, Any]:
        """A JSON-able summary of the run so far."""
        p = self.pose()
        pos_err, yaw_err = self.odometry_error()
        return {
            'world': self.world.name,
            'seed': self.seed,
            'sim_seconds': round(self.time, 3),
            'collisions': len(self.collisions.events),
            'collision_events': [
                {'time': round(e.time, 3), 'obstacle': e.obstacle, 'x': round(e.x, 3),
                 'y': round(e.y, 3), 'speed': round(e.speed, 3)}
                for e in self.collisions.events
            ],
            'estops': self.estops,
            'distance': round(self.distance, 3),
            'final_pose': {'x': round(p.x, 4), 'y': round(p.y, 4), 'yaw': round(p.yaw, 4)},
            'odometry_error': {'position': round(pos_err, 4), 'yaw': round(yaw_err, 4)},
        }

    def path_csv(self) -> str:
        """The recorded path (10 Hz) as CSV: ground truth in map, odometry in odom frame."""
        s = self.start
        lines = ['t,x,y,yaw,odom_x,odom_y,odom_yaw,start_x,start_y,start_yaw']
        for row in self.path:
            lines.append(','.join(f'{v:.4f}' for v in (*row, s.x, s.y, s.yaw)))
        return '\n'.join(lines) + '\n'
