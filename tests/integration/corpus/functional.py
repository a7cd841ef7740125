"""A node written as functions: rclpy.create_node and module globals."""

import json

import rclpy
from std_msgs.msg import Int64, String

counter = 0
seen = []
node = None
pub = None


def on_number(msg):
    global counter
    counter += 1
    seen.append(msg.data % 7)
    report()


def report():
    pub.publish(String(data=json.dumps({'counter': counter, 'seen': seen})))


def main():
    global node, pub
    rclpy.init()
    node = rclpy.create_node('functional')
    pub = node.create_publisher(String, '/state', 10)
    node.create_subscription(Int64, '/numbers', on_number, 100)
    node.create_timer(1.0, report)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
