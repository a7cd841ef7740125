"""The SLAM state and its update per scan: match against the map, then maybe update the map.

``GridMapper`` holds everything a restart would lose: the log-odds grids of every level, the
current pose and the pose of the last map update (which the update thresholds compare
against). Everything else (the grids' geometry, the update factors) is configuration.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from grid_slam_grid import FloatArray, GridGeometry, LogOdds, update
from grid_slam_matcher import match, transform


@dataclass(frozen=True)
class MapperConfig:
    """Parameters of the mapper (hector_mapping's names where it has one).

    Attributes:
        map_resolution: cell side of the finest level (m).
        map_size: cells per side of the finest level; each coarser level halves it.
        map_multi_res_levels: number of levels (resolution doubles from one to the next).
        map_start_x: map-frame x of base_link at the first scan (the grid is centred on it).
        map_start_y: map-frame y of base_link at the first scan.
        map_start_yaw: its heading (rad).
        map_update_distance_thresh: the map is updated when the robot moved this far (m)...
        map_update_angle_thresh: ...or turned this much (rad) since the last update.
        update_factor_free: occupancy probability a crossing beam stands for (< 0.5).
        update_factor_occupied: occupancy probability a beam's end stands for (> 0.5).
        log_odds_clamp: cells are held to [-clamp, clamp] log-odds.
        iterations_coarse: Gauss-Newton iterations on every level but the finest.
        iterations_fine: Gauss-Newton iterations on the finest level.
        max_prediction_gap: scans further apart than this (s) are matched from the last pose
            instead of a constant-velocity prediction.
    """

    map_resolution: float = 0.05
    map_size: int = 1024
    map_multi_res_levels: int = 3
    map_start_x: float = 0.0
    map_start_y: float = 0.0
    map_start_yaw: float = 0.0
    map_update_distance_thresh: float = 0.4
    map_update_angle_thresh: float = 0.06
    update_factor_free: float = 0.4
    update_factor_occupied: float = 0.9
    log_odds_clamp: float = 5.0
    iterations_coarse: int = 3
    iterations_fine: int = 5
    max_prediction_gap: float = 0.5

    def geometries(self) -> list[GridGeometry]:
        """The levels' geometry, finest first; all cover the same square around the start."""
        half = self.map_size * self.map_resolution / 2
        ox, oy = self.map_start_x - half, self.map_start_y - half
        out = []
        for level in range(self.map_multi_res_levels):
            cells = self.map_size >> level
            out.append(GridGeometry(self.map_resolution * (1 << level), ox, oy, cells, cells))
        return out


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def wrap(angle: float) -> float:
    """An angle in (-pi, pi]."""
    return math.atan2(math.sin(angle), math.cos(angle))


def predict(pose: FloatArray, velocity: FloatArray, dt: float) -> FloatArray:
    """Where base_link will be after ``dt`` seconds at a constant body-frame velocity."""
    yaw = float(pose[2]) + 0.5 * float(velocity[2]) * dt  # midpoint heading over the step
    c, s = math.cos(yaw), math.sin(yaw)
    vx, vy = float(velocity[0]), float(velocity[1])
    return np.array([pose[0] + (c * vx - s * vy) * dt, pose[1] + (s * vx + c * vy) * dt,
                     pose[2] + velocity[2] * dt])


def body_velocity(before: FloatArray, after: FloatArray, dt: float) -> FloatArray:
    """The constant body-frame velocity that moves ``before`` to ``after`` in ``dt``."""
    turn = wrap(float(after[2] - before[2]))
    yaw = float(before[2]) + 0.5 * turn
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = float(after[0] - before[0]), float(after[1] - before[1])
    return np.array([c * dx + s * dy, -s * dx + c * dy, turn]) / dt


class GridMapper:
    """hector_mapping's core: multi-resolution scan-to-map matching and map updates.

    Args:
        config: parameters.

    Attributes:
        log_odds: one float32 grid per level, finest first (state).
        pose: base_link in the map frame, (x, y, yaw) (state).
        last_update_pose: the pose at the last map update, None before the first (state).
        velocity: (forward, lateral, yaw rate) of base_link per second, from the last two
            matched scans; predicts the next scan's pose (state).
        last_stamp_ns: the last matched scan's stamp (ns), None before the first (state).
        scans_matched: scans processed so far (state).
        map_updates: map updates so far (state).
    """

    def __init__(self, config: MapperConfig) -> None:
        self.config = config
        self.geometry = config.geometries()  # derived from config: not state
        self.log_odds: list[LogOdds] = [np.zeros((g.height, g.width), np.float32)
                                        for g in self.geometry]
        self.pose: FloatArray = np.array(
            [config.map_start_x, config.map_start_y, config.map_start_yaw], dtype=np.float64)
        self.last_update_pose: FloatArray | None = None
        self.velocity: FloatArray = np.zeros(3)
        self.last_stamp_ns: int | None = None
        self.scans_matched = 0
        self.map_updates = 0

    def process(self, points: FloatArray, laser_origin: tuple[float, float],
                stamp_ns: int) -> bool:
        """Match one scan (base_link endpoints, taken at ``stamp_ns``) to the map, then update
        the map if due.

        The first scan only initialises the map at the start pose. Returns whether the map
        was updated.
        """
        cfg = self.config
        dt = None if self.last_stamp_ns is None else (stamp_ns - self.last_stamp_ns) * 1e-9
        steady = dt is not None and 0.0 < dt <= cfg.max_prediction_gap
        if not steady:
            self.velocity = np.zeros(3)  # a gap or a jump back in time: predict nothing
        if self.last_update_pose is not None:
            iterations = [cfg.iterations_fine] + [cfg.iterations_coarse] * (len(self.geometry) - 1)
            guess = predict(self.pose, self.velocity, dt if steady and dt else 0.0)
            pose = match(list(zip(self.log_odds, self.geometry, strict=True)), points, guess,
                         iterations)
            pose[2] = wrap(float(pose[2]))
            if steady and dt:
                self.velocity = body_velocity(self.pose, pose, dt)
            self.pose = pose
        self.last_stamp_ns = stamp_ns
        self.scans_matched += 1
        if not self._update_due():
            return False
        self._integrate(points, laser_origin)
        self.last_update_pose = self.pose.copy()
        self.map_updates += 1
        return True

    def _update_due(self) -> bool:
        last = self.last_update_pose
        if last is None:
            return True
        moved = math.hypot(float(self.pose[0] - last[0]), float(self.pose[1] - last[1]))
        turned = abs(wrap(float(self.pose[2] - last[2])))
        return (moved > self.config.map_update_distance_thresh
                or turned > self.config.map_update_angle_thresh)

    def _integrate(self, points: FloatArray, laser_origin: tuple[float, float]) -> None:
        cfg = self.config
        ends = transform(points, self.pose)
        origin = transform(np.asarray([laser_origin], dtype=np.float64), self.pose)[0]
        free = _logit(cfg.update_factor_free)
        occupied = _logit(cfg.update_factor_occupied)
        for log_odds, geometry in zip(self.log_odds, self.geometry, strict=True):
            update(log_odds, geometry, (float(origin[0]), float(origin[1])), ends, free,
                   occupied, cfg.log_odds_clamp)
