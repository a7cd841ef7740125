"""targets/planar/planar_localizer.py: the ROS callbacks amcl and lama_local share, once.

No ROS graph: a stand-in node holds what each node's ``__init__`` makes (a localizer that
records its calls, a publisher and a logger that record theirs), and real ROS messages go in.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.node import Node
from sensor_msgs.msg import LaserScan

from planar_geometry import OdometrySample, Pose, quaternion_from_yaw, yaw_from_quaternion
from planar_localizer import (
    SCAN_QUEUE,
    WARN_EVERY,
    LocalizerCallbacks,
    covariance_3x3,
    covariance_36,
)
from planar_map import GridMap

# -- a stand-in node ---------------------------------------------------------------------------


class Skipped(Exception):
    """The stand-in localizer's ScanSkipped."""


@dataclass(frozen=True)
class Estimate:
    stamp_ns: int
    pose: Pose
    covariance: np.ndarray
    updated: bool
    used_scan: bool


class Localizer:
    """Records what the callbacks give it; the pose it answers is the odometry's x + 1."""

    def __init__(self) -> None:
        self.grid: GridMap | None = None
        self.odometry: deque[OdometrySample] = deque(maxlen=100)
        self.scans: list[tuple[int, int]] = []  # (stamp, newest odometry stamp) per scan
        self.initial: list[tuple[Pose, np.ndarray]] = []

    def set_map(self, grid: GridMap) -> None:
        self.grid = grid

    def add_odometry(self, stamp_ns: int, pose: Pose) -> bool:
        if self.odometry and stamp_ns < self.odometry[-1][0]:
            return False
        self.odometry.append((stamp_ns, *pose))
        return True

    def set_pose(self, pose: Pose, covariance: np.ndarray) -> None:
        self.initial.append((pose, covariance))

    def process_scan(self, stamp_ns: int, ranges: Any, angle_min: float,
                     angle_increment: float, range_min: float, range_max: float) -> Estimate:
        ranges = np.asarray(ranges)
        assert ranges.dtype == np.float32
        if ranges.size == 0:
            raise Skipped('unusable scan')
        self.scans.append((stamp_ns, self.odometry[-1][0]))
        x = self.odometry[-1][1] + 1.0
        return Estimate(stamp_ns, (x, 2.0, 0.5), np.diag([0.1, 0.2, 0.3]), True,
                        bool(np.isfinite(ranges).any()))


class Logger:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str, dict[str, Any]]] = []

    def info(self, message: str, **kwargs: Any) -> None:
        self.lines.append(('info', message, kwargs))

    def warning(self, message: str, **kwargs: Any) -> None:
        self.lines.append(('warning', message, kwargs))


class Publisher:
    def __init__(self) -> None:
        self.sent: list[Any] = []

    def publish(self, msg: Any) -> None:
        self.sent.append(msg)


class StandIn(LocalizerCallbacks[Estimate]):
    """What a node class adds to the callbacks, with recording stand-ins for ROS."""

    scan_skipped = Skipped

    def __init__(self) -> None:
        self.localizer = Localizer()
        self.waiting_scans: deque[LaserScan] = deque(maxlen=SCAN_QUEUE)
        self.global_frame = 'map'
        self.pose_pub = Publisher()  # type: ignore[assignment]
        for name, topic in (('map_sub', '/map'), ('odom_sub', '/odom'), ('scan_sub', '/scan'),
                            ('initial_pose_sub', '/initialpose')):
            setattr(self, name, SimpleNamespace(topic_name=topic))
        self.logger = Logger()

    def get_logger(self) -> Any:
        return self.logger

    def _odometry_alone(self, estimate: Estimate) -> str | None:
        return None if estimate.used_scan else 'nothing to match'

    def warnings(self) -> list[str]:
        return [message for level, message, _kw in self.logger.lines if level == 'warning']


# -- messages ------------------------------------------------------------------------------------

def stamp(ns: int) -> Any:
    msg = LaserScan()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(ns, 1_000_000_000)
    return msg.header.stamp


def map_msg(width: int = 4, height: int = 3, cells: int | None = None) -> OccupancyGrid:
    msg = OccupancyGrid()
    msg.info.width, msg.info.height, msg.info.resolution = width, height, 0.05
    msg.info.origin.position.x, msg.info.origin.position.y = -1.0, 2.0
    msg.info.origin.orientation.w = 1.0
    msg.data = [0] * (width * height if cells is None else cells)
    return msg


def odom_msg(ns: int, x: float, yaw: float = 0.0) -> Odometry:
    msg = Odometry()
    msg.header.stamp = stamp(ns)
    msg.pose.pose.position.x = x
    _, _, msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = quaternion_from_yaw(yaw)
    return msg


def scan_msg(ns: int, ranges: list[float] | None = None) -> LaserScan:
    msg = LaserScan()
    msg.header.stamp = stamp(ns)
    msg.angle_min, msg.angle_increment, msg.range_min, msg.range_max = -3.0, 0.5, 0.1, 10.0
    msg.ranges = [1.0, 2.0] if ranges is None else ranges
    return msg


def initial_pose_msg(x: float, frame: str = 'map',
                     diagonal: tuple[float, float, float] = (0.25, 0.25, 0.07)
                     ) -> PoseWithCovarianceStamped:
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = frame
    msg.pose.pose.position.x, msg.pose.pose.position.y = x, 4.0
    _, _, msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = quaternion_from_yaw(0.3)
    cov = np.zeros((6, 6))
    cov[0, 0], cov[1, 1], cov[5, 5] = diagonal
    cov[0, 1] = cov[1, 0] = 0.01
    cov[2, 2] = 99.0  # z: not planar, dropped
    msg.pose.covariance = [float(v) for v in cov.ravel()]
    return msg


def published_x(node: StandIn) -> list[float]:
    return [m.pose.pose.position.x for m in node.pose_pub.sent]  # type: ignore[attr-defined]


# -- the callbacks -------------------------------------------------------------------------------

def test_a_scan_waits_for_the_map_and_the_odometry_at_its_stamp() -> None:
    node = StandIn()
    node.on_scan(scan_msg(100))
    assert node.warnings() == ['/scan: no map yet; scans wait for it (the newest 10 are kept)']
    assert node.logger.lines[0][2] == {'throttle_duration_sec': WARN_EVERY}
    node.on_map(map_msg())
    assert node.localizer.grid is not None and node.localizer.grid.origin_y == 2.0
    assert ('info', '/map: map 4 x 3 at 0.05 m', {}) in node.logger.lines
    node.on_odom(odom_msg(50, 0.5))
    assert not node.localizer.scans and len(node.waiting_scans) == 1  # odometry not there yet
    node.on_odom(odom_msg(100, 1.0))
    assert node.localizer.scans == [(100, 100)] and not node.waiting_scans
    assert published_x(node) == [2.0]


def test_the_pose_does_not_depend_on_which_of_scan_and_odometry_came_first() -> None:
    runs = []
    for scan_first in (True, False):
        node = StandIn()
        node.on_map(map_msg())
        node.on_odom(odom_msg(0, 0.0))
        inputs = [scan_msg(20), odom_msg(20, 0.2)]
        for msg in inputs if scan_first else inputs[::-1]:
            if isinstance(msg, LaserScan):
                node.on_scan(msg)
            else:
                node.on_odom(msg)
        assert node.localizer.scans == [(20, 20)]
        runs.append(published_x(node))
    assert runs[0] == runs[1] == [pytest.approx(1.2)]


def test_the_queue_keeps_the_newest_scans_until_the_map_comes() -> None:
    node = StandIn()
    node.on_odom(odom_msg(10**9, 0.0))
    for k in range(SCAN_QUEUE + 3):
        node.on_scan(scan_msg(k))
    assert len(node.waiting_scans) == SCAN_QUEUE
    node.on_map(map_msg())
    assert [s for s, _odom in node.localizer.scans] == list(range(3, SCAN_QUEUE + 3))


def test_the_pose_goes_out_at_the_scans_stamp_in_the_global_frame() -> None:
    node = StandIn()
    node.global_frame = 'world'
    node.on_map(map_msg())
    node.on_odom(odom_msg(1_500_000_000, 3.0))
    node.on_scan(scan_msg(1_500_000_000))
    [out] = node.pose_pub.sent  # type: ignore[attr-defined]
    assert (out.header.stamp.sec, out.header.stamp.nanosec) == (1, 500_000_000)
    assert out.header.frame_id == 'world'
    p = out.pose.pose
    assert (p.position.x, p.position.y, p.position.z) == (4.0, 2.0, 0.0)
    assert yaw_from_quaternion(p.orientation.x, p.orientation.y, p.orientation.z,
                               p.orientation.w) == pytest.approx(0.5)
    assert np.array_equal(covariance_3x3(out.pose.covariance), np.diag([0.1, 0.2, 0.3]))
    assert sum(v != 0 for v in out.pose.covariance) == 3


def test_a_skipped_scan_and_an_update_without_it_are_warned_about_by_topic() -> None:
    node = StandIn()
    node.on_map(map_msg())
    node.on_odom(odom_msg(10, 0.0))
    node.on_scan(scan_msg(10, ranges=[]))
    assert not node.pose_pub.sent  # type: ignore[attr-defined]
    node.on_scan(scan_msg(10, ranges=[math.nan, math.inf]))
    assert len(node.pose_pub.sent) == 1  # type: ignore[attr-defined]
    assert node.warnings() == ['/scan: unusable scan; skipped',
                               '/scan: nothing to match; moved on odometry alone']
    assert all(kw == {'throttle_duration_sec': WARN_EVERY}
               for level, _message, kw in node.logger.lines if level == 'warning')


def test_bad_input_is_ignored_with_a_warning_naming_the_topic() -> None:
    node = StandIn()
    rotated = map_msg()
    rotated.info.origin.orientation.z, rotated.info.origin.orientation.w = 0.6, 0.8
    node.on_map(rotated)
    node.on_map(map_msg(10, 10, cells=7))
    assert node.localizer.grid is None
    node.on_odom(odom_msg(100, math.nan))
    node.on_odom(odom_msg(100, 1.0))
    node.on_odom(odom_msg(50, 2.0))
    assert list(node.localizer.odometry) == [(100, 1.0, 0.0, 0.0)]
    node.on_initial_pose(initial_pose_msg(1.0, frame='odom'))
    node.on_initial_pose(initial_pose_msg(math.nan))
    node.on_initial_pose(initial_pose_msg(1.0, diagonal=(0.25, -0.1, 0.07)))
    assert not node.localizer.initial
    assert node.warnings() == [
        '/map: a rotated map origin is not supported; ignored',
        '/map: malformed map (7 cells for a 10 x 10 grid); ignored',
        '/odom: non-finite pose; skipped',
        '/odom: stamp older than the last one; skipped',
        "/initialpose: pose in frame 'odom', expected 'map'; ignored",
        '/initialpose: non-finite pose or bad covariance; ignored',
        '/initialpose: non-finite pose or bad covariance; ignored',
    ]


@pytest.mark.parametrize('restarted', [None, 'filter restarted'])
def test_an_initial_pose_restarts_the_localizer(restarted: str | None) -> None:
    node = StandIn()
    if restarted is not None:
        node.restarted = restarted  # type: ignore[misc]  # as amcl's class sets it
    node.on_initial_pose(initial_pose_msg(1.0, frame='/map'))
    [(pose, cov)] = node.localizer.initial
    assert pose == pytest.approx((1.0, 4.0, 0.3))
    assert np.array_equal(cov, [[0.25, 0.01, 0.0], [0.01, 0.25, 0.0], [0.0, 0.0, 0.07]])
    said = restarted or 'restarted'
    assert node.logger.lines == [('info', f'/initialpose: {said} at (1.00, 4.00, 0.30)', {})]


def test_covariances_go_between_3x3_and_6x6() -> None:
    cov3 = np.arange(9, dtype=np.float64).reshape(3, 3)
    cov36 = covariance_36(cov3)
    assert len(cov36) == 36 and all(isinstance(v, float) for v in cov36)
    assert cov36[0] == 0.0 and cov36[1] == 1.0 and cov36[5] == 2.0 and cov36[35] == 8.0
    assert np.array_equal(covariance_3x3(cov36), cov3)


# -- the two nodes -------------------------------------------------------------------------------

@pytest.mark.parametrize('target', ['amcl', 'lama_local'])
def test_each_localization_node_takes_the_callbacks_from_here(target: str) -> None:
    # Listed before Node, and Node a base of its own, as rory-instrument looks for it in the
    # node's file (the mixin's file is outside the target's folder).
    node_module = __import__(f'{target}_node')
    localizer_module = __import__(f'{target}_localizer')
    cls = next(c for c in vars(node_module).values()
               if isinstance(c, type) and c.__module__ == node_module.__name__
               and issubclass(c, Node))
    assert cls.__bases__[-1] is Node and issubclass(cls, LocalizerCallbacks)
    assert cls.scan_skipped is localizer_module.ScanSkipped
    for name in ('on_map', 'on_odom', 'on_initial_pose', 'on_scan', '_process_scan'):
        assert name not in vars(cls), f'{cls.__name__}.{name} should be the shared one'
