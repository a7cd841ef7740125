"""State inside helper objects: a PID's integral and a 1-D Kalman filter's estimate."""

import json

import numpy as np
import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64, String


class Pid:
    def __init__(self, kp, ki):
        self.kp = kp
        self.ki = ki
        self.accu_e = 0.0
        self.last_e = 0.0

    def step(self, error):
        self.accu_e += error
        self.last_e = error
        return self.kp * error + self.ki * self.accu_e


class Kalman:
    def __init__(self):
        self.x = np.zeros(2)
        self.P = np.eye(2)

    def update(self, z):
        F = np.array([[1.0, 1.0], [0.0, 1.0]])
        self.x = F @ self.x
        self.P = F @ self.P @ F.T + 0.01 * np.eye(2)
        H = np.array([[1.0, 0.0]])
        S = H @ self.P @ H.T + 1.0
        K = self.P @ H.T / S
        self.x = self.x + (K * (z - H @ self.x)).ravel()
        self.P = (np.eye(2) - K @ H) @ self.P


class TrackerNode(Node):
    def __init__(self):
        super().__init__('tracker')
        self.pid = Pid(kp=0.5, ki=0.01)  # gains are configuration, not state
        self.kf = Kalman()
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.report)

    def on_number(self, msg):
        self.kf.update(float(msg.data))
        self.pid.step(float(msg.data) - self.kf.x[0])
        self.report()

    def report(self):
        state = {
            'accu_e': self.pid.accu_e,
            'last_e': self.pid.last_e,
            'x': self.kf.x.tolist(),
            'P': self.kf.P.tolist(),
        }
        self.pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = TrackerNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
