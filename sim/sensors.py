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
    """A pinhole depth camera modelled on the Intel RealSense D435's depth stream.

    ROS optical frame: z forward, x right, y down. The field of view, range and noise are the
    D435's (87 deg x 58 deg, 0.2-10 m, stereo depth error growing with z^2); the resolution is
    coarser than its native 848 x 480, so that the ray casting and every consumer of the cloud
    stay cheap (sim/README.md, "Performance"). 96 x 56 square pixels keep the D435's aspect of
    the two fields of view: 87 deg across gives 57.9 deg down.

    Attributes:
        width: pixels across.
        height: pixels down.
        hfov_deg: horizontal field of view (deg), edge to edge of the image.
        range_min: nearer depths are no return (m).
        range_max: farther depths are no return (m).
        rate: frames per second.
        baseline: the stereo pair's baseline (m), for the noise model.
        subpixel: the stereo matcher's RMS disparity error (pixels), for the noise model.
        native_width: pixels across of the D435's depth stream at its native resolution; its
            focal length, not the simulated image's, sets the noise.
    """

    width: int = 96
    height: int = 56
    hfov_deg: float = 87.0
    range_min: float = 0.2
    range_max: float = 10.0
    rate: float = 5.0
    baseline: float = 0.050
    subpixel: float = 0.08
    native_width: int = 848

    @property
    def fx(self) -> float:
        """Focal length in pixels (square pixels: fy == fx)."""
        return (self.width / 2) / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def vfov_deg(self) -> float:
        """Vertical field of view (deg), edge to edge, that square pixels give."""
        return math.degrees(2 * math.atan((self.height / 2) / self.fx))

    @property
    def cx(self) -> float:
        """Principal point x (pixels; pixel centres at integer coordinates)."""
        return (self.width - 1) / 2

    @property
    def cy(self) -> float:
        """Principal point y (pixels)."""
        return (self.height - 1) / 2

    @property
    def native_fx(self) -> float:
        """Focal length (pixels) of the depth stream at its native resolution."""
        return (self.native_width / 2) / math.tan(math.radians(self.hfov_deg) / 2)

    def depth_rms(self, z: npt.ArrayLike) -> npt.NDArray[np.float64]:
        """RMS depth error (m) at depth ``z`` (m): ``z^2 * subpixel / (native_fx * baseline)``.

        The stereo depth RMS error formula of Intel's white paper "Best-Known-Methods for
        Tuning Intel RealSense D400 Depth Cameras for Best Performance" (Grunnet-Jepsen et al.),
        with the D435's 50 mm baseline, its typical 0.08 pixel subpixel error and its 848-pixel
        depth stream at 87 deg; it meets the D400 datasheet's "under 2 % at 2 m".
        """
        zz = np.asarray(z, dtype=np.float64)
        out: npt.NDArray[np.float64] = zz * zz * (self.subpixel / (self.native_fx * self.baseline))
        return out


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

    Depth noise is Gaussian with the D435's stereo RMS error, ``DepthSpec.depth_rms(z)``
    (grows with z^2); pixels with no return, a measured depth outside [range_min, range_max],
    or dropped, are NaN.
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

    def measured_depth(self, z: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        """The depths the camera reports for true depths ``z`` (-1: no hit): noisy, NaN where
        nothing is hit, where the measured depth is outside [range_min, range_max], or where
        the pixel drops out."""
        # Draw the same amount of randomness every frame so that the stream stays aligned.
        gauss = self.rng.standard_normal(z.size)
        drop = self.rng.random(z.size)
        hit = z >= 0.0
        zn = z + gauss * self.spec.depth_rms(np.where(hit, z, 0.0))
        ok = hit & (zn >= self.spec.range_min) & (zn <= self.spec.range_max)
        if self.noise.depth_dropout > 0.0:
            ok &= drop >= self.noise.depth_dropout
        out: npt.NDArray[np.float64] = np.where(ok, zn, np.nan)
        return out

    def measure(self, x: float, y: float, yaw: float) -> F32:
        """One noisy organised cloud, shape (height, width, 3), float32, NaN for no return."""
        zn = self.measured_depth(self.true_depth(x, y, yaw))
        pts = np.empty((zn.size, 3), np.float32)
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
