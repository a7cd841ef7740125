"""Sensors: 2D lidar and depth camera from ``mujoco.mj_multiRay``, wheel odometry with drift.

No rendering and no OpenGL: every range is a ray cast against the geometry. The robot's own
body is excluded from every ray. Noise comes from ``numpy.random.Generator`` streams the
simulation seeds, one per sensor, so a run is repeatable and switching one sensor off does not
change another's noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np
import numpy.typing as npt

from .robot import Mount, RobotSpec
from .worlds import Noise

F32 = npt.NDArray[np.float32]


def wrap(angle: float) -> float:
    """``angle`` wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class LidarSpec:
    """A 360-degree 2D lidar (LaserScan conventions; angles counter-clockwise from +x).

    Beam ``i`` points at ``angle_min + i * angle_increment`` in ``base_scan``.
    """

    beams: int = 360
    range_min: float = 0.12
    range_max: float = 10.0
    rate: float = 10.0

    @property
    def angle_min(self) -> float:
        """Angle of the first beam (rad)."""
        return -math.pi

    @property
    def angle_increment(self) -> float:
        """Angle between beams (rad)."""
        return 2 * math.pi / self.beams

    @property
    def angle_max(self) -> float:
        """Angle of the last beam (rad)."""
        return self.angle_min + (self.beams - 1) * self.angle_increment


@dataclass(frozen=True)
class DepthSpec:
    """A pinhole depth camera (ROS optical frame: z forward, x right, y down)."""

    width: int = 80
    height: int = 60
    hfov_deg: float = 60.0
    range_min: float = 0.3
    range_max: float = 5.0
    rate: float = 5.0

    @property
    def fx(self) -> float:
        """Focal length in pixels (square pixels: fy == fx)."""
        return (self.width / 2) / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def cx(self) -> float:
        """Principal point x (pixels; pixel centres at integer coordinates)."""
        return (self.width - 1) / 2

    @property
    def cy(self) -> float:
        """Principal point y (pixels)."""
        return (self.height - 1) / 2


LIDAR = LidarSpec()
DEPTH = DepthSpec()


def _mount_in_world(mount: Mount, x: float, y: float, yaw: float) -> npt.NDArray[np.float64]:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([x + c * mount.x - s * mount.y, y + s * mount.x + c * mount.y, mount.z])


class Lidar:
    """360 beams in the horizontal plane of ``base_scan``.

    Range noise is Gaussian, ``sigma + sigma_rel * range``; a dropout is a beam that returns
    nothing (NaN); no return within ``range_max`` is +inf (REP 117).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        robot_body: int,
        mount: Mount,
        noise: Noise,
        rng: np.random.Generator,
        spec: LidarSpec = LIDAR,
    ) -> None:
        self.model, self.data, self.body = model, data, robot_body
        self.mount, self.noise, self.rng, self.spec = mount, noise, rng, spec
        n = spec.beams
        self.angles = spec.angle_min + np.arange(n) * spec.angle_increment
        self._vec = np.zeros((n, 3))
        self._geomid = np.zeros(n, np.int32)
        self._dist = np.zeros(n)

    def true_ranges(self, x: float, y: float, yaw: float) -> npt.NDArray[np.float64]:
        """Noise-free ranges from the lidar at robot pose (x, y, yaw); -1 where nothing is hit."""
        pnt = _mount_in_world(self.mount, x, y, yaw)
        a = self.angles + yaw
        self._vec[:, 0] = np.cos(a)
        self._vec[:, 1] = np.sin(a)
        mujoco.mj_multiRay(
            self.model, self.data, pnt, self._vec.reshape(-1), None, 1, self.body,
            self._geomid, self._dist, None, self.spec.beams, self.spec.range_max,
        )
        return self._dist.copy()

    def measure(self, x: float, y: float, yaw: float) -> F32:
        """One noisy scan (float32, one range per beam)."""
        true = self.true_ranges(x, y, yaw)
        nz = self.noise
        # Draw the same amount of randomness every scan so that the stream stays aligned.
        gauss = self.rng.standard_normal(true.size)
        drop = self.rng.random(true.size)
        hit = (true >= 0.0) & (true <= self.spec.range_max)
        ranges = true + gauss * (nz.lidar_sigma + nz.lidar_sigma_rel * np.maximum(true, 0.0))
        ranges = np.where(hit, np.maximum(ranges, 0.0), np.inf)
        if nz.lidar_dropout > 0.0:
            ranges = np.where(drop < nz.lidar_dropout, np.nan, ranges)
        out: F32 = ranges.astype(np.float32)
        return out


class DepthCamera:
    """An organised point cloud (height x width x 3, float32) in the optical frame.

    Depth noise follows the Kinect-style model ``sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2`` m;
    pixels with no return in [range_min, range_max], or dropped, are NaN.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        data: mujoco.MjData,
        robot_body: int,
        mount: Mount,
        noise: Noise,
        rng: np.random.Generator,
        spec: DepthSpec = DEPTH,
    ) -> None:
        self.model, self.data, self.body = model, data, robot_body
        self.mount, self.noise, self.rng, self.spec = mount, noise, rng, spec
        u, v = np.meshgrid(np.arange(spec.width), np.arange(spec.height))
        # Optical-frame ray with unit z, so that mj_multiRay's distance (in units of the
        # ray vector) is the depth z itself.
        self._xo = ((u - spec.cx) / spec.fx).reshape(-1)
        self._yo = ((v - spec.cy) / spec.fx).reshape(-1)
        # The same ray in base_link axes (x forward = optical z, y left = -x, z up = -y).
        self._bx = np.ones_like(self._xo)
        self._by = -self._xo
        self._bz = -self._yo
        n = spec.width * spec.height
        self._vec = np.zeros((n, 3))
        self._geomid = np.zeros(n, np.int32)
        self._dist = np.zeros(n)

    def true_depth(self, x: float, y: float, yaw: float) -> npt.NDArray[np.float64]:
        """Noise-free depth z per pixel (row-major), -1 where nothing is hit."""
        pnt = _mount_in_world(self.mount, x, y, yaw)
        c, s = math.cos(yaw), math.sin(yaw)
        self._vec[:, 0] = c * self._bx - s * self._by
        self._vec[:, 1] = s * self._bx + c * self._by
        self._vec[:, 2] = self._bz
        n = self._dist.size
        mujoco.mj_multiRay(
            self.model, self.data, pnt, self._vec.reshape(-1), None, 1, self.body,
            self._geomid, self._dist, None, n, self.spec.range_max * 1.5,
        )
        return self._dist.copy()

    def measure(self, x: float, y: float, yaw: float) -> F32:
        """One noisy organised cloud, shape (height, width, 3), float32, NaN for no return."""
        z = self.true_depth(x, y, yaw)
        gauss = self.rng.standard_normal(z.size)
        drop = self.rng.random(z.size)
        sigma = 0.0012 + 0.0019 * (np.maximum(z, 0.4) - 0.4) ** 2
        zn = z + gauss * sigma
        ok = (z >= self.spec.range_min) & (z <= self.spec.range_max)
        if self.noise.depth_dropout > 0.0:
            ok &= drop >= self.noise.depth_dropout
        zn = np.where(ok, zn, np.nan)
        pts = np.empty((z.size, 3), np.float32)
        pts[:, 0] = self._xo * zn
        pts[:, 1] = self._yo * zn
        pts[:, 2] = zn
        return pts.reshape(self.spec.height, self.spec.width, 3)


class WheelOdometry:
    """Dead reckoning from simulated wheel encoders, in the ``odom`` frame.

    The ``odom`` frame is the robot's start pose. Each tick the body's true motion is turned
    into left and right wheel travel (using the *effective* wheel separation), inflated by slip
    (the wheels turn more than the body moves), scaled by each encoder's error, disturbed by
    random noise, counted in whole encoder ticks (4096 per wheel turn, as on the TurtleBot3's
    motors), then integrated with the *nominal* separation. Sideways sliding is invisible to the
    encoders. The result drifts, mostly in heading; standing still it does not move at all.
    """

    TICKS_PER_REV = 4096

    def __init__(
        self, x: float, y: float, yaw: float, robot: RobotSpec, noise: Noise,
        rng: np.random.Generator,
    ) -> None:
        self.robot, self.noise, self.rng = robot, noise, rng
        self._prev = (x, y, yaw)
        self.x = 0.0
        self.y = 0.0
        self.yaw = 0.0
        self.v = 0.0
        self.w = 0.0
        self.distance = 0.0  # wheel-measured travel (m), for the summary
        self._tick = 2 * math.pi * robot.wheel_radius / self.TICKS_PER_REV
        self._wheel = [0.0, 0.0]  # accumulated wheel travel (m), left and right
        self._ticks = [0, 0]

    def update(self, x: float, y: float, yaw: float, slip: float, dt: float) -> None:
        """Advance with the body's true pose after ``dt`` seconds and the current slip."""
        px, py, pyaw = self._prev
        self._prev = (x, y, yaw)
        c, s = math.cos(pyaw), math.sin(pyaw)
        ds = c * (x - px) + s * (y - py)
        dth = wrap(yaw - pyaw)
        nz = self.noise
        half_b = self.robot.wheel_separation * nz.odom_wheelbase_scale / 2
        grow = 1.0 / (1.0 - slip)
        dl = (ds - dth * half_b) * grow * nz.odom_scale_left
        dr = (ds + dth * half_b) * grow * nz.odom_scale_right
        e = self.rng.standard_normal(2)
        self._wheel[0] += dl + nz.odom_wheel_sigma * math.sqrt(abs(dl)) * float(e[0])
        self._wheel[1] += dr + nz.odom_wheel_sigma * math.sqrt(abs(dr)) * float(e[1])
        ticks = [math.floor(w / self._tick) for w in self._wheel]
        dl = (ticks[0] - self._ticks[0]) * self._tick
        dr = (ticks[1] - self._ticks[1]) * self._tick
        self._ticks = ticks
        ds_o = (dl + dr) / 2
        dth_o = (dr - dl) / self.robot.wheel_separation
        mid = self.yaw + dth_o / 2
        self.x += ds_o * math.cos(mid)
        self.y += ds_o * math.sin(mid)
        self.yaw = wrap(self.yaw + dth_o)
        self.distance += abs(ds_o)
        if dt > 0:
            self.v = ds_o / dt
            self.w = dth_o / dt
