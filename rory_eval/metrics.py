"""Quality metrics against the simulator's ground truth: maps, poses, 3D points.

These are the numbers the target issue asks for (and the evaluation reuses): how many observed
cells of a map agree with the ground-truth map, the IoU of their occupied cells, position
errors of a pose estimate against ground truth, and how far 3D points lie from the geometry.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from sim.maps import OccupancyMap
from sim.worlds import World

FloatArray = npt.NDArray[np.float64]

OCCUPIED_AT = 65  # map_server's occupied_thresh 0.65 on 0..100
FREE_BELOW = 20  # map_server's free_thresh 0.196


@dataclass(frozen=True)
class MapScore:
    """How an estimated occupancy grid agrees with the ground-truth map.

    Attributes:
        agreement: of the cells the estimate observed (occupied or free) that the ground truth
            knows, the fraction whose occupied/free class is the same.
        iou_occupied: |est occupied and truth occupied| / |est occupied or truth occupied|,
            over the cells the estimate observed; with ``tolerance`` cells, an estimated
            occupied cell counts as right if truth has an occupied cell that near (and vice
            versa), the usual allowance for a 5 cm grid.
        observed_cells: how many ground-truth-known cells the estimate observed.
        observed_fraction: observed_cells over the ground truth's free + occupied cells.
    """

    agreement: float
    iou_occupied: float
    observed_cells: int
    observed_fraction: float


def grid_from_msg(msg: Any) -> OccupancyMap:
    """A nav_msgs/OccupancyGrid as an OccupancyMap (the origin's rotation must be zero)."""
    q = msg.info.origin.orientation
    if abs(q.z) > 1e-6 or abs(q.x) > 1e-6 or abs(q.y) > 1e-6:
        msg_text = 'OccupancyGrid: a rotated origin is not supported by the metrics'
        raise ValueError(msg_text)
    data = np.asarray(msg.data, dtype=np.int8).reshape(msg.info.height, msg.info.width)
    return OccupancyMap(data, float(msg.info.resolution), float(msg.info.origin.position.x),
                        float(msg.info.origin.position.y))


def map_score(estimate: OccupancyMap, truth: OccupancyMap, tolerance: int = 1) -> MapScore:
    """Compare an estimated grid (any resolution and origin, in ``map``) to the ground truth.

    Each ground-truth cell takes the estimate's value at its centre (nearest cell). Estimate
    values >= 65 are occupied, 0..19 free, anything else (unknown, in between) unobserved.
    """
    cx, cy = truth.cell_centres()
    col = np.floor((cx - estimate.origin_x) / estimate.resolution).astype(np.int64)
    row = np.floor((cy - estimate.origin_y) / estimate.resolution).astype(np.int64)
    inside = (col >= 0) & (col < estimate.width) & (row >= 0) & (row < estimate.height)
    est = np.full(truth.data.shape, -1, dtype=np.int16)
    est[inside] = estimate.data[row[inside], col[inside]]
    est_occ = est >= OCCUPIED_AT
    est_free = (est >= 0) & (est < FREE_BELOW)
    known = truth.data >= 0
    truth_occ = truth.data >= OCCUPIED_AT
    observed = (est_occ | est_free) & known
    n = int(observed.sum())
    agreement = float(((est_occ == truth_occ) & observed).sum() / n) if n else 0.0
    est_o = est_occ & observed
    truth_o = truth_occ & observed
    if tolerance > 0:
        near_truth = _dilate(truth_occ, tolerance)
        near_est = _dilate(est_occ, tolerance)
        hit_est = est_o & near_truth  # estimated occupied with truth nearby
        hit_truth = truth_o & near_est  # truth occupied that the estimate found nearby
        union = int(est_o.sum() + truth_o.sum()) - min(int(hit_est.sum()), int(hit_truth.sum()))
        inter = min(int(hit_est.sum()), int(hit_truth.sum()))
    else:
        inter = int((est_o & truth_o).sum())
        union = int((est_o | truth_o).sum())
    iou = inter / union if union else 0.0
    return MapScore(agreement, iou, n, n / max(int(known.sum()), 1))


def _dilate(mask: npt.NDArray[np.bool_], cells: int) -> npt.NDArray[np.bool_]:
    out = mask.copy()
    h, w = mask.shape
    for dy in range(-cells, cells + 1):
        for dx in range(-cells, cells + 1):
            src = mask[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)]
            out[max(0, dy):h - max(0, -dy), max(0, dx):w - max(0, -dx)] |= src
    return out


def position_errors(estimates: Sequence[tuple[float, float, float]],
                    truth: Sequence[tuple[float, float, float, float]]) -> FloatArray:
    """Distance of each estimate ``(t, x, y)`` from ground truth ``(t, x, y, yaw)`` at t.

    Truth is interpolated linearly in time; estimates outside its time span are dropped.
    Both are in ``map``; ``t`` is sim time in seconds (a header stamp).
    """
    if not estimates or len(truth) < 2:
        return np.zeros(0)
    tt = np.array([r[0] for r in truth])
    tx = np.array([r[1] for r in truth])
    ty = np.array([r[2] for r in truth])
    est = np.array(estimates, dtype=np.float64)
    keep = (est[:, 0] >= tt[0]) & (est[:, 0] <= tt[-1])
    est = est[keep]
    x = np.interp(est[:, 0], tt, tx)
    y = np.interp(est[:, 0], tt, ty)
    return np.asarray(np.hypot(est[:, 1] - x, est[:, 2] - y), dtype=np.float64)


def distance_to_geometry(world: World, points: FloatArray) -> FloatArray:
    """Distance of each map-frame point ``(x, y, z)`` to the nearest surface of the world.

    Surfaces: the floor (z = 0) and every obstacle, a box or cylinder standing on the floor up
    to its height (walls included). Exact for points outside the solids.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    best = np.abs(p[:, 2])  # the floor
    for obstacle in world.obstacles:
        horizontal = obstacle.distance(p[:, 0], p[:, 1])  # negative inside the footprint
        height = obstacle.height
        above = p[:, 2] - height  # > 0 above the top
        below_top = np.minimum(0.0, above)  # depth under the top plane when inside
        d_out = np.hypot(np.maximum(horizontal, 0.0), np.maximum(above, 0.0))
        d_in = np.maximum(horizontal, below_top)  # inside: distance to the nearest face
        inside = (horizontal < 0) & (above < 0)
        d = np.where(inside, np.abs(d_in), d_out)
        best = np.minimum(best, d)
    return np.asarray(best, dtype=np.float64)


def near(points: FloatArray, reference: FloatArray, radius: float) -> npt.NDArray[np.bool_]:
    """For each point, whether some reference point lies within ``radius`` (exact).

    The reference is hashed into cubes of side ``radius``; a point's neighbours within the
    radius are all in the 27 cubes around its own. Each cube's points are taken one "layer"
    at a time (the k-th point of every cube), so the search stays vectorised however the
    points cluster.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    found = np.zeros(len(p), dtype=bool)
    if not len(p) or not len(r):
        return found
    lo = np.minimum(p.min(axis=0), r.min(axis=0)) - radius
    span = np.floor((np.maximum(p.max(axis=0), r.max(axis=0)) + radius - lo) / radius) + 3

    def key(cells: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        return np.asarray((cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2],
                          dtype=np.int64)

    ref_cells = np.floor((r - lo) / radius).astype(np.int64) + 1
    ref_keys = key(ref_cells)
    order = np.argsort(ref_keys, kind='stable')
    ref_keys, r = ref_keys[order], r[order]
    first = np.searchsorted(ref_keys, ref_keys, side='left')
    layer = np.arange(len(ref_keys)) - first  # rank of each point within its cube
    cells = np.floor((p - lo) / radius).astype(np.int64) + 1
    limit = radius * radius
    for k in range(int(layer.max()) + 1):
        in_layer = layer == k
        keys_k, pts_k = ref_keys[in_layer], r[in_layer]
        for offset in np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1])).T.reshape(-1, 3):
            todo = ~found
            if not todo.any():
                return found
            q = key(cells[todo] + offset)
            at = np.clip(np.searchsorted(keys_k, q), 0, len(keys_k) - 1)
            hit = keys_k[at] == q
            d2 = np.sum((pts_k[at] - p[todo]) ** 2, axis=1)
            idx = np.flatnonzero(todo)
            found[idx[hit & (d2 <= limit)]] = True
    return found
