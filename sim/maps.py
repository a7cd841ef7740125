"""Ground-truth occupancy grids rendered from a world's geometry, and map_server files.

Grid convention (the same as nav_msgs/OccupancyGrid): ``data[row, col]`` with row 0 at the
map's origin (lowest y) and col 0 at the lowest x; the cell ``(row, col)`` covers
``[origin_x + col * res, origin_x + (col + 1) * res) x [origin_y + row * res, ...)``.
Values: 100 occupied, 0 free, -1 unknown.

A cell is occupied when it overlaps an obstacle's footprint; free when the robot could reach
it from the start pose through free cells (4-connected); unknown otherwise (outside the walls,
inside closed spaces). Files follow the map_server convention: a binary PGM (occupied 0, free
254, unknown 205, top row = highest y) and a YAML with ``image``, ``resolution``, ``origin``,
``negate``, ``occupied_thresh``, ``free_thresh``, ``mode``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import yaml

from .worlds import World

OCCUPIED = 100
FREE = 0
UNKNOWN = -1

_PGM_OCCUPIED = 0
_PGM_FREE = 254
_PGM_UNKNOWN = 205


@dataclass
class OccupancyMap:
    """An occupancy grid in the map frame.

    Attributes:
        data: int8 array (height, width); 100 occupied, 0 free, -1 unknown; row 0 at origin_y.
        resolution: cell side (m).
        origin_x: map-frame x of the lower-left corner of cell (0, 0).
        origin_y: map-frame y of that corner.
    """

    data: npt.NDArray[np.int8]
    resolution: float
    origin_x: float
    origin_y: float

    @property
    def width(self) -> int:
        """Number of columns."""
        return int(self.data.shape[1])

    @property
    def height(self) -> int:
        """Number of rows."""
        return int(self.data.shape[0])

    def cell_of(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the cell holding map point (x, y); may be outside the grid."""
        col = math.floor((x - self.origin_x) / self.resolution)
        row = math.floor((y - self.origin_y) / self.resolution)
        return row, col

    def value_at(self, x: float, y: float) -> int:
        """Cell value at map point (x, y); UNKNOWN outside the grid."""
        row, col = self.cell_of(x, y)
        if 0 <= row < self.height and 0 <= col < self.width:
            return int(self.data[row, col])
        return UNKNOWN

    def cell_centres(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Map-frame x and y of every cell centre, each shaped like ``data``."""
        xs = self.origin_x + (np.arange(self.width) + 0.5) * self.resolution
        ys = self.origin_y + (np.arange(self.height) + 0.5) * self.resolution
        gx, gy = np.meshgrid(xs, ys)
        return gx, gy


def ground_truth_map(world: World, resolution: float = 0.05, margin: float = 0.5) -> OccupancyMap:
    """Render the occupancy grid of ``world`` from its geometry.

    Args:
        world: the world.
        resolution: cell side (m); the origin is snapped to a multiple of it so that walls on
            round coordinates fall on cell edges.
        margin: extra space around the world's bounds (m).

    Returns:
        The grid (occupied, free as reachable from the start pose, unknown elsewhere).
    """
    xmin, ymin, xmax, ymax = world.bounds
    ox = round(math.floor((xmin - margin) / resolution) * resolution, 9)
    oy = round(math.floor((ymin - margin) / resolution) * resolution, 9)
    width = math.ceil((xmax + margin - ox) / resolution)
    height = math.ceil((ymax + margin - oy) / resolution)
    grid = OccupancyMap(np.zeros((height, width), np.int8), resolution, ox, oy)
    cx, cy = grid.cell_centres()
    occupied = np.zeros((height, width), dtype=bool)
    half = resolution / 2
    for obstacle in world.obstacles:
        occupied |= obstacle.overlaps_cells(cx, cy, half)
    reachable = _flood(~occupied, grid.cell_of(world.start.x, world.start.y))
    data = np.full((height, width), UNKNOWN, np.int8)
    data[reachable] = FREE
    data[occupied] = OCCUPIED
    grid.data = data
    return grid


def _flood(free: npt.NDArray[np.bool_], seed: tuple[int, int]) -> npt.NDArray[np.bool_]:
    """Cells 4-connected to ``seed`` through ``free`` cells."""
    h, w = free.shape
    seen = np.zeros_like(free)
    r0, c0 = seed
    if not (0 <= r0 < h and 0 <= c0 < w) or not free[r0, c0]:
        raise ValueError(f'start cell {seed} is not a free cell of the map')
    seen[r0, c0] = True
    queue = deque([(r0, c0)])
    # A plain BFS: ~100k cells take ~0.2 s, once per world; no scipy here.
    flat_free = free.tolist()
    flat_seen = seen.tolist()
    while queue:
        r, c = queue.popleft()
        for rr, cc in ((r + 1, c), (r - 1, c), (r, c + 1), (r, c - 1)):
            if 0 <= rr < h and 0 <= cc < w and flat_free[rr][cc] and not flat_seen[rr][cc]:
                flat_seen[rr][cc] = True
                queue.append((rr, cc))
    return np.array(flat_seen, dtype=bool)


def write_map(grid: OccupancyMap, folder: Path, name: str = 'map') -> tuple[Path, Path]:
    """Write ``name.pgm`` and ``name.yaml`` (map_server convention) into ``folder``.

    Returns:
        The paths of the PGM and the YAML.
    """
    folder.mkdir(parents=True, exist_ok=True)
    pgm_path = folder / f'{name}.pgm'
    yaml_path = folder / f'{name}.yaml'
    pixels = np.full(grid.data.shape, _PGM_UNKNOWN, np.uint8)
    pixels[grid.data == FREE] = _PGM_FREE
    pixels[grid.data == OCCUPIED] = _PGM_OCCUPIED
    pixels = pixels[::-1]  # image rows run top (highest y) to bottom
    header = f'P5\n# ground truth, resolution {grid.resolution}\n{grid.width} {grid.height}\n255\n'
    pgm_path.write_bytes(header.encode('ascii') + pixels.tobytes())
    meta = {
        'image': pgm_path.name,
        'mode': 'trinary',
        'resolution': float(grid.resolution),
        'origin': [round(float(grid.origin_x), 6), round(float(grid.origin_y), 6), 0.0],
        'negate': 0,
        'occupied_thresh': 0.65,
        'free_thresh': 0.196,  # map_saver's value: 205 (unknown) is not free
    }
    yaml_path.write_text(yaml.safe_dump(meta, sort_keys=False))
    return pgm_path, yaml_path


def load_map(yaml_path: Path) -> OccupancyMap:
    """Load a map_server map (YAML + PGM, binary P5 or ASCII P2).

    Pixel p (0..255) is read as occupancy ``(255 - p) / 255`` (or ``p / 255`` with
    ``negate: 1``): above ``occupied_thresh`` occupied, below ``free_thresh`` free, else unknown.

    Raises:
        ValueError: a missing or malformed field or image; the message names the file.
    """
    try:
        meta = yaml.safe_load(Path(yaml_path).read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ValueError(f'{yaml_path}: cannot read map YAML: {err}') from err
    if not isinstance(meta, dict):
        raise ValueError(f'{yaml_path}: expected a mapping')
    for key in ('image', 'resolution', 'origin'):
        if key not in meta:
            raise ValueError(f'{yaml_path}: field {key!r} missing')
    origin = meta['origin']
    if not (isinstance(origin, list) and len(origin) >= 2):
        raise ValueError(f'{yaml_path}: field \'origin\' must be [x, y, yaw]')
    image_path = Path(yaml_path).parent / str(meta['image'])
    pixels = _read_pgm(image_path)
    occ = pixels.astype(np.float64) / 255.0
    if not int(meta.get('negate', 0)):
        occ = 1.0 - occ
    occupied_thresh = float(meta.get('occupied_thresh', 0.65))
    free_thresh = float(meta.get('free_thresh', 0.196))
    data = np.full(pixels.shape, UNKNOWN, np.int8)
    data[occ > occupied_thresh] = OCCUPIED
    data[occ < free_thresh] = FREE
    return OccupancyMap(data[::-1].copy(), float(meta['resolution']), float(origin[0]),
                        float(origin[1]))


def _read_pgm(path: Path) -> npt.NDArray[np.uint8]:
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise ValueError(f'{path}: cannot read map image: {err}') from err
    tokens: list[bytes] = []
    pos = 0
    # Header: magic, width, height, maxval, separated by whitespace, with # comments.
    while len(tokens) < 4:
        while pos < len(raw) and raw[pos:pos + 1].isspace():
            pos += 1
        if raw[pos:pos + 1] == b'#':
            while pos < len(raw) and raw[pos:pos + 1] != b'\n':
                pos += 1
            continue
        end = pos
        while end < len(raw) and not raw[end:end + 1].isspace():
            end += 1
        if end == pos:
            raise ValueError(f'{path}: truncated PGM header')
        tokens.append(raw[pos:end])
        pos = end
    magic, width, height, maxval = tokens[0], int(tokens[1]), int(tokens[2]), int(tokens[3])
    if maxval != 255:
        raise ValueError(f'{path}: only 8-bit PGM is supported (maxval {maxval})')
    if magic == b'P5':
        body = raw[pos + 1:pos + 1 + width * height]
        if len(body) != width * height:
            raise ValueError(f'{path}: expected {width * height} pixels, found {len(body)}')
        return np.frombuffer(body, np.uint8).reshape(height, width).copy()
    if magic == b'P2':
        values = np.array(raw[pos:].split(), dtype=np.int64)
        if values.size != width * height:
            raise ValueError(f'{path}: expected {width * height} pixels, found {values.size}')
        return values.astype(np.uint8).reshape(height, width)
    raise ValueError(f'{path}: not a PGM image (magic {magic!r})')
