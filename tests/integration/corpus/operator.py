"""Not a node under test: the operator, taking the steps it is given one after another, each
only once the one before it was taken (so the node is asked in the order given, however late
the first checkpoint falls among the numbers):

    N=VALUE    at the first number it sees from N on (it may join after the first went by;
               N=0: as soon as the service is there, before any number)
    cK=VALUE   at the K-th number seen after both the node's first checkpoint (read on
               /rory/events) and the step before, so that it lands after that checkpoint

A careful client: it sends a step's request only once the one before was answered, and sends
a request again when no response came within RESEND_AFTER (a request sent while the node's
process was dead is lost, as in ROS: docs/architecture.md, "Services"); each operator's
requests are harmless to repeat (a value set again, a transition refused when already made).

    operator.py gain STEP ...        set /gain_controller's `gain` (its ~/set_parameters)
    operator.py fast STEP ...        call /mode_switch/fast_mode (std_srvs/SetBool), VALUE 0|1
    operator.py lifecycle STEP ...   ask /lifecycle_counter/change_state for a transition
"""

import json
import sys
import time

import rclpy
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rcl_interfaces.srv import SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import Int64, String
from std_srvs.srv import SetBool

RESEND_AFTER = 1.0  # seconds without a response


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

    pending = []  # [future, sent at, request value, what was printed] while unanswered

    def answered():
        """Whether the last request was answered; sends it again when its time is up."""
        if not pending:
            return True
        future, sent_at, value, said = pending
        if future.done():
            pending.clear()
            return True
        if time.monotonic() - sent_at > RESEND_AFTER and client.service_is_ready():
            pending[:] = [client.call_async(request(value)), time.monotonic(), value, said]
            print(f'{said}: no response in {RESEND_AFTER} s, sent again', flush=True)
        return False

    def on_number(msg):
        if not answered() or not steps:
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
        said = f'at {msg.data} ({where}): {what} {value}'
        pending[:] = [client.call_async(request(value)), time.monotonic(), value, said]
        print(said, flush=True)

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
