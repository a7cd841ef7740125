"""The 3D model: a sparse voxel map, one averaged point and normal per voxel.

Each occupied voxel accumulates the sum of the points that fell into it (their mean is the
voxel's point), the sum of their unit normals (its surface normal), how many points it took
and in how many keyframes it was seen (``hits``: a voxel seen once is likely noise and is left
out of the published model). Voxels are kept sorted by a 63-bit key built from their integer
coordinates, so lookups are ``numpy.searchsorted`` and the whole model is five arrays: plain
data that a checkpoint stores as it is. Nearest-model-point queries search the 3 x 3 x 3 voxels
around a point, as voxel-hashing ICP front ends do (KinectFusion's successors, KISS-ICP).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_BITS = 21
_OFFSET = 1 << (_BITS - 1)  # voxel indices in [-2^20, 2^20): +-52 km at 5 cm
_MASK = (1 << _BITS) - 1


def _keys(index: IntArray) -> IntArray:
    i = index + _OFFSET
    keys: IntArray = (i[..., 0] << (2 * _BITS)) | (i[..., 1] << _BITS) | i[..., 2]
    return keys


_OCTANT = np.array([(dx, dy, dz) for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)],
                   dtype=np.int64)


@dataclass(frozen=True)
class Neighbourhood:
    """Candidate voxels around query points: model indices (-1: none) and their points."""

    index: IntArray  # (n, k)
    means: FloatArray  # (n, k, 3), inf where there is no voxel

    def nearest(self, points: FloatArray) -> tuple[IntArray, FloatArray]:
        """For each point ``(n, 3)``: the nearest candidate's model index (or -1), distance."""
        n = points.shape[0]
        if n == 0:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        with np.errstate(invalid='ignore'):
            d2 = np.sum((self.means - points[:, None, :]) ** 2, axis=-1)
        d2 = np.where(self.index >= 0, d2, np.inf)
        best = np.argmin(d2, axis=1)
        rows = np.arange(n)
        dist = np.sqrt(d2[rows, best])
        index = np.where(np.isfinite(dist), self.index[rows, best], -1)
        return index.astype(np.int64), dist


class VoxelModel:
    """Points averaged per voxel, sorted by voxel key.

    Args:
        voxel_size: edge of a voxel (m).

    Attributes:
        keys: sorted voxel keys, shape (n,).
        point_sums: weighted sum of the points per voxel (n, 3), in ``map``.
        normal_sums: weighted sum of the unit normals per voxel (n, 3).
        counts: sum of the weights per voxel (n,).
        hits: keyframes that saw the voxel (n,).
    """

    def __init__(self, voxel_size: float = 0.05) -> None:
        self.voxel_size = voxel_size
        self.keys: IntArray = np.zeros(0, dtype=np.int64)
        self.point_sums: FloatArray = np.zeros((0, 3))
        self.normal_sums: FloatArray = np.zeros((0, 3))
        self.counts: FloatArray = np.zeros(0)
        self.hits: IntArray = np.zeros(0, dtype=np.int64)

    def __len__(self) -> int:
        return int(self.keys.size)

    def voxel_keys(self, points: FloatArray) -> IntArray:
        """The key of the voxel each point ``(n, 3)`` falls into."""
        index = np.floor(points / self.voxel_size).astype(np.int64)
        return _keys(index)

    def integrate(self, points: FloatArray, normal_sums: FloatArray, weights: FloatArray
                  ) -> int:
        """Add one keyframe's points (``map``, (n, 3)) with their weights.

        Each point counts with its weight (the inverse variance of its depth), so a voxel's
        point leans on its nearest, least noisy observations. ``normal_sums`` are the points'
        unit normals already multiplied by their weights (zero where a point has none).

        Returns:
            how many new voxels it created.
        """
        if points.shape[0] == 0:
            return 0
        keys = self.voxel_keys(points)
        unique, inverse = np.unique(keys, return_inverse=True)
        m = unique.size
        p_sum = np.zeros((m, 3))
        n_sum = np.zeros((m, 3))
        for k in range(3):
            p_sum[:, k] = np.bincount(inverse, weights=points[:, k] * weights, minlength=m)
            n_sum[:, k] = np.bincount(inverse, weights=normal_sums[:, k], minlength=m)
        count = np.bincount(inverse, weights=weights, minlength=m)
        pos = np.searchsorted(self.keys, unique)
        found = pos < self.keys.size
        found[found] = self.keys[pos[found]] == unique[found]
        old = pos[found]
        self.point_sums[old] += p_sum[found]
        self.normal_sums[old] += n_sum[found]
        self.counts[old] += count[found]
        self.hits[old] += 1
        new = ~found
        if new.any():
            at = pos[new]
            self.keys = np.insert(self.keys, at, unique[new])
            self.point_sums = np.insert(self.point_sums, at, p_sum[new], axis=0)
            self.normal_sums = np.insert(self.normal_sums, at, n_sum[new], axis=0)
            self.counts = np.insert(self.counts, at, count[new])
            self.hits = np.insert(self.hits, at, np.ones(int(new.sum()), dtype=np.int64))
        return int(new.sum())

    def rebuild(self, points: list[FloatArray], normal_sums: list[FloatArray],
                weights: list[FloatArray]) -> None:
        """Replace the contents by these keyframes' clouds (in ``map``), each one hit."""
        if not points:
            self.keys = np.zeros(0, dtype=np.int64)
            self.point_sums = np.zeros((0, 3))
            self.normal_sums = np.zeros((0, 3))
            self.counts = np.zeros(0)
            self.hits = np.zeros(0, dtype=np.int64)
            return
        keys = [self.voxel_keys(p) for p in points]
        # A voxel's hits: how many keyframes have a point in it.
        per_frame = np.concatenate([np.unique(k) for k in keys])
        all_keys = np.concatenate(keys)
        unique, inverse = np.unique(all_keys, return_inverse=True)
        m = unique.size
        p = np.concatenate(points)
        n = np.concatenate(normal_sums)
        w = np.concatenate(weights)
        self.keys = unique
        self.point_sums = np.stack(
            [np.bincount(inverse, weights=p[:, k] * w, minlength=m) for k in range(3)], axis=1)
        self.normal_sums = np.stack(
            [np.bincount(inverse, weights=n[:, k], minlength=m) for k in range(3)], axis=1)
        self.counts = np.bincount(inverse, weights=w, minlength=m).astype(np.float64)
        self.hits = np.bincount(np.searchsorted(unique, per_frame), minlength=m).astype(np.int64)

    def neighbourhood(self, points: FloatArray, min_hits: int = 1) -> Neighbourhood:
        """Candidate voxels around each query point ``(n, 3)``: the 2 x 2 x 2 nearest it.

        The search (the costly part) is done once; ``Neighbourhood.nearest`` then pairs points
        that have moved by less than a voxel with the nearest of these, again and again.
        """
        n = points.shape[0]
        if n == 0 or self.keys.size == 0:
            return Neighbourhood(np.full((n, 1), -1, dtype=np.int64),
                                 np.full((n, 1, 3), np.inf))
        # The 2 x 2 x 2 voxels around the corner of the point's voxel nearest to it: the
        # nearest voxel point is almost always among them (a point's voxel mean lies within
        # its voxel), for a third of the cost of all 27.
        scaled = points / self.voxel_size
        index = np.floor(scaled).astype(np.int64)
        side = np.where(scaled - index >= 0.5, 1, -1)
        corner = index[:, None, :] + _OCTANT[None, :, :] * side[:, None, :]
        candidates = _keys(corner)
        pos = np.searchsorted(self.keys, candidates)
        pos = np.minimum(pos, self.keys.size - 1)
        found = self.keys[pos] == candidates
        if min_hits > 1:
            found &= self.hits[pos] >= min_hits
        index = np.where(found, pos, -1)
        means = np.where(found[..., None],
                         self.point_sums[pos] / self.counts[pos][..., None], np.inf)
        return Neighbourhood(index, means)

    def nearest(self, points: FloatArray, min_hits: int = 1) -> tuple[IntArray, FloatArray]:
        """The nearest voxel point to each query point among the 8 voxels around it.

        Returns:
            ``(index into the model's arrays or -1, distance or inf)``, each (n,).
        """
        return self.neighbourhood(points, min_hits).nearest(points)

    def means(self, index: IntArray | None = None) -> FloatArray:
        """Voxel points (means), of all voxels or of ``index``."""
        if index is None:
            return self.point_sums / self.counts[:, None]
        out: FloatArray = self.point_sums[index] / self.counts[index][:, None]
        return out

    def normals(self, index: IntArray) -> tuple[FloatArray, FloatArray]:
        """Unit normals of voxels ``index`` and their consistency in [0, 1].

        Consistency is the length of the mean of the unit normals the voxel took: 1 when they
        all agreed, near 0 where they point every way (an edge, a corner, noise).
        """
        sums = self.normal_sums[index]
        length = np.linalg.norm(sums, axis=1)
        consistency = length / self.counts[index]
        unit = sums / np.maximum(length, 1e-12)[:, None]
        return unit, consistency

    def points(self, min_hits: int = 1) -> FloatArray:
        """The model as points: the mean of each voxel seen in at least ``min_hits`` keyframes."""
        keep = self.hits >= min_hits
        out: FloatArray = self.point_sums[keep] / self.counts[keep][:, None]
        return out
