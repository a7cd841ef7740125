"""Not a node under test: the operator, taking the steps it is given one after another, each
only once the one before it was taken (so the node is asked in the order given, however late
the first checkpoint falls among the numbers):

    N=VALUE    at the first number it sees from N on (it may join after the first went by;
               N=0: as soon as the service is there, before any number)
    cK=VALUE   at the K-th number seen after both the node's first checkpoint (read on
               /rory/events) and the step before, so that it lands after that checkpoint

    operator.py gain STEP ...        set /gain_controller's `gain` (its ~/set_parameters)
    operator.py fast STEP ...        call /mode_switch/fast_mode (std_srvs/SetBool), VALUE 0|1
    operator.py lifecycle STEP ...   ask /lifecycle_counter/change_state for a transition
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
    # [(after the first checkpoint?, N or K, value), ...] in the order given
    steps = [(n.startswith('c'), int(n.removeprefix('c')), v)
             for n, v in (arg.split('=') for arg in sys.argv[2:])]
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

    checkpointed = []  # [True] once the node's first checkpoint was seen
    counted = [0]  # numbers seen since the last step was taken and the first checkpoint

    def on_number(msg):
        if not steps:
            return
        after_checkpoint, n, value = steps[0]
        if after_checkpoint:
            if not checkpointed:
                return
            counted[0] += 1
            if counted[0] < n:
                return
            where = f'{n} after the first checkpoint and the step before'
        elif msg.data >= n:
            where = f'{n} or later'
        else:
            return
        steps.pop(0)
        counted[0] = 0
        client.call_async(request(value))
        print(f'at {msg.data} ({where}): {what} {value}', flush=True)

    while steps and steps[0][:2] == (False, 0):
        _, _, value = steps.pop(0)
        client.wait_for_service()
        future = client.call_async(request(value))
        rclpy.spin_until_future_complete(node, future)
        print(f'at start: {what} {value}: {future.result()}', flush=True)

    def on_event(msg):
        if not checkpointed and json.loads(msg.data).get('kind') == 'checkpoint':
            checkpointed.append(True)  # counting from the next number

    latched = QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(String, '/rory/events', on_event, latched)
    node.create_subscription(Int64, '/numbers', on_number, 100)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
