"""A talker that pauses, in the shape of ros2/demos' deadline demo (quality_of_service_demo_py).

A 10 Hz publish timer says a count. Every 2 s a second timer pauses the talker: its callback
cancels the publish timer and makes a one-shot pause timer; when that expires it says the
count once more, resets the publish timer and destroys itself. Which timers exist, and which
are cancelled, is the node's state as much as its count: a recovery that loses the pause timer
skips a saying and says a count twice; one that starts the cancelled publish timer says during
a pause.

Each saying on /said is ``<count> <tick|resume> <paused|running>``: a ``tick`` while paused is
a cancelled timer firing.
"""

import json

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile
from std_msgs.msg import String

PAUSE_S = 0.6


class PauseTalker(Node):
    def __init__(self):
        super().__init__('pause_talker')
        self.count = 0
        self.pauses = 0
        every = QoSProfile(depth=1000, history=HistoryPolicy.KEEP_ALL,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.said_pub = self.create_publisher(String, '/said', every)
        self.state_pub = self.create_publisher(String, '/state', 10)
        self.publish_timer = self.create_timer(0.1, self.on_tick)
        self.pause_timer = None
        self.create_timer(2.0, self.pause_for)

    def on_tick(self):
        self.say('tick')

    def say(self, how):
        self.count += 1
        paused = 'paused' if self.pause_timer else 'running'
        self.said_pub.publish(String(data=f'{self.count} {how} {paused}'))
        self.report()

    def pause_for(self):
        if self.pause_timer:
            return
        self.publish_timer.cancel()
        self.pause_timer = self.create_timer(PAUSE_S, self._pause_expired)
        self.pauses += 1
        self.report()

    def _pause_expired(self):
        self.say('resume')
        self.publish_timer.reset()
        self.destroy_timer(self.pause_timer)
        self.pause_timer = None
        self.report()

    def report(self):
        state = {'count': self.count, 'pauses': self.pauses,
                 'paused': self.pause_timer is not None}
        self.state_pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = PauseTalker()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
