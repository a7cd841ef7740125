"""The occupancy grid a localizer localizes on, and its distance field.

``GridMap`` holds what ``/map`` said (nav_msgs/OccupancyGrid conventions: row 0 at the origin,
100 occupied, 0 free, -1 unknown). ``distance_field`` gives, for every cell, the distance to the
nearest occupied cell, truncated at a maximum: amcl's likelihood field (the classic
``map_update_cspace`` precomputation) and lama_local's cost surface (LaMa's distance map, static
here since the map is). It is exact (a two-pass separable Euclidean distance transform,
Felzenszwalb & Huttenlocher 2012, restricted to the truncation radius) and runs once per map,
not per scan.

Shared by targets/amcl and targets/lama_local, each of which links it into its folder
(targets/planar/README.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

OCCUPIED_AT = 65  # map_server's occupied_thresh 0.65 on 0..100
FREE_BELOW = 20  # map_server's free_thresh 0.196


@dataclass
class GridMap:
    """An occupancy grid in the ``map`` frame (unrotated origin).

    Attributes:
        data: int8 (height, width), row 0 at ``origin_y``; 100 occupied, 0 free, -1 unknown.
        resolution: cell side (m).
        origin_x: x of the lower-left corner of cell (0, 0).
        origin_y: y of that corner.
    """

    data: npt.NDArray[np.int8]
    resolution: float
    origin_x: float
    origin_y: float

    @property
    def height(self) -> int:
        """Rows."""
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        """Columns."""
        return int(self.data.shape[1])

    def occupied(self) -> npt.NDArray[np.bool_]:
        """Cells at or above map_server's occupied threshold."""
        return np.asarray(self.data >= OCCUPIED_AT)

    def free(self) -> npt.NDArray[np.bool_]:
        """Cells below map_server's free threshold (unknown, -1, is not free)."""
        return np.asarray((self.data >= 0) & (self.data < FREE_BELOW))


def grid_from_values(values: npt.ArrayLike, width: int, height: int, resolution: float,
                     origin_x: float, origin_y: float) -> GridMap:
    """Check and wrap the fields of an OccupancyGrid.

    Raises:
        ValueError: the sizes disagree, the resolution is not positive, or the origin is not
            finite (the message names what is wrong).
    """
    if width <= 0 or height <= 0:
        raise ValueError(f'empty grid ({width} x {height})')
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise ValueError(f'resolution must be positive, got {resolution}')
    if not (math.isfinite(origin_x) and math.isfinite(origin_y)):
        raise ValueError(f'origin is not finite: ({origin_x}, {origin_y})')
    data = np.asarray(values, dtype=np.int8)
    if data.size != width * height:
        raise ValueError(f'{data.size} cells for a {width} x {height} grid')
    return GridMap(data.reshape(height, width).copy(), float(resolution), float(origin_x),
                   float(origin_y))


def distance_field(occupied: npt.NDArray[np.bool_], resolution: float,
                   max_distance: float) -> npt.NDArray[np.float32]:
    """Distance (m) from each cell centre to the nearest occupied cell centre, at most max.

    Exact Euclidean distance within ``max_distance``; ``max_distance`` beyond it (and
    everywhere when nothing is occupied).
    """
    reach = max(1, math.ceil(max_distance / resolution))
    h, w = occupied.shape
    big = float(reach + 1)
    # Pass 1: along each column, the distance in cells to the nearest occupied cell.
    column = np.full((h, w), big)
    column[occupied] = 0.0
    for dy in range(1, reach + 1):
        if dy < h:
            # a cell dy rows below / above an occupied one
            np.minimum(column[:-dy], np.where(occupied[dy:], float(dy), big), out=column[:-dy])
            np.minimum(column[dy:], np.where(occupied[:-dy], float(dy), big), out=column[dy:])
    # Pass 2: along each row, min over columns c' of column(c')^2 + (c - c')^2.
    g2 = column * column
    best = g2.copy()
    for dx in range(1, reach + 1):
        if dx < w:
            d2 = float(dx * dx)
            np.minimum(best[:, :-dx], g2[:, dx:] + d2, out=best[:, :-dx])
            np.minimum(best[:, dx:], g2[:, :-dx] + d2, out=best[:, dx:])
    dist = np.sqrt(best) * resolution
    out: npt.NDArray[np.float32] = np.minimum(dist, max_distance).astype(np.float32)
    return out
