"""targets/planar: the map and geometry modules amcl and lama_local share, and the links that
bring them into each folder, run in place and instrumented (targets/planar/README.md)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from planar_geometry import compose, odometry_at, relative, wrap_angle
from planar_map import distance_field, grid_from_values

TARGETS = Path(__file__).resolve().parents[2] / 'targets'
SHARED = ('planar_map.py', 'planar_geometry.py', 'planar_localizer.py')
USERS = ('amcl', 'lama_local')


# -- the modules -------------------------------------------------------------------------------

def test_distance_field_is_exact_within_its_reach() -> None:
    rng = np.random.default_rng(3)
    occupied = rng.random((40, 55)) < 0.02
    field = distance_field(occupied, 0.05, 0.6)
    rows, cols = np.nonzero(occupied)
    for r in range(40):
        for c in range(55):
            true = math.sqrt(float(((rows - r) ** 2 + (cols - c) ** 2).min())) * 0.05
            assert field[r, c] == pytest.approx(min(true, 0.6), abs=1e-6)
    assert distance_field(np.zeros((4, 4), bool), 0.05, 1.0).max() == pytest.approx(1.0)


def test_grid_from_values_refuses_malformed_maps() -> None:
    grid = grid_from_values([0] * 12, 4, 3, 0.05, -1.0, 2.0)
    assert grid.data.shape == (3, 4) and grid.origin_y == 2.0
    for args in (([0] * 11, 4, 3, 0.05), ([0] * 12, 4, 3, 0.0), ([], 0, 0, 0.05),
                 ([0] * 12, 4, 3, math.nan)):
        with pytest.raises(ValueError):
            grid_from_values(*args, 0.0, 0.0)


def test_odometry_lookup_interpolates_between_samples() -> None:
    history = [(0, 0.0, 0.0, 3.1), (20, 1.0, 2.0, -3.1)]
    x, y, yaw = odometry_at(history, 10)  # type: ignore[misc]
    assert (x, y) == pytest.approx((0.5, 1.0))
    assert abs(wrap_angle(yaw - math.pi)) < 1e-9  # through +-pi, not through 0
    assert odometry_at(history, -5) == (0.0, 0.0, 3.1)
    assert odometry_at(history, 99) == (1.0, 2.0, -3.1)
    assert odometry_at([], 0) is None
    a, b = (1.0, 2.0, 0.5), (1.5, 1.0, -2.0)
    assert compose(a, relative(a, b)) == pytest.approx(b)


def test_odometry_at_a_sample_stamp_does_not_depend_on_later_odometry() -> None:
    # A scan is used with the odometry at its stamp, whether that sample was the newest when the
    # scan arrived or later ones had come too (delivery order varies). wrap_angle changes the
    # last bits of most angles, so the sample must come back as it is, not interpolated at 0.
    history = [(k * 20, 0.1 * k + 0.013, 0.2 * k, 1.29 + 0.0137 * k) for k in range(8)]
    for k in range(7):
        assert odometry_at(history, k * 20) == odometry_at(history[:k + 1], k * 20)
        assert odometry_at(history, k * 20) == history[k][1:]


# -- the links -----------------------------------------------------------------------------------

@pytest.mark.parametrize('target', USERS)
def test_each_user_links_the_shared_modules_rather_than_copying_them(target: str) -> None:
    # A copy would drift from the other target's; the link keeps one module.
    for name in SHARED:
        link = TARGETS / target / name
        assert link.is_symlink(), f'{link} should be a link to ../planar/{name}'
        assert os.readlink(link) == f'../planar/{name}'
        assert link.resolve() == TARGETS / 'planar' / name


@pytest.mark.parametrize('target', USERS)
def test_an_instrumented_target_carries_the_shared_modules(target: str, tmp_path: Path) -> None:
    # As the evaluation instruments a target (rory_eval/runs/runner.py, instrument): the
    # folder alone is copied, so the links must arrive as files.
    source = TARGETS / target
    out = tmp_path / target
    subprocess.run([sys.executable, '-m', 'rory_instrument', str(source), '--vars',
                    str(source / 'keyvars.yaml'), '-o', str(out)], check=True,
                   capture_output=True, timeout=120)
    for name in SHARED:
        copied = out / name
        assert not copied.is_symlink()
        assert copied.read_bytes() == (TARGETS / 'planar' / name).read_bytes()
    # The instrumented node imports (inert without RORY_NODE) with its folder first on sys.path.
    env = {k: v for k, v in os.environ.items() if not k.startswith('RORY_')}
    modules = [name.removesuffix('.py') for name in SHARED]
    code = '\n'.join([f'import {target}_node',
                      *(f'import {m}; print({m}.__file__)' for m in modules)])
    done = subprocess.run([sys.executable, '-c', code], cwd=out, env=env, capture_output=True,
                          text=True, timeout=120, check=False)
    assert (done.returncode, done.stderr) == (0, '')
    assert [Path(line) for line in done.stdout.split()] == [out / name for name in SHARED]
