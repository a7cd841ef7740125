"""depth_mapper: depth-camera SLAM (the camera's trajectory and a voxel model of the world).

ORB_SLAM2's role in the RORY evaluation, from a depth camera: per frame it tracks the camera
against the model it has built (point-to-plane ICP, seeded by the wheel odometry), and fuses
keyframes into a sparse voxel model. Subscribes ``camera/depth/points`` (sensor_msgs/
PointCloud2, organised, x y z float32, optical frame) and ``odom`` (nav_msgs/Odometry);
publishes ``~/pose`` (geometry_msgs/PoseStamped: the camera's optical frame in ``map``, per
frame), ``~/cloud`` (the model as PointCloud2 in ``map``, every ``cloud_period`` seconds,
latched) and ``~/keyframes`` (nav_msgs/Path of the keyframe poses of ``base_link``). Run::

    python targets/depth_mapper/depth_mapper_node.py --ros-args -p use_sim_time:=true \
        -p map_start_x:=0.8 -p map_start_y:=4.25 -p map_start_yaw:=0.0

The algorithm lives in the sibling modules (``depth_mapper_tracker`` and below), plain numpy.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2, PointField

from depth_mapper_backend import BackendSettings, LoopClosure
from depth_mapper_cloud import CloudError, FieldSpec, decode_xyz
from depth_mapper_geometry import camera_quaternion, yaw_of_quaternion
from depth_mapper_icp import IcpSettings
from depth_mapper_tracker import DepthMapper, FrameResult, MapperSettings

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     reliability=ReliabilityPolicy.RELIABLE)
WARN_EVERY = 5.0  # seconds between repeats of the same warning
REPORT_EVERY = 100  # frames between progress lines in the log


def stamp_ns(stamp: Any) -> int:
    """A builtin_interfaces/Time as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def set_stamp(stamp: Any, ns: int) -> None:
    """Fill a builtin_interfaces/Time from integer nanoseconds."""
    stamp.sec = ns // 1_000_000_000
    stamp.nanosec = ns % 1_000_000_000


class DepthMapperNode(Node):
    """The ROS side: parameters, subscriptions, message conversion, publishing.

    Its state is ``mapper`` (see ``keyvars.yaml``).
    """

    def __init__(self) -> None:
        super().__init__('depth_mapper')
        p = self._declare_parameters()
        self.min_hits = max(1, int(p['min_hits']))
        settings = MapperSettings(
            voxel_size=float(p['voxel_size']),
            min_depth=float(p['min_depth']),
            max_depth=float(p['max_depth']),
            mount=(float(p['camera_x']), float(p['camera_y']), float(p['camera_z'])),
            icp=IcpSettings(
                iterations=int(p['icp_iterations']),
                max_distance=float(p['icp_max_distance']),
                max_normal_angle=math.radians(float(p['icp_max_normal_angle_deg'])),
                sigma_floor=float(p['icp_sigma_floor']),
                degenerate_sigma=float(p['icp_degenerate_sigma']),
                min_pairs=int(p['icp_min_pairs'])),
            icp_max_points=int(p['icp_max_points']),
            keyframe_distance=float(p['keyframe_distance']),
            keyframe_angle=math.radians(float(p['keyframe_angle_deg'])),
            backend=BackendSettings(loop_radius=float(p['loop_radius']),
                                    loop_min_gap=int(p['loop_min_gap'])),
            close_loops=bool(p['close_loops']),
            calibrate_odometry=bool(p['calibrate_odometry']),
        )
        self.mount = settings.mount
        start = np.array([float(p['map_start_x']), float(p['map_start_y']),
                          float(p['map_start_yaw'])])
        self.mapper = DepthMapper(settings, start)
        # (keyframes, graph solves) the last published model showed: a note, not state.
        self._published_version = (0, 0)
        self.pose_pub = self.create_publisher(PoseStamped, '~/pose', 10)
        self.cloud_pub = self.create_publisher(PointCloud2, '~/cloud', LATCHED)
        self.path_pub = self.create_publisher(Path, '~/keyframes', LATCHED)
        # Sensors: reliable and deep enough to ride out a CPU stall (2 s of each).
        self.odom_sub = self.create_subscription(Odometry, 'odom', self.on_odom, 100)
        self.cloud_sub = self.create_subscription(PointCloud2, 'camera/depth/points',
                                                  self.on_cloud, 10)
        self.timer = self.create_timer(float(p['cloud_period']), self.on_timer)
        self.get_logger().info(
            f'depth_mapper: {settings.voxel_size * 100:.0f} cm voxels, depth '
            f'{settings.min_depth}-{settings.max_depth} m, start ({start[0]:.2f}, '
            f'{start[1]:.2f}, {start[2]:.2f}); waiting for {self.cloud_sub.topic_name}')

    def _declare_parameters(self) -> dict[str, Any]:
        defaults: dict[str, Any] = {
            # The robot's start pose in map (rory sim info), so the model lines up with it.
            'map_start_x': 0.0, 'map_start_y': 0.0, 'map_start_yaw': 0.0,
            # camera_depth_optical_frame in base_link (no TF in this system: fixed offsets).
            'camera_x': 0.12, 'camera_y': 0.0, 'camera_z': 0.25,
            'voxel_size': 0.05, 'min_depth': 0.3, 'max_depth': 5.0,
            'icp_iterations': 8, 'icp_max_distance': 0.15, 'icp_max_normal_angle_deg': 35.0,
            'icp_sigma_floor': 0.02, 'icp_degenerate_sigma': 0.01, 'icp_min_pairs': 40,
            'icp_max_points': 600,
            'keyframe_distance': 0.25, 'keyframe_angle_deg': 12.0,
            'close_loops': True, 'loop_radius': 1.5, 'loop_min_gap': 20,
            'calibrate_odometry': True,
            'min_hits': 2, 'cloud_period': 1.0,
        }
        for name, value in defaults.items():
            self.declare_parameter(name, value)
        return {name: self.get_parameter(name).value for name in defaults}

    # -- callbacks ----------------------------------------------------------------------------

    def on_odom(self, msg: Odometry) -> None:
        """An odometry sample; frames that waited for it are tracked now."""
        p = msg.pose.pose
        q = p.orientation
        pose = (float(p.position.x), float(p.position.y),
                yaw_of_quaternion(q.x, q.y, q.z, q.w))
        if not all(math.isfinite(v) for v in pose):
            self.get_logger().warning(f'{self.odom_sub.topic_name}: non-finite pose; skipped',
                                      throttle_duration_sec=WARN_EVERY)
            return
        stamp = stamp_ns(msg.header.stamp)
        self.get_logger().debug(f'odom {stamp}')
        for result in self.mapper.add_odometry(stamp, *pose):
            self._frame_done(result)

    def on_cloud(self, msg: PointCloud2) -> None:
        """A depth frame: decoded and tracked (or held until odometry at its stamp is in)."""
        topic = self.cloud_sub.topic_name
        try:
            fields = [FieldSpec(f.name, int(f.offset), int(f.datatype), int(f.count))
                      for f in msg.fields]
            points = decode_xyz(msg.data, int(msg.height), int(msg.width),
                                int(msg.point_step), fields, bool(msg.is_bigendian))
        except CloudError as err:
            self.get_logger().warning(f'{topic}: malformed cloud ({err}); skipped',
                                      throttle_duration_sec=WARN_EVERY)
            return
        counters = self.mapper.counters
        stale, extrapolated = counters['stale_frames'], counters['extrapolated']
        stamp = stamp_ns(msg.header.stamp)
        self.get_logger().debug(f'cloud {stamp}')
        results = self.mapper.add_frame(stamp, points)
        if counters['stale_frames'] != stale:
            self.get_logger().warning(f'{topic}: frame not newer than the last one; skipped',
                                      throttle_duration_sec=WARN_EVERY)
        if counters['extrapolated'] != extrapolated:
            self.get_logger().warning(
                f'{self.odom_sub.topic_name}: no odometry up to a frame\'s stamp after '
                f'{self.mapper.settings.odom_wait_ns / 1e9:.1f} s; extrapolated it',
                throttle_duration_sec=WARN_EVERY)
        for result in results:
            self._frame_done(result)

    def on_timer(self) -> None:
        """Publish the model and the keyframes when a keyframe or a loop changed them."""
        version = (self.mapper.counters['keyframes'], self.mapper.counters['graph_solves'])
        if version == self._published_version:
            return
        self._published_version = version
        self._publish_cloud()
        self._publish_keyframes()

    # -- outputs ----------------------------------------------------------------------------------

    def _frame_done(self, result: FrameResult) -> None:
        topic = self.cloud_sub.topic_name
        t = result.stamp_ns / 1e9
        if result.valid_points < self.mapper.settings.icp.min_pairs:
            self.get_logger().warning(
                f'{topic}: frame at t={t:.2f} s has {result.valid_points} usable points; '
                'pose from odometry', throttle_duration_sec=WARN_EVERY)
        elif not result.tracked and not result.first:
            self.get_logger().warning(
                f'{topic}: frame at t={t:.2f} s matched only {result.pairs} model points; '
                'pose from odometry', throttle_duration_sec=WARN_EVERY)
        self._publish_pose(result)
        if result.loop is not LoopClosure.NONE:
            moved = ('the map was corrected' if result.loop is LoopClosure.MOVED
                     else 'the map already agreed')
            self.get_logger().info(
                f'loop closure at t={t:.1f} s ({self.mapper.counters["loops"]} so far): '
                f'{moved}')
        self.get_logger().debug(
            f'frame {result.stamp_ns}: tracked {result.tracked}, {result.pairs} pairs, '
            f'keyframe {result.keyframe}, pose {result.pose[0]:.4f} {result.pose[1]:.4f} '
            f'{result.pose[2]:.5f}')
        c = self.mapper.counters
        if c['frames'] % REPORT_EVERY == 0:
            self.get_logger().info(
                f'{c["frames"]} frames ({c["tracked"]} tracked), {c["keyframes"]} keyframes, '
                f'{c["loops"]} loop closures ({c["graph_solves"]} moved the map), '
                f'{c["relocalised"]} relocalised, '
                f'{len(self.mapper.model)} voxels; pose ({result.pose[0]:.2f}, '
                f'{result.pose[1]:.2f}, {result.pose[2]:.2f}) at t={t:.1f} s')

    def _publish_pose(self, result: FrameResult) -> None:
        x, y, yaw = (float(v) for v in result.pose)
        c, s = math.cos(yaw), math.sin(yaw)
        mx, my, mz = self.mount
        out = PoseStamped()
        set_stamp(out.header.stamp, result.stamp_ns)
        out.header.frame_id = 'map'
        out.pose.position.x = x + c * mx - s * my
        out.pose.position.y = y + s * mx + c * my
        out.pose.position.z = mz
        qx, qy, qz, qw = camera_quaternion(yaw)
        out.pose.orientation.x = qx
        out.pose.orientation.y = qy
        out.pose.orientation.z = qz
        out.pose.orientation.w = qw
        self.pose_pub.publish(out)

    def _publish_cloud(self) -> None:
        points = self.mapper.model.points(self.min_hits).astype(np.float32)
        out = PointCloud2()
        set_stamp(out.header.stamp, max(self.mapper.last_frame_ns, 0))
        out.header.frame_id = 'map'
        out.height = 1
        out.width = int(points.shape[0])
        out.fields = [PointField(name=name, offset=4 * k, datatype=PointField.FLOAT32, count=1)
                      for k, name in enumerate('xyz')]
        out.is_bigendian = False
        out.point_step = 12
        out.row_step = 12 * out.width
        out.is_dense = True
        out.data = points.tobytes()
        self.cloud_pub.publish(out)

    def _publish_keyframes(self) -> None:
        out = Path()
        set_stamp(out.header.stamp, max(self.mapper.last_frame_ns, 0))
        out.header.frame_id = 'map'
        poses = []
        for kf in self.mapper.backend.keyframes:
            x, y, yaw = (float(v) for v in kf.pose)
            pose = PoseStamped()
            set_stamp(pose.header.stamp, kf.stamp_ns)
            pose.header.frame_id = 'map'
            pose.pose.position.x = x
            pose.pose.position.y = y
            pose.pose.orientation.z = math.sin(yaw / 2.0)
            pose.pose.orientation.w = math.cos(yaw / 2.0)
            poses.append(pose)
        out.poses = poses
        self.path_pub.publish(out)


def main(args: list[str] | None = None) -> None:
    """Run the node until shut down."""
    rclpy.init(args=args)
    node = DepthMapperNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
