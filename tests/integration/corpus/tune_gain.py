"""Not a node under test: the operator. Sets /gain_controller's `gain` through its
~/set_parameters service at the first number it sees from N on: `tune_gain.py N=GAIN ...`
(it may join after the first numbers went by)."""

import sys

import rclpy
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Int64


def main():
    plan = {int(n): float(g) for n, g in (arg.split('=') for arg in sys.argv[1:])}
    rclpy.init()
    node = Node('tune_gain')
    client = node.create_client(SetParameters, '/gain_controller/set_parameters')

    def on_number(msg):
        due = [n for n in plan if n <= msg.data]
        if due:
            gain = plan.pop(max(due))
            for n in due:
                plan.pop(n, None)
            request = SetParameters.Request(
                parameters=[Parameter('gain', value=gain).to_parameter_msg()])
            client.call_async(request)
            print(f'at {msg.data}: gain {gain}', flush=True)

    node.create_subscription(Int64, '/numbers', on_number, 100)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
