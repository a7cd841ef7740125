"""The global costmap: the static map, inflated by the robot's footprint plus a cost gradient.

As in ROS's costmap_2d inflation layer: a cell whose centre lies closer than the robot's
footprint radius (plus half a cell and a small safety margin) to an obstacle is *lethal* (the
robot's centre may not be there), and beyond that the cost decays exponentially with the
distance until ``inflation_radius``, so plans keep to the middle of corridors and doors.

Distances come from an exact Euclidean distance transform limited to the inflation radius: a
column pass (distance to the nearest obstacle in the same column, in cells) and then a row pass
over the few horizontal offsets that can still matter. Unknown cells count as obstacles for
planning (outside the walls), as move_base does with ``track_unknown_space``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

OCCUPIED_AT = 65  # map_server's occupied_thresh 0.65 on the 0..100 scale


@dataclass
class GridMap:
    """An occupancy grid as received on ``/map`` (the navigator's copy of it: key state).

    Attributes:
        data: int8 ``(height, width)``, row 0 at ``origin_y``; 0..100 occupancy, -1 unknown.
        resolution: cell side (m).
        origin_x: map-frame x of the lower-left corner of cell (0, 0).
        origin_y: map-frame y of that corner.
        stamp_ns: the message's header stamp (ns), to tell a new map from the same one again.
    """

    data: npt.NDArray[np.int8]
    resolution: float
    origin_x: float
    origin_y: float
    stamp_ns: int

    def same_as(self, other: GridMap) -> bool:
        """Whether other is the same map (a latched map delivered again)."""
        return (self.stamp_ns == other.stamp_ns and self.resolution == other.resolution
                and self.origin_x == other.origin_x and self.origin_y == other.origin_y
                and self.data.shape == other.data.shape
                and bool(np.array_equal(self.data, other.data)))


@dataclass(frozen=True)
class InflationParams:
    """How obstacles are inflated.

    Attributes:
        robot_radius: radius of the circle holding the footprint (m).
        safety_margin: extra clearance added to the lethal zone (m).
        inflation_radius: distance from an obstacle beyond which a cell costs nothing extra (m).
        cost_scaling: exponential decay rate of the cost with distance (1/m).
        cost_weight: a cell's step cost is ``1 + cost_weight * cost`` with cost in (0, 1].
        unknown_is_lethal: plan through unknown cells or not.
    """

    robot_radius: float = 0.205
    safety_margin: float = 0.02
    inflation_radius: float = 0.8
    cost_scaling: float = 4.0
    cost_weight: float = 3.0
    unknown_is_lethal: bool = True


@dataclass
class Costmap:
    """Derived from a GridMap (and obstacles the scan saw); a cache, never key state.

    Attributes:
        resolution, origin_x, origin_y: as the GridMap's.
        distance: distance from each cell centre to the nearest obstacle cell centre (m),
            capped at ``inflation_radius + resolution``.
        lethal: cells the robot's centre may not occupy.
        step_cost: per-cell multiplier of the length of a step into it; inf where lethal.
    """

    resolution: float
    origin_x: float
    origin_y: float
    distance: npt.NDArray[np.float32]
    lethal: BoolArray
    step_cost: FloatArray

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width)."""
        return (int(self.lethal.shape[0]), int(self.lethal.shape[1]))

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of map point (x, y); may lie outside the grid."""
        return (math.floor((y - self.origin_y) / self.resolution),
                math.floor((x - self.origin_x) / self.resolution))

    def contains(self, cell: tuple[int, int]) -> bool:
        """Whether a (row, col) lies on the grid."""
        return 0 <= cell[0] < self.shape[0] and 0 <= cell[1] < self.shape[1]

    def centre_of(self, row: int, col: int) -> tuple[float, float]:
        """Map-frame centre of a cell."""
        return (self.origin_x + (col + 0.5) * self.resolution,
                self.origin_y + (row + 0.5) * self.resolution)

    def distance_at(self, points: FloatArray) -> FloatArray:
        """Obstacle distance at map points ``(N, 2)``; 0 off the grid."""
        cols = np.floor((points[:, 0] - self.origin_x) / self.resolution).astype(np.int64)
        rows = np.floor((points[:, 1] - self.origin_y) / self.resolution).astype(np.int64)
        h, w = self.shape
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        out = np.zeros(len(points))
        out[inside] = self.distance[rows[inside], cols[inside]]
        return out

    def lethal_at(self, points: FloatArray) -> npt.NDArray[np.bool_]:
        """Whether each map point ``(N, 2)`` is lethal (off the grid counts as lethal)."""
        cols = np.floor((points[:, 0] - self.origin_x) / self.resolution).astype(np.int64)
        rows = np.floor((points[:, 1] - self.origin_y) / self.resolution).astype(np.int64)
        h, w = self.shape
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        out = np.ones(len(points), dtype=bool)
        out[inside] = self.lethal[rows[inside], cols[inside]]
        return out


def obstacle_mask(grid: GridMap, unknown_is_lethal: bool) -> BoolArray:
    """Cells that count as obstacles: occupied, and unknown if so configured."""
    data = grid.data
    mask = data >= OCCUPIED_AT
    if unknown_is_lethal:
        mask |= data < 0
    return np.asarray(mask)


def distance_transform(obstacles: BoolArray, max_cells: int) -> npt.NDArray[np.float32]:
    """Euclidean distance in cells from each cell centre to the nearest obstacle centre.

    Exact up to ``max_cells``; anything farther (or a grid with no obstacle) reads
    ``max_cells + 1``.
    """
    h = obstacles.shape[0]
    cap = max_cells + 1
    # Column pass: cells to the nearest obstacle in the same column, both directions.
    vertical = np.where(obstacles, 0, cap).astype(np.int32)
    for r in range(1, h):
        np.minimum(vertical[r], vertical[r - 1] + 1, out=vertical[r])
    for r in range(h - 2, -1, -1):
        np.minimum(vertical[r], vertical[r + 1] + 1, out=vertical[r])
    np.minimum(vertical, cap, out=vertical)
    squared = vertical.astype(np.int64) ** 2
    best = squared.copy()
    # Row pass: the nearest obstacle is in some column within max_cells.
    for dx in range(1, max_cells + 1):
        shift = dx * dx
        np.minimum(best[:, dx:], squared[:, :-dx] + shift, out=best[:, dx:])
        np.minimum(best[:, :-dx], squared[:, dx:] + shift, out=best[:, :-dx])
    return np.minimum(np.sqrt(best), cap).astype(np.float32)


def build_costmap(grid: GridMap, params: InflationParams,
                  extra_obstacles: FloatArray | None = None) -> Costmap:
    """The costmap of a map, plus obstacle points ``(N, 2)`` in ``map`` the scan saw.

    Args:
        grid: the static map.
        params: footprint and inflation.
        extra_obstacles: map-frame points to mark as obstacles (off-grid ones are ignored).
    """
    res = grid.resolution
    obstacles = obstacle_mask(grid, params.unknown_is_lethal)
    h, w = obstacles.shape
    if extra_obstacles is not None and len(extra_obstacles):
        cols = np.floor((extra_obstacles[:, 0] - grid.origin_x) / res).astype(np.int64)
        rows = np.floor((extra_obstacles[:, 1] - grid.origin_y) / res).astype(np.int64)
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        obstacles = obstacles.copy()
        obstacles[rows[inside], cols[inside]] = True
    max_cells = math.ceil(params.inflation_radius / res)
    distance = distance_transform(obstacles, max_cells) * np.float32(res)
    lethal_radius = params.robot_radius + 0.5 * res + params.safety_margin
    lethal = distance < lethal_radius - 1e-6
    # The outermost ring of cells is lethal too, so a plan never leaves the grid.
    lethal[0, :] = lethal[-1, :] = True
    lethal[:, 0] = lethal[:, -1] = True
    gradient = np.exp(-params.cost_scaling * (distance.astype(np.float64) - lethal_radius))
    cost = np.where(distance <= params.inflation_radius, np.minimum(gradient, 1.0), 0.0)
    step_cost = 1.0 + params.cost_weight * cost
    step_cost[lethal] = np.inf
    return Costmap(res, grid.origin_x, grid.origin_y, distance, lethal, step_cost)
