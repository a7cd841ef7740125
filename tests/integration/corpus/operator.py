"""Not a node under test: the operator, acting when it sees numbers go by (at the first number
it sees from N on; it may join after the first went by; N=0: as soon as the service is there).
``cK`` instead of N: at the K-th number after the node's first checkpoint (read on
/rory/events), so that an action lands after that checkpoint whenever it is taken.

    operator.py gain N=GAIN ...        set /gain_controller's `gain` (its ~/set_parameters)
    operator.py fast N=0|1 ...         call /mode_switch/fast_mode (std_srvs/SetBool)
    operator.py lifecycle N=LABEL ...  ask /lifecycle_counter/change_state for a transition
"""

import json
import sys

import rclpy
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import Int64, String
from std_srvs.srv import SetBool


def main():
    what = sys.argv[1]
    pairs = [arg.split('=') for arg in sys.argv[2:]]
    plan = {int(n): v for n, v in pairs if not n.startswith('c')}
    after_checkpoint = {int(n[1:]): v for n, v in pairs if n.startswith('c')}
    seen_after = []  # numbers seen since the first checkpoint
    rclpy.init()
    node = Node('operator')
    if what == 'gain':
        client = node.create_client(SetParameters, '/gain_controller/set_parameters')

        def request(value):
            parameter = Parameter('gain', value=float(value)).to_parameter_msg()
            return SetParameters.Request(parameters=[parameter])
    elif what == 'fast':
        client = node.create_client(SetBool, '/mode_switch/fast_mode')

        def request(value):
            return SetBool.Request(data=value == '1')
    else:
        client = node.create_client(ChangeState, '/lifecycle_counter/change_state')

        def request(value):
            return ChangeState.Request(transition=Transition(label=value))

    def on_number(msg):
        if seen_after:
            seen_after.append(msg.data)
            value = after_checkpoint.pop(len(seen_after) - 1, None)
            if value is not None:
                client.call_async(request(value))
                print(f'at {msg.data} ({len(seen_after) - 1} after the first checkpoint): '
                      f'{what} {value}', flush=True)
        due = [n for n in plan if n <= msg.data]
        if due:
            value = plan.pop(max(due))
            for n in due:
                plan.pop(n, None)
            client.call_async(request(value))
            print(f'at {msg.data}: {what} {value}', flush=True)

    now = plan.pop(0, None)
    if now is not None:
        client.wait_for_service()
        future = client.call_async(request(now))
        rclpy.spin_until_future_complete(node, future)
        print(f'at start: {what} {now}: {future.result()}', flush=True)
    def on_event(msg):
        if not seen_after and json.loads(msg.data).get('kind') == 'checkpoint':
            seen_after.append(None)  # counting from the next number

    latched = QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(String, '/rory/events', on_event, latched)
    node.create_subscription(Int64, '/numbers', on_number, 100)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
