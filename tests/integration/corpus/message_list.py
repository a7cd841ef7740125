"""A list of ROS messages: the last 40 poses built from the input."""

import json
import math

import rclpy
from geometry_msgs.msg import Pose
from rclpy.node import Node
from std_msgs.msg import Int64, String


class PathNode(Node):
    def __init__(self):
        super().__init__('path')
        self.poses = []
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.report)

    def on_number(self, msg):
        pose = Pose()
        pose.position.x = float(msg.data)
        pose.position.y = math.sin(msg.data / 10.0)
        pose.orientation.w = 1.0
        self.poses.append(pose)
        self.poses = self.poses[-40:]
        self.report()

    def report(self):
        state = [[p.position.x, p.position.y] for p in self.poses]
        self.pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = PathNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
