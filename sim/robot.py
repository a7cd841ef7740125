"""The differential-drive robot: dimensions, sensor mounts, limits, and the chassis controller.

The robot is TurtleBot3-Waffle sized. Its chassis is one rigid body on three planar joints
(x, y, yaw). Three MuJoCo velocity actuators act through a site at ``base_link``: forward along
the body's x axis, yaw about z, and a stiff lateral one held at zero that stands in for the
wheels' grip (a push harder than its force limit slides the robot sideways, as tyres would).
The wheels themselves are drawn but carry no contacts: wheel rotation is what the odometry
model (``sim.sensors.WheelOdometry``) reconstructs from the body's motion.

``Chassis`` turns ``/cmd_vel`` and ``/e_stop`` into the actuators' set-points: speed and
acceleration limits, a command timeout, the emergency stop (a harder deceleration, then held at
zero while the stop is on) and wheel slip (the body moves a fraction less than the wheels turn).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mount:
    """A sensor frame fixed on ``base_link`` (translation only; see ``sim/README.md``)."""

    frame_id: str
    x: float
    y: float
    z: float


@dataclass(frozen=True)
class RobotSpec:
    """Dimensions and mass of the robot.

    ``base_link`` is on the floor, midway between the wheel contact points; x forward, y left,
    z up. The chassis is centred on it.
    """

    chassis_half: tuple[float, float, float] = (0.14, 0.15, 0.07)
    chassis_z: float = 0.08
    mass: float = 1.8
    wheel_radius: float = 0.033
    wheel_separation: float = 0.287
    lidar: Mount = Mount('base_scan', -0.064, 0.0, 0.18)
    # The camera's optical frame (z forward, x right, y down) at this point of base_link.
    camera: Mount = Mount('camera_depth_optical_frame', 0.12, 0.0, 0.25)

    @property
    def footprint_radius(self) -> float:
        """Radius of the circle around base_link that holds the whole footprint (m)."""
        return math.hypot(self.chassis_half[0], self.chassis_half[1])


@dataclass(frozen=True)
class Limits:
    """Velocity and acceleration limits, command timeout and emergency-stop deceleration."""

    max_linear: float = 0.5
    max_angular: float = 1.8
    linear_accel: float = 1.0
    angular_accel: float = 3.0
    estop_linear_decel: float = 5.0
    estop_angular_decel: float = 15.0
    cmd_timeout: float = 0.5


ROBOT = RobotSpec()
LIMITS = Limits()


class WheelSlip:
    """Fraction of wheel travel lost to slip: an Ornstein-Uhlenbeck process clipped to [0, 0.5].

    Grows with acceleration as well (wheels spin up before the body follows), which is where a
    real robot slips most.
    """

    def __init__(self, mean: float, sigma: float, tau: float, rng: np.random.Generator) -> None:
        self.mean = mean
        self.sigma = sigma
        self.tau = tau
        self.rng = rng
        self.value = mean

    @property
    def enabled(self) -> bool:
        """Whether this world has slip at all."""
        return self.mean > 0.0 or self.sigma > 0.0

    def update(self, dt: float, accel: float) -> float:
        """Advance by ``dt`` with the current linear acceleration; the new slip fraction."""
        if not self.enabled:
            return 0.0
        a = math.exp(-dt / self.tau)
        noise = self.sigma * math.sqrt(1.0 - a * a) * float(self.rng.standard_normal())
        self.value = self.mean + a * (self.value - self.mean) + noise
        boost = 0.05 * min(abs(accel), 2.0)
        return min(max(self.value + boost, 0.0), 0.5)


class Chassis:
    """From commands to actuator set-points, once per control tick.

    Args:
        limits: speed, acceleration, timeout and e-stop parameters.
    """

    def __init__(self, limits: Limits = LIMITS) -> None:
        self.limits = limits
        self.cmd = (0.0, 0.0)
        self.cmd_time = -math.inf
        self.estop = False
        self.v = 0.0  # set-points after limits (the wheels' speed)
        self.w = 0.0
        self.accel = 0.0

    def command(self, v: float, w: float, now: float) -> None:
        """A ``/cmd_vel`` arrived at sim time ``now``; ignored while the e-stop is on."""
        if self.estop:
            return
        if not (math.isfinite(v) and math.isfinite(w)):
            return  # a NaN command must never reach the actuators
        self.cmd = (v, w)
        self.cmd_time = now

    def set_estop(self, on: bool) -> None:
        """Engage or release the emergency stop.

        Engaging drops the current command, so releasing does not resume an old one: the robot
        moves again only on a ``/cmd_vel`` received after the release.
        """
        self.estop = on
        if on:
            self.cmd = (0.0, 0.0)
            self.cmd_time = -math.inf

    def update(self, now: float, dt: float) -> tuple[float, float]:
        """New set-points (v, w) for the next ``dt`` seconds."""
        lim = self.limits
        if self.estop or now - self.cmd_time > lim.cmd_timeout:
            target_v, target_w = 0.0, 0.0
        else:
            target_v = min(max(self.cmd[0], -lim.max_linear), lim.max_linear)
            target_w = min(max(self.cmd[1], -lim.max_angular), lim.max_angular)
        if self.estop:
            dv, dw = lim.estop_linear_decel * dt, lim.estop_angular_decel * dt
        else:
            dv, dw = lim.linear_accel * dt, lim.angular_accel * dt
        old_v = self.v
        self.v += min(max(target_v - self.v, -dv), dv)
        self.w += min(max(target_w - self.w, -dw), dw)
        self.accel = (self.v - old_v) / dt if dt > 0 else 0.0
        return self.v, self.w
