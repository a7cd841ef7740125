"""Scan matching: point-to-line ICP for refinement, correlative search for loop closures.

* ``icp``: point-to-line ICP (Censi, "An ICP variant using a point-to-line metric", ICRA
  2008), point-to-point where a reference point lies on no line. The reference (points of
  earlier keyframes in the map frame, each with the normal of the surface it lies on) is
  indexed by a grid holding, per cell, the nearest reference point within ``reach``; a
  correspondence is the closest of the four cells' points around the scan point. Each
  iteration solves the 3 x 3 normal equations of ``Σ w (nᵀ (R p + t - q))²`` with Huber
  weights. The Hessian ``JᵀJ`` says how well the scan pins the pose down: in a featureless
  corridor its smallest translational eigenvalue is near zero.
* ``search``: correlative scan matching (Olson, "Real-time correlative scan matching", ICRA
  2009): every pose on a grid of translations and rotations is scored by the mean value of a
  likelihood field (Thrun et al., Probabilistic Robotics, ch. 6.4, ``exp(-d² / 2 sigma²)``) under
  the scan's points. It finds the match when the prior is poor (a loop closure); ICP refines it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from graph_slam_se2 import FloatArray, transform_points, wrap_angle

Float32Array = npt.NDArray[np.float32]
IndexArray = npt.NDArray[np.int64]

_NO_POINT = np.iinfo(np.int64).max
_INDEX_BITS = 24  # reference points per grid: < 16.7 million


# -- normals -------------------------------------------------------------------------------


def estimate_normals(points: npt.NDArray[np.floating], neighbours: int = 12,
                     radius: float = 0.2, max_flatness: float = 0.5,
                     min_points: int = 5) -> tuple[FloatArray, npt.NDArray[np.bool_]]:
    """Unit normals of the surface under each point of a scan (points in beam order).

    The normal is the minor axis of the points up to ``neighbours`` beams either side that lie
    within ``radius`` of the point (a neighbourhood of ~0.4 m smooths out centimetres of range
    noise; the radius keeps other surfaces out). A point with fewer than ``min_points`` such
    neighbours, or whose neighbourhood is not a line (minor over major spread above
    ``max_flatness``: a corner, clutter), has no normal.

    Returns:
        Normals ``(n, 2)`` and whether each is valid.
    """
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    normals = np.zeros((n, 2))
    if n < min_points:
        return normals, np.zeros(n, dtype=bool)
    offsets = np.arange(-neighbours, neighbours + 1)
    index = np.arange(n)[:, None] + offsets[None, :]
    inside = (index >= 0) & (index < n)
    window = pts[np.clip(index, 0, n - 1)]  # (n, k, 2)
    near = np.hypot(window[:, :, 0] - pts[:, None, 0], window[:, :, 1] - pts[:, None, 1])
    use = (inside & (near <= radius)).astype(np.float64)
    count = use.sum(axis=1)
    mean = (window * use[:, :, None]).sum(axis=1) / np.maximum(count, 1)[:, None]
    d = (window - mean[:, None, :]) * use[:, :, None]
    cxx = (d[:, :, 0] ** 2).sum(axis=1)
    cyy = (d[:, :, 1] ** 2).sum(axis=1)
    cxy = (d[:, :, 0] * d[:, :, 1]).sum(axis=1)
    major = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)  # direction of the line
    normals[:, 0] = -np.sin(major)
    normals[:, 1] = np.cos(major)
    spread = np.sqrt(np.maximum((cxx - cyy) ** 2 + 4.0 * cxy**2, 0.0))
    big = 0.5 * (cxx + cyy + spread)
    small = np.maximum(0.5 * (cxx + cyy - spread), 0.0)
    valid = (count >= min_points) & (big > 1e-8) & (
        np.sqrt(small / np.maximum(big, 1e-12)) <= max_flatness)
    return normals, valid


# -- ICP -----------------------------------------------------------------------------------


@dataclass
class Reference:
    """Points with normals in the map, and a grid of the nearest one per cell (a cache).

    Attributes:
        points: ``(m, 2)`` map frame.
        normals: ``(m, 2)`` unit normals (zero where there is none).
        has_normal: ``(m,)`` whether the point lies on a line (else it is matched point to
            point).
        nearest: int64 ``(rows, cols)``: index of the point nearest the cell's centre within
            the reach, or -1.
        origin_x: map x of the grid's lower-left corner.
        origin_y: map y of it.
        resolution: cell side (m).
    """

    points: FloatArray
    normals: FloatArray
    has_normal: npt.NDArray[np.bool_]
    nearest: IndexArray
    origin_x: float
    origin_y: float
    resolution: float

    def lookup(self, xy: FloatArray) -> IndexArray:
        """Index of the reference point nearest each map point; -1 if none within reach.

        The candidates are the nearest points of the four cells whose centres surround the
        point; the closest of them to the point itself wins. One cell alone would give the
        point nearest that cell's centre, and point-to-point pairs would then pull the scan
        onto the cell lattice (a bias of up to half a cell).
        """
        rows, cols = self.nearest.shape
        u = (xy[:, 0] - self.origin_x) / self.resolution - 0.5
        v = (xy[:, 1] - self.origin_y) / self.resolution - 0.5
        c0 = np.floor(u).astype(np.int64)
        r0 = np.floor(v).astype(np.int64)
        best = np.full(xy.shape[0], -1, dtype=np.int64)
        best_d2 = np.full(xy.shape[0], np.inf)
        for dr, dc in ((0, 0), (0, 1), (1, 0), (1, 1)):
            r, c = r0 + dr, c0 + dc
            inside = (c >= 0) & (c < cols) & (r >= 0) & (r < rows)
            candidate = np.full(xy.shape[0], -1, dtype=np.int64)
            candidate[inside] = self.nearest[r[inside], c[inside]]
            found = candidate >= 0
            q = self.points[np.where(found, candidate, 0)]
            d2 = np.where(found, (q[:, 0] - xy[:, 0]) ** 2 + (q[:, 1] - xy[:, 1]) ** 2, np.inf)
            closer = d2 < best_d2
            best = np.where(closer, candidate, best)
            best_d2 = np.where(closer, d2, best_d2)
        return best


def build_reference(points: FloatArray, normals: FloatArray,
                    has_normal: npt.NDArray[np.bool_] | None = None, resolution: float = 0.05,
                    reach: float = 0.3) -> Reference:
    """Index points (with normals, where ``has_normal``; default all) by a nearest-point grid
    out to ``reach`` around them."""
    pts = np.asarray(points, dtype=np.float64)
    flags = (np.ones(pts.shape[0], dtype=bool) if has_normal is None
             else np.asarray(has_normal, dtype=bool))
    if pts.shape[0] == 0:
        return Reference(pts.reshape(0, 2), np.zeros((0, 2)), flags,
                         np.full((1, 1), -1, np.int64), 0.0, 0.0, resolution)
    x0 = math.floor((float(pts[:, 0].min()) - reach) / resolution) * resolution
    y0 = math.floor((float(pts[:, 1].min()) - reach) / resolution) * resolution
    cols = math.ceil((float(pts[:, 0].max()) + reach - x0) / resolution) + 1
    rows = math.ceil((float(pts[:, 1].max()) + reach - y0) / resolution) + 1
    radius = max(1, math.ceil(reach / resolution))
    offsets = np.arange(-radius, radius + 1)
    c = np.floor((pts[:, 0] - x0) / resolution).astype(np.int64)
    r = np.floor((pts[:, 1] - y0) / resolution).astype(np.int64)
    cc = c[:, None] + offsets[None, :]
    rr = r[:, None] + offsets[None, :]
    dx2 = (x0 + (cc + 0.5) * resolution - pts[:, :1]) ** 2
    dy2 = (y0 + (rr + 0.5) * resolution - pts[:, 1:]) ** 2
    d2 = dy2[:, :, None] + dx2[:, None, :]  # (m, window, window)
    # one int64 per (cell, point): squared distance in µm² above the point's index, so that a
    # minimum per cell picks the nearest point (ties: the lower index), in one ufunc pass
    key = (np.minimum(d2 * 1e6, 2.0**38).astype(np.int64) << _INDEX_BITS) | np.arange(
        pts.shape[0], dtype=np.int64)[:, None, None]
    key[d2 > reach * reach] = _NO_POINT
    cell = rr[:, :, None] * cols + cc[:, None, :]
    best = np.full(rows * cols, _NO_POINT, dtype=np.int64)
    np.minimum.at(best, cell.reshape(-1), key.reshape(-1))
    nearest = np.where(best == _NO_POINT, -1, best & ((1 << _INDEX_BITS) - 1))
    return Reference(pts, np.asarray(normals, dtype=np.float64), flags,
                     nearest.reshape(rows, cols), x0, y0, resolution)


@dataclass(frozen=True)
class Match:
    """The result of matching a scan.

    Attributes:
        pose: the scan's pose in the map frame ``(x, y, yaw)``.
        inliers: fraction of the scan's points with a correspondence within the inlier
            distance at ``pose``.
        rmse: root mean square point-to-line distance of those inliers (m).
        hessian: ``JᵀJ`` (3 x 3) at ``pose`` over the inliers, per scan point.
    """

    pose: FloatArray
    inliers: float
    rmse: float
    hessian: FloatArray

    @property
    def weakest_translation(self) -> float:
        """Smallest eigenvalue of the translational block of the Hessian (per point): near
        zero where the scan slides freely along one direction (a corridor), up to 0.5 with
        walls every way."""
        return float(np.linalg.eigvalsh(self.hessian[:2, :2])[0])


def icp(reference: Reference, points: npt.NDArray[np.floating], initial: FloatArray, *,
        iterations: int = 15, max_distance: float = 0.3, inlier_distance: float = 0.1,
        huber: float = 0.03, tolerance: float = 1e-4) -> Match:
    """ICP of ``points`` (robot frame) onto ``reference`` from ``initial``: point-to-line where
    the reference point has a normal, point-to-point where it has none (a pillar, a corner)."""
    pts = np.asarray(points, dtype=np.float64)
    pose = np.array(initial, dtype=np.float64)
    n = max(pts.shape[0], 1)
    if pts.shape[0] == 0 or reference.points.shape[0] == 0:
        return Match(pose, 0.0, 0.0, np.zeros((3, 3)))
    for _ in range(iterations):
        residual, jac, _ = _residuals(reference, pts, pose, max_distance)
        if residual.size < 6:
            break
        weight = np.minimum(1.0, huber / np.maximum(np.abs(residual), 1e-12))
        h = (jac * weight[:, None]).T @ jac
        g = (jac * weight[:, None]).T @ residual
        step = -np.linalg.solve(h + np.diag([1e-6, 1e-6, 1e-6]) * n, g)
        pose[0] += step[0]
        pose[1] += step[1]
        pose[2] = wrap_angle(float(pose[2] + step[2]))
        if abs(step[0]) + abs(step[1]) < tolerance and abs(step[2]) < tolerance:
            break
    residual, jac, matched = _residuals(reference, pts, pose, inlier_distance)
    if not matched:
        return Match(pose, 0.0, 0.0, np.zeros((3, 3)))
    rmse = float(np.sqrt(np.mean(residual**2)))
    return Match(pose, matched / n, rmse, (jac.T @ jac) / n)


def _residuals(reference: Reference, pts: FloatArray, pose: FloatArray,
               max_distance: float) -> tuple[FloatArray, FloatArray, int]:
    """Residuals and their Jacobian in (x, y, yaw) of the points with a correspondence closer
    than ``max_distance``: one row ``nᵀ(T p - q)`` per point-to-line pair, two rows
    ``T p - q`` per point-to-point pair; and how many points matched."""
    world = transform_points(pose, pts)
    index = reference.lookup(world)
    safe = np.where(index >= 0, index, 0)
    diff = world - reference.points[safe]
    ok = (index >= 0) & (np.hypot(diff[:, 0], diff[:, 1]) <= max_distance)
    nrm = reference.normals[safe]
    lined = ok & reference.has_normal[safe]
    pointed = ok & ~reference.has_normal[safe]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dx_dth = -s * pts[:, 0] - c * pts[:, 1]
    dy_dth = c * pts[:, 0] - s * pts[:, 1]
    nl, dl = nrm[lined], diff[lined]
    line_r = nl[:, 0] * dl[:, 0] + nl[:, 1] * dl[:, 1]
    line_j = np.stack([nl[:, 0], nl[:, 1], nl[:, 0] * dx_dth[lined] + nl[:, 1] * dy_dth[lined]],
                      axis=1)
    m = int(pointed.sum())
    point_r = diff[pointed].reshape(-1)  # x0, y0, x1, y1, ...
    point_j = np.zeros((2 * m, 3))
    point_j[0::2, 0] = 1.0
    point_j[1::2, 1] = 1.0
    point_j[0::2, 2] = dx_dth[pointed]
    point_j[1::2, 2] = dy_dth[pointed]
    return (np.concatenate([line_r, point_r]), np.concatenate([line_j, point_j]),
            int(ok.sum()))


# -- correlative search --------------------------------------------------------------------


@dataclass
class LikelihoodField:
    """``exp(-d² / 2 sigma²)`` on a grid, ``d`` the distance to the nearest reference point (to a
    cell; a cache, never state).

    Attributes:
        values: float32 ``(rows, cols)``, row 0 at ``origin_y``.
        origin_x: map x of the lower-left corner of cell (0, 0).
        origin_y: map y of that corner.
        resolution: cell side (m).
    """

    values: Float32Array
    origin_x: float
    origin_y: float
    resolution: float


def build_field(reference: npt.NDArray[np.floating], resolution: float, sigma: float,
                margin: float = 0.5) -> LikelihoodField:
    """The likelihood field of points ``(n, 2)`` (map frame), ``margin`` around them.

    ``max over neighbours of g(dx) g(dy) R`` with ``g`` Gaussian and ``R`` the raster of the
    points is separable into two 1-D maxima: the exact field (to a cell) out to 3 sigma costs two
    passes of ``6 sigma / resolution`` shifted maxima.
    """
    pts = np.asarray(reference, dtype=np.float64)
    if pts.shape[0] == 0:
        return LikelihoodField(np.zeros((1, 1), np.float32), 0.0, 0.0, resolution)
    reach = 3.0 * sigma
    x0 = math.floor((float(pts[:, 0].min()) - reach - margin) / resolution) * resolution
    y0 = math.floor((float(pts[:, 1].min()) - reach - margin) / resolution) * resolution
    cols = math.ceil((float(pts[:, 0].max()) + reach + margin - x0) / resolution) + 1
    rows = math.ceil((float(pts[:, 1].max()) + reach + margin - y0) / resolution) + 1
    raster = np.zeros((rows, cols), np.float32)
    c = np.floor((pts[:, 0] - x0) / resolution).astype(np.int64)
    r = np.floor((pts[:, 1] - y0) / resolution).astype(np.int64)
    raster[r, c] = 1.0
    radius = max(1, math.ceil(reach / resolution))
    weights = np.exp(-0.5 * (np.arange(-radius, radius + 1) * resolution / sigma) ** 2)
    field = _shifted_max(raster, weights, radius, axis=1)
    field = _shifted_max(field, weights, radius, axis=0)
    return LikelihoodField(field, x0, y0, resolution)


def _shifted_max(a: Float32Array, weights: FloatArray, radius: int, axis: int) -> Float32Array:
    out = a * np.float32(weights[radius])
    n = a.shape[axis]
    for k in range(1, min(radius, n - 1) + 1):
        w = np.float32(weights[radius + k])
        if axis == 1:
            np.maximum(out[:, k:], a[:, :-k] * w, out=out[:, k:])
            np.maximum(out[:, :-k], a[:, k:] * w, out=out[:, :-k])
        else:
            np.maximum(out[k:], a[:-k] * w, out=out[k:])
            np.maximum(out[:-k], a[k:] * w, out=out[:-k])
    return out


def search(field: LikelihoodField, points: npt.NDArray[np.floating], center: FloatArray,
           linear_window: float, angular_window: float,
           angular_step: float) -> tuple[FloatArray, float]:
    """Exhaustive search (nearest-cell lookups) of the pose of ``points`` around ``center``:
    every whole-cell translation within ``± linear_window``, every ``angular_step`` within
    ``± angular_window``.

    Returns:
        The best pose and its score (mean field value under the points, 0..1).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[0] == 0:
        return np.array(center, dtype=np.float64), 0.0
    res = field.resolution
    reach = math.ceil(linear_window / res)
    offsets = np.arange(-reach, reach + 1)
    pad = reach + 1
    values = np.pad(field.values, pad)
    rows, cols = values.shape
    flat = values.reshape(-1)
    shift = (offsets[:, None] * cols + offsets[None, :]).reshape(-1)  # (dy, dx) candidates
    n_angles = math.floor(angular_window / angular_step + 1e-9)
    best_score, best = -1.0, (0, 0, float(center[2]))
    for k in range(-n_angles, n_angles + 1):
        yaw = float(center[2]) + k * angular_step
        world = transform_points(np.array([center[0], center[1], yaw]), pts)
        c = np.floor((world[:, 0] - field.origin_x) / res).astype(np.int64) + pad
        r = np.floor((world[:, 1] - field.origin_y) / res).astype(np.int64) + pad
        ok = (c >= pad) & (c < cols - pad) & (r >= pad) & (r < rows - pad)
        base = (r * cols + c)[ok]
        if base.size == 0:
            continue
        scores = flat[base[None, :] + shift[:, None]].sum(axis=1)
        i = int(np.argmax(scores))
        if scores[i] > best_score:
            best_score = float(scores[i])
            best = (int(offsets[i // offsets.size]), int(offsets[i % offsets.size]), yaw)
    found = np.array([center[0] + best[1] * res, center[1] + best[0] * res, wrap_angle(best[2])],
                     dtype=np.float64)
    return found, max(best_score, 0.0) / pts.shape[0]
