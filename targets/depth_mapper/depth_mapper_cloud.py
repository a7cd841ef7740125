"""An organised depth cloud: decoding PointCloud2 bytes and surface normals per pixel.

Kept free of ROS so the decoding and the normals can be tested on plain arrays; the node hands
in the message's fields.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

FLOAT32 = 7  # sensor_msgs/PointField.FLOAT32


class CloudError(ValueError):
    """A cloud that cannot be decoded; the message says why."""


@dataclass(frozen=True)
class FieldSpec:
    """One PointField: name, byte offset, datatype code and count."""

    name: str
    offset: int
    datatype: int
    count: int = 1


def decode_xyz(data: bytes | bytearray | memoryview, height: int, width: int, point_step: int,
               fields: Sequence[FieldSpec], is_bigendian: bool = False) -> F32:
    """The organised cloud's x, y, z as a ``(height, width, 3)`` float32 array.

    Args:
        data: the message's ``data`` bytes.
        height: rows (1 for an unorganised cloud, which is refused: normals need neighbours).
        width: columns.
        point_step: bytes per point.
        fields: the message's fields; x, y and z must be FLOAT32.
        is_bigendian: byte order of the data.

    Raises:
        CloudError: missing or non-float32 x/y/z, a size that does not add up, or an
            unorganised cloud.
    """
    if height < 3 or width < 3:
        msg = f'an organised cloud of at least 3 x 3 is needed, got {height} x {width}'
        raise CloudError(msg)
    by_name = {f.name: f for f in fields}
    offsets = []
    for name in ('x', 'y', 'z'):
        spec = by_name.get(name)
        if spec is None or spec.datatype != FLOAT32 or spec.count != 1:
            msg = f'field {name!r} missing or not a single FLOAT32'
            raise CloudError(msg)
        if spec.offset % 4 or spec.offset + 4 > point_step:
            msg = f'field {name!r} at offset {spec.offset} does not fit point_step {point_step}'
            raise CloudError(msg)
        offsets.append(spec.offset // 4)
    if point_step % 4 or point_step <= 0:
        msg = f'point_step {point_step} is not a positive multiple of 4'
        raise CloudError(msg)
    expected = height * width * point_step
    if len(data) < expected:
        msg = f'{len(data)} bytes of data, {height} x {width} x {point_step} = {expected} expected'
        raise CloudError(msg)
    dtype = np.dtype('>f4' if is_bigendian else '<f4')
    raw = np.frombuffer(bytes(data[:expected]), dtype=dtype).reshape(height, width, -1)
    return np.ascontiguousarray(raw[:, :, offsets], dtype=np.float32)


def valid_mask(points: F32, min_depth: float, max_depth: float) -> BoolArray:
    """Pixels with a finite point whose depth (optical z) lies in [min_depth, max_depth]."""
    z = points[..., 2]
    with np.errstate(invalid='ignore'):
        ok: BoolArray = np.isfinite(points).all(axis=-1) & (z >= min_depth) & (z <= max_depth)
    return ok


def organised_normals(points: F32, valid: BoolArray, step: int = 2,
                      max_jump: float = 0.1) -> tuple[FloatArray, BoolArray]:
    """Unit surface normals per pixel from the neighbours ``step`` pixels away.

    The normal is the cross product of the horizontal and vertical central differences (the
    usual organised-cloud estimate, as in KinectFusion), turned to face the camera. A pixel
    gets none where a neighbour is missing or lies across a depth jump (more than
    ``max_jump`` times the depth per pixel of baseline, so edges do not produce normals).

    Returns:
        ``(normals (h, w, 3) float64, has_normal (h, w) bool)``.
    """
    p = np.where(valid[..., None], points, np.nan).astype(np.float64)
    h, w = valid.shape
    normals = np.zeros((h, w, 3))
    has = np.zeros((h, w), dtype=bool)
    s = step
    left, right = p[s:-s, :-2 * s], p[s:-s, 2 * s:]
    up, down = p[:-2 * s, s:-s], p[2 * s:, s:-s]
    du = right - left
    dv = down - up
    n = np.cross(du, dv)
    centre = p[s:-s, s:-s]
    depth = centre[..., 2]
    with np.errstate(invalid='ignore'):
        limit = max_jump * 2 * s * depth
        smooth = (np.abs(du[..., 2]) < limit) & (np.abs(dv[..., 2]) < limit)
        norm = np.linalg.norm(n, axis=-1)
        ok = np.isfinite(norm) & (norm > 1e-12) & smooth & np.isfinite(depth)
    n = np.where(ok[..., None], n / np.where(ok, norm, 1.0)[..., None], 0.0)
    # Face the camera (the origin of the optical frame): n . p < 0.
    facing = np.einsum('ijk,ijk->ij', n, np.nan_to_num(centre))
    n = np.where((facing > 0)[..., None], -n, n)
    normals[s:-s, s:-s] = n
    has[s:-s, s:-s] = ok
    return normals, has
