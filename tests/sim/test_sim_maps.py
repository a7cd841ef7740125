"""Ground-truth maps: they match the geometry (checked by MuJoCo's own ray casts), and files."""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np
import pytest

from sim.maps import FREE, OCCUPIED, UNKNOWN, OccupancyMap, ground_truth_map, load_map, write_map
from sim.model import compile_world
from sim.worlds import WORLDS, get_world

NAMES = sorted(WORLDS)


def _inside_by_mujoco(name: str, points: np.ndarray) -> np.ndarray:
    """Whether each (x, y) lies in an obstacle's footprint: a ray cast straight down hits it."""
    compiled = compile_world(get_world(name))
    data = mujoco.MjData(compiled.model)
    mujoco.mj_forward(compiled.model, data)
    geomid = np.zeros(1, np.int32)
    down = np.array([0.0, 0.0, -1.0])
    inside = np.zeros(len(points), bool)
    for k, (x, y) in enumerate(points):
        dist = mujoco.mj_ray(compiled.model, data, np.array([x, y, 5.0]), down, None, 1,
                             compiled.robot_body, geomid)
        inside[k] = dist >= 0 and int(geomid[0]) != compiled.floor_geom
    return inside


@pytest.mark.parametrize('name', NAMES)
def test_ground_truth_map_matches_the_geometry(name: str) -> None:
    world = get_world(name)
    grid = ground_truth_map(world)
    assert grid.resolution == 0.05
    rng = np.random.default_rng(7)
    xmin, ymin, xmax, ymax = world.bounds
    pts = rng.uniform((xmin, ymin), (xmax, ymax), size=(2500, 2))
    inside = _inside_by_mujoco(name, pts)
    assert inside.any() and not inside.all()
    values = np.array([grid.value_at(x, y) for x, y in pts])
    # A point inside an obstacle always lies in an occupied cell...
    assert (values[inside] == OCCUPIED).all()
    # ...and an occupied cell whose point is outside every obstacle is a boundary cell: some
    # obstacle lies within one cell diagonal of the point.
    stray = pts[(values == OCCUPIED) & ~inside]
    diag = grid.resolution * math.sqrt(2)
    near = np.zeros(len(stray), bool)
    for a in np.linspace(0, 2 * math.pi, 16, endpoint=False):
        ring = stray + diag * np.array([math.cos(a), math.sin(a)])
        near |= _inside_by_mujoco(name, ring)
    assert near.all(), f'occupied cells away from any obstacle at {stray[~near][:5]}'
    # Free space is what the robot can reach; its start and goals are free.
    assert grid.value_at(world.start.x, world.start.y) == FREE
    for goal in world.goals.values():
        assert grid.value_at(goal.x, goal.y) == FREE
    assert (values[~inside] != UNKNOWN).mean() > 0.9


def test_outside_the_walls_is_unknown() -> None:
    grid = ground_truth_map(get_world('office_small'))
    assert grid.value_at(-0.3, -0.3) == UNKNOWN
    assert grid.value_at(6.0, 9.3) == UNKNOWN
    assert grid.value_at(6.0, 4.25) == FREE  # the corridor
    assert grid.value_at(0.0, 4.0) == OCCUPIED  # the west wall


def test_wall_on_round_coordinates_fills_exactly_its_cells() -> None:
    grid = ground_truth_map(get_world('real_room'))
    # The south wall spans y in [-0.05, 0.05]: two rows of cells, not three.
    col = grid.cell_of(1.0, 0.0)[1]
    rows = [r for r in range(grid.height) if grid.data[r, col] == OCCUPIED
            and grid.origin_y + r * 0.05 < 1.0]
    ys = [round(grid.origin_y + r * 0.05, 3) for r in rows]
    assert ys == [-0.05, 0.0]


@pytest.mark.parametrize('name', NAMES)
def test_map_files_round_trip(tmp_path: Path, name: str) -> None:
    grid = ground_truth_map(get_world(name))
    pgm, yml = write_map(grid, tmp_path)
    text = yml.read_text()
    for field in ('image: map.pgm', 'resolution: 0.05', 'origin:', 'negate: 0',
                  'occupied_thresh: 0.65', 'free_thresh: 0.196', 'mode: trinary'):
        assert field in text
    assert pgm.read_bytes().startswith(b'P5\n')
    back = load_map(yml)
    assert back.resolution == grid.resolution
    assert (back.origin_x, back.origin_y) == pytest.approx((grid.origin_x, grid.origin_y))
    assert np.array_equal(back.data, grid.data)


def test_pgm_top_row_is_the_highest_y(tmp_path: Path) -> None:
    data = np.zeros((3, 4), np.int8)
    data[2, 0] = OCCUPIED  # highest row, lowest x
    write_map(OccupancyMap(data, 0.1, 0.0, 0.0), tmp_path)
    raw = (tmp_path / 'map.pgm').read_bytes()
    pixels = raw[-12:]
    assert pixels[0] == 0 and pixels[1] == 254


def test_load_errors_name_the_file_and_field(tmp_path: Path) -> None:
    bad = tmp_path / 'bad.yaml'
    bad.write_text('image: x.pgm\nresolution: 0.05\n')
    with pytest.raises(ValueError, match=r"bad\.yaml: field 'origin' missing"):
        load_map(bad)
    bad.write_text('image: x.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n')
    with pytest.raises(ValueError, match=r'x\.pgm: cannot read map image'):
        load_map(bad)
    (tmp_path / 'x.pgm').write_bytes(b'P6\n1 1\n255\n\x00\x00\x00')
    with pytest.raises(ValueError, match=r"x\.pgm: not a PGM image"):
        load_map(bad)
    (tmp_path / 'x.pgm').write_bytes(b'P2\n# ascii\n2 1\n255\n0 254\n')
    grid = load_map(bad)
    assert grid.data.tolist() == [[OCCUPIED, FREE]]
