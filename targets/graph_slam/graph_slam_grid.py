"""The occupancy grid assembled from keyframes: per cell, how many beams ended in it (hits)
and how many crossed it (passes); log odds follow from the counts.

Counting instead of clamping log odds per update makes the grid independent of the order the
scans were added in: rebuilding it from every keyframe at its optimised pose gives exactly the
grid that adding the same keyframes one by one at those poses gives, and a rebuild is one
``bincount`` over all of them. Counting beams rather than scans keeps walls thin under range
noise: a cell just in front of a wall, where a few noisy returns end, is crossed by many more
beams that end behind it (the counting model of Probabilistic Robotics, Thrun et al., ch. 9,
with the log-odds update of its inverse sensor model).

A return lies on an obstacle's surface, so the obstacle's cell is the one just behind it: each
hit is counted ``hit_depth`` beyond the measured range, else a surface on a cell boundary puts
half its hits in the free cell in front. The grid grows in whole chunks as the robot sees
further.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from graph_slam_se2 import FloatArray, transform_points

CountArray = npt.NDArray[np.int32]
IndexArray = npt.NDArray[np.int64]

CHUNK_CELLS = 64  # the grid grows by whole chunks, aligned to the map origin


@dataclass
class OccupancyCounts:
    """Hit and pass counts on a grid in the map frame (this is key state).

    Attributes:
        hits: int32 ``(rows, cols)``: beams that ended in the cell; row 0 at ``origin_y``.
        passes: int32, same shape: beams that crossed the cell.
        resolution: cell side (m).
        origin_x: map x of the lower-left corner of cell (0, 0).
        origin_y: map y of that corner.
    """

    hits: CountArray
    passes: CountArray
    resolution: float
    origin_x: float = 0.0
    origin_y: float = 0.0

    @classmethod
    def empty(cls, resolution: float) -> OccupancyCounts:
        """A grid with no cells yet."""
        return cls(np.zeros((0, 0), np.int32), np.zeros((0, 0), np.int32), resolution)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols)."""
        return int(self.hits.shape[0]), int(self.hits.shape[1])

    def grow_to(self, xmin: float, ymin: float, xmax: float, ymax: float) -> None:
        """Enlarge the grid (by whole chunks) so that it covers the given box."""
        res = self.resolution
        chunk = CHUNK_CELLS * res
        rows, cols = self.shape
        old = (round(self.origin_x / res), round(self.origin_y / res))
        if rows and cols:
            xmin, ymin = min(xmin, self.origin_x), min(ymin, self.origin_y)
            xmax = max(xmax, self.origin_x + cols * res)
            ymax = max(ymax, self.origin_y + rows * res)
        c0 = math.floor(xmin / chunk) * CHUNK_CELLS
        r0 = math.floor(ymin / chunk) * CHUNK_CELLS
        c1 = math.ceil(xmax / chunk) * CHUNK_CELLS
        r1 = math.ceil(ymax / chunk) * CHUNK_CELLS
        if rows and cols and (c0, r0, c1, r1) == (old[0], old[1], old[0] + cols, old[1] + rows):
            return
        hits = np.zeros((r1 - r0, c1 - c0), np.int32)
        passes = np.zeros_like(hits)
        if rows and cols:
            dr, dc = old[1] - r0, old[0] - c0
            hits[dr:dr + rows, dc:dc + cols] = self.hits
            passes[dr:dr + rows, dc:dc + cols] = self.passes
        self.hits, self.passes = hits, passes
        self.origin_x, self.origin_y = c0 * res, r0 * res

    def add_scans(self, scans: list[tuple[FloatArray, FloatArray]], hit_depth: float) -> None:
        """Count scans: for each, rays from ``sensor`` ``(x, y)`` to its endpoints ``(n, 2)``
        (map frame). Cells a ray crosses before its end are passes; its end's cell is a hit."""
        scans = [(s, e) for s, e in scans if e.shape[0]]
        if not scans:
            return
        res = self.resolution
        ends = [_deepen(s, e, hit_depth) for s, e in scans]
        every = np.concatenate([np.vstack([s[None, :], e]) for (s, _), e in zip(scans, ends,
                                                                                strict=True)])
        self.grow_to(float(every[:, 0].min()) - res, float(every[:, 1].min()) - res,
                     float(every[:, 0].max()) + res, float(every[:, 1].max()) + res)
        rows, cols = self.shape
        hit_cells = self._flat(np.concatenate(ends), cols)
        pass_cells = np.concatenate([self._passes(s, e, cols)
                                     for (s, _), e in zip(scans, ends, strict=True)])
        self.hits += np.bincount(hit_cells, minlength=rows * cols).astype(np.int32).reshape(
            rows, cols)
        self.passes += np.bincount(pass_cells, minlength=rows * cols).astype(np.int32).reshape(
            rows, cols)

    def _passes(self, sensor: FloatArray, ends: FloatArray, cols: int) -> IndexArray:
        """The cells the rays cross before their ends, one entry per sample. A sample in the
        end's own cell counts too: the beam did cross that part of the cell, and under range
        noise this keeps a wall one cell thick (the cell just in front of it, where short
        returns end, is crossed by the many beams that end further on)."""
        samples, _ = _ray_samples(sensor, ends, self.resolution)
        return self._flat(samples, cols)

    def _flat(self, xy: FloatArray, cols: int) -> IndexArray:
        c = np.floor((xy[:, 0] - self.origin_x) / self.resolution).astype(np.int64)
        r = np.floor((xy[:, 1] - self.origin_y) / self.resolution).astype(np.int64)
        return r * cols + c

    def log_odds(self, hit_log_odds: float, pass_log_odds: float) -> npt.NDArray[np.float32]:
        """Log odds of occupancy per cell (0 where nothing was seen)."""
        return (self.hits * np.float32(hit_log_odds)
                + self.passes * np.float32(pass_log_odds)).astype(np.float32)

    def occupancy(self, hit_log_odds: float, pass_log_odds: float, occupied_above: float,
                  free_below: float) -> npt.NDArray[np.int8]:
        """Trinary map values: 100 occupied, 0 free, -1 unknown (unseen or undecided).

        Args:
            hit_log_odds: log odds added per hit (positive).
            pass_log_odds: log odds added per pass (negative).
            occupied_above: occupancy probability at or above which a cell is occupied.
            free_below: probability at or below which it is free.
        """
        lo = self.log_odds(hit_log_odds, pass_log_odds)
        out = np.full(lo.shape, -1, np.int8)
        seen = (self.hits + self.passes) > 0
        out[seen & (lo >= _logit(occupied_above))] = 100
        out[seen & (lo <= _logit(free_below))] = 0
        return out


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def _deepen(sensor: FloatArray, endpoints: FloatArray, depth: float) -> FloatArray:
    d = endpoints - sensor[None, :]
    length = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
    return np.asarray(endpoints + d * (depth / length)[:, None], dtype=np.float64)


def _ray_samples(sensor: FloatArray, endpoints: FloatArray,
                 step: float) -> tuple[FloatArray, IndexArray]:
    """Points ``(m, 2)`` every ``step`` along each ray, at ``(k + 1/2) step``, strictly
    before its end, and the ray each belongs to."""
    dx = endpoints[:, 0] - sensor[0]
    dy = endpoints[:, 1] - sensor[1]
    length = np.hypot(dx, dy)
    count = np.maximum(np.ceil(length / step - 0.5).astype(np.int64), 0)
    total = int(count.sum())
    if total == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    ray = np.repeat(np.arange(length.size), count)
    along = np.arange(total) - np.repeat(np.cumsum(count) - count, count)  # 0..count-1 per ray
    t = (along + 0.5) * step / np.maximum(length[ray], 1e-9)
    return np.stack([sensor[0] + t * dx[ray], sensor[1] + t * dy[ray]], axis=1), ray


def scan_in_map(pose: FloatArray, laser_xy: FloatArray,
                points: npt.NDArray[np.floating]) -> tuple[FloatArray, FloatArray]:
    """The sensor position and a scan's endpoints in the map for a keyframe at ``pose``."""
    sensor = transform_points(pose, laser_xy.reshape(1, 2))[0]
    return sensor, transform_points(pose, points)


def rebuild(resolution: float, scans: Iterable[tuple[FloatArray, npt.NDArray[np.floating]]],
            laser_xy: FloatArray, hit_depth: float, batch: int = 32) -> OccupancyCounts:
    """A grid counted afresh from ``(pose, points)`` of every keyframe (``batch`` at a time,
    to bound the memory of the ray samples)."""
    items = [scan_in_map(pose, laser_xy, points) for pose, points in scans]
    grid = OccupancyCounts.empty(resolution)
    if items:
        every = np.concatenate([np.vstack([s[None, :], e]) for s, e in items])
        grid.grow_to(float(every[:, 0].min()) - resolution - hit_depth,
                     float(every[:, 1].min()) - resolution - hit_depth,
                     float(every[:, 0].max()) + resolution + hit_depth,
                     float(every[:, 1].max()) + resolution + hit_depth)
    for k in range(0, len(items), batch):
        grid.add_scans(items[k:k + batch], hit_depth)
    return grid
