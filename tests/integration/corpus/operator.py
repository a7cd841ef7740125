"""Not a node under test: the operator, acting when it sees numbers go by (at the first number
it sees from N on; it may join after the first went by).

    operator.py gain N=GAIN ...    set /gain_controller's `gain` (its ~/set_parameters service)
    operator.py fast N=0|1 ...     call /mode_switch/fast_mode (std_srvs/SetBool)
"""

import sys

import rclpy
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_msgs.msg import Int64
from std_srvs.srv import SetBool


def main():
    what = sys.argv[1]
    plan = {int(n): v for n, v in (arg.split('=') for arg in sys.argv[2:])}
    rclpy.init()
    node = Node('operator')
    if what == 'gain':
        client = node.create_client(SetParameters, '/gain_controller/set_parameters')

        def request(value):
            parameter = Parameter('gain', value=float(value)).to_parameter_msg()
            return SetParameters.Request(parameters=[parameter])
    else:
        client = node.create_client(SetBool, '/mode_switch/fast_mode')

        def request(value):
            return SetBool.Request(data=value == '1')

    def on_number(msg):
        due = [n for n in plan if n <= msg.data]
        if due:
            value = plan.pop(max(due))
            for n in due:
                plan.pop(n, None)
            client.call_async(request(value))
            print(f'at {msg.data}: {what} {value}', flush=True)

    node.create_subscription(Int64, '/numbers', on_number, 100)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
