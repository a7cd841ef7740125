"""One level of a log-odds occupancy grid: bilinear interpolation and its gradient, ray updates.

The grid is an array ``log_odds[row, col]`` (float32) whose cell ``(row, col)`` covers
``[origin_x + col * res, origin_x + (col + 1) * res) x [origin_y + row * res, ...)`` in the map
frame, as in nav_msgs/OccupancyGrid. 0 is unknown (p = 0.5).

For scan matching the occupancy probability is taken as a continuous function of position by
bilinear interpolation between the four nearest cell centres, with its analytic gradient, as in
Kohlbrecher et al., "A Flexible and Scalable SLAM System with Full 3D Motion Estimation"
(SSRR 2011), Sec. IV-A. Map updates trace each beam with a Bresenham line in cell space: the
cells it crosses become more likely free, the cell it ends in more likely occupied; a cell is
updated at most once per scan, occupied winning over free (hector_mapping's update index).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
LogOdds = npt.NDArray[np.float32]


@dataclass(frozen=True)
class GridGeometry:
    """Where a grid level lies in the map frame (parameters, not state).

    Attributes:
        resolution: cell side (m).
        origin_x: map-frame x of the lower-left corner of cell (0, 0).
        origin_y: map-frame y of that corner.
        width: columns.
        height: rows.
    """

    resolution: float
    origin_x: float
    origin_y: float
    width: int
    height: int

    def continuous(self, xy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Map points as continuous (col, row) coordinates with cell centres at integers."""
        u = (xy[:, 0] - self.origin_x) / self.resolution - 0.5
        v = (xy[:, 1] - self.origin_y) / self.resolution - 0.5
        return u, v

    def cells(self, xy: FloatArray) -> tuple[IntArray, IntArray]:
        """(col, row) of the cells holding map points (may lie outside the grid)."""
        col = np.floor((xy[:, 0] - self.origin_x) / self.resolution).astype(np.int64)
        row = np.floor((xy[:, 1] - self.origin_y) / self.resolution).astype(np.int64)
        return col, row


def probability(log_odds: npt.ArrayLike) -> FloatArray:
    """Occupancy probability of log-odds values."""
    return np.asarray(1.0 / (1.0 + np.exp(-np.asarray(log_odds, dtype=np.float64))))


def interpolate(log_odds: LogOdds, geometry: GridGeometry,
                xy: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Occupancy probability M at map points and its gradient (dM/dx, dM/dy per metre).

    Points whose four neighbouring cell centres are not all inside the grid get M = 0 and a
    zero gradient: they add nothing to a Gauss-Newton step (hector_mapping does the same).
    """
    u, v = geometry.continuous(xy)
    fu, fv = np.floor(u), np.floor(v)
    c0, r0 = fu.astype(np.int64), fv.astype(np.int64)
    width = geometry.width
    inside = (c0 >= 0) & (c0 < width - 1) & (r0 >= 0) & (r0 < geometry.height - 1)
    base = np.where(inside, r0 * width + c0, 0)
    # The four neighbours' probabilities in one gather: p00, p10 (next column), p01 (next
    # row), p11.
    flat = log_odds.reshape(-1)
    p00, p10, p01, p11 = probability(flat[base[None, :] + np.array([[0], [1], [width],
                                                                      [width + 1]])])
    a = u - fu  # fraction towards the next column
    b = v - fv  # fraction towards the next row
    m = (1 - b) * ((1 - a) * p00 + a * p10) + b * ((1 - a) * p01 + a * p11)
    scale = 1.0 / geometry.resolution
    dm_du = ((1 - b) * (p10 - p00) + b * (p11 - p01)) * scale
    dm_dv = ((1 - a) * (p01 - p00) + a * (p11 - p10)) * scale
    m[~inside] = 0.0
    dm_du[~inside] = 0.0
    dm_dv[~inside] = 0.0
    return m, dm_du, dm_dv


def ray_cells(start: tuple[int, int], ends: IntArray) -> tuple[IntArray, IntArray]:
    """The cells a Bresenham line crosses from ``start`` to each end, the ends excluded.

    Args:
        start: (col, row) of the beam's origin.
        ends: (N, 2) int (col, row) of the beams' end cells.

    Returns:
        (cols, rows) of every crossed cell, all rays concatenated (repeats possible).
    """
    d = ends - np.asarray(start, dtype=np.int64)
    steps = np.max(np.abs(d), axis=1)
    total = int(steps.sum())
    if total == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    ray = np.repeat(np.arange(len(ends)), steps)
    k = np.arange(total) - np.repeat(np.cumsum(steps) - steps, steps)
    frac = k / steps[ray]
    cols = start[0] + np.rint(frac * d[ray, 0]).astype(np.int64)
    rows = start[1] + np.rint(frac * d[ray, 1]).astype(np.int64)
    return cols, rows


def update(log_odds: LogOdds, geometry: GridGeometry, origin_xy: tuple[float, float],
           ends_xy: FloatArray, free_delta: float, occupied_delta: float,
           clamp: float) -> None:
    """Integrate one scan, in place: beams from ``origin_xy`` to each of ``ends_xy`` (map frame).

    Every crossed cell gets ``free_delta`` once, every end cell ``occupied_delta`` once (and
    not the free update), and the touched cells are clamped to ``[-clamp, clamp]`` so that the
    map stays able to change. Cells outside the grid are skipped.
    """
    if len(ends_xy) == 0:
        return
    o_col, o_row = geometry.cells(np.asarray([origin_xy], dtype=np.float64))
    e_col, e_row = geometry.cells(ends_xy)
    f_col, f_row = ray_cells((int(o_col[0]), int(o_row[0])), np.stack([e_col, e_row], axis=1))
    # Work in the window the beams cover (clipped to the grid): marking cells in a boolean
    # mask updates each at most once, without sorting.
    c_lo = max(int(min(o_col[0], e_col.min())), 0)
    r_lo = max(int(min(o_row[0], e_row.min())), 0)
    c_hi = min(int(max(o_col[0], e_col.max())) + 1, geometry.width)
    r_hi = min(int(max(o_row[0], e_row.max())) + 1, geometry.height)
    if c_lo >= c_hi or r_lo >= r_hi:
        return
    window = log_odds[r_lo:r_hi, c_lo:c_hi]
    free = _mark(window.shape, f_row - r_lo, f_col - c_lo)
    occupied = _mark(window.shape, e_row - r_lo, e_col - c_lo)
    free &= ~occupied
    window[free] = np.maximum(window[free] + np.float32(free_delta), np.float32(-clamp))
    window[occupied] = np.minimum(window[occupied] + np.float32(occupied_delta),
                                  np.float32(clamp))


def _mark(shape: tuple[int, ...], rows: IntArray, cols: IntArray) -> npt.NDArray[np.bool_]:
    """A boolean mask of ``shape`` set at the (rows, cols) inside it."""
    mask = np.zeros(shape, dtype=bool)
    inside = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
    mask[rows[inside], cols[inside]] = True
    return mask
