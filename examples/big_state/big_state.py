"""BigState: a node whose state is a large array, like a mapper's grid or a voxel map.

A plain rclpy node that knows nothing of RORY. Its state is ``grid`` (a float32 array of
``BIG_STATE_MB`` megabytes, default 1), the cells it last touched and a tick count; a 20 Hz
timer updates a patch of the grid, as a mapper integrating a scan would.
"""

import os

import numpy as np
import rclpy
from rclpy.node import Node


class BigState(Node):
    """Holds a large grid and keeps changing it."""

    def __init__(self):
        super().__init__('big_state')
        megabytes = float(os.environ.get('BIG_STATE_MB', '1'))
        cells = int(megabytes * 1024 * 1024) // 4
        side = int(cells ** 0.5)
        self.grid = np.zeros((side, cells // side), dtype=np.float32)
        self.touched = []  # (row, col) of the last patches, newest last
        self.ticks = 0
        self.create_timer(0.05, self.on_tick)

    def on_tick(self):
        self.ticks += 1
        row = (self.ticks * 37) % (self.grid.shape[0] - 16)
        col = (self.ticks * 91) % (self.grid.shape[1] - 16)
        self.grid[row:row + 16, col:col + 16] += 0.1
        self.touched = [*self.touched, (row, col)][-100:]


def main():
    rclpy.init()
    node = BigState()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
