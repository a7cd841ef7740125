"""Log-odds grids as nav_msgs/OccupancyGrid values (plain numpy, no ROS)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

OCCUPIED = 100
FREE = 0
UNKNOWN = -1


def occupancy_values(log_odds: npt.NDArray[np.float32]) -> npt.NDArray[np.int8]:
    """Trinary OccupancyGrid values as hector_mapping publishes them.

    A cell is occupied when its log-odds is above 0 (p > 0.5), free when below, unknown when
    it was never updated (or its evidence cancelled exactly).
    """
    out = np.full(log_odds.shape, UNKNOWN, dtype=np.int8)
    out[log_odds < 0] = FREE
    out[log_odds > 0] = OCCUPIED
    return out


def known_extent(values: npt.NDArray[np.int8]) -> tuple[int, int, int, int] | None:
    """(row0, row1, col0, col1), half open, of the smallest box holding every known cell.

    None when no cell is known. The map is published cropped to this box: a 1024 x 1024 grid
    of which a 12 x 9 m building uses 5 % costs ~0.2 s to serialise in rclpy.
    """
    known = values != UNKNOWN
    rows = np.flatnonzero(known.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(known.any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
