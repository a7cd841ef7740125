"""Quality metrics against ground truth: maps, positions, 3D points."""

from __future__ import annotations

import numpy as np
import pytest

from rory_eval.metrics import distance_to_geometry, map_score, position_errors
from sim.maps import OccupancyMap, ground_truth_map
from sim.worlds import get_world


@pytest.fixture(scope='module')
def truth() -> OccupancyMap:
    return ground_truth_map(get_world('real_room'))


def test_the_truth_agrees_with_itself(truth: OccupancyMap) -> None:
    score = map_score(truth, truth, tolerance=0)
    assert score.agreement == 1.0 and score.iou_occupied == 1.0
    assert score.observed_fraction == 1.0


def test_a_map_shifted_by_one_cell_is_forgiven_only_with_tolerance(truth: OccupancyMap) -> None:
    shifted = OccupancyMap(truth.data, truth.resolution, truth.origin_x + 0.05, truth.origin_y)
    strict = map_score(shifted, truth, tolerance=0)
    tolerant = map_score(shifted, truth, tolerance=1)
    assert strict.iou_occupied < 0.9
    assert tolerant.iou_occupied > 0.95
    assert strict.agreement == tolerant.agreement < 1.0


def test_an_unknown_estimate_observes_nothing(truth: OccupancyMap) -> None:
    blank = OccupancyMap(np.full_like(truth.data, -1), 0.05, truth.origin_x, truth.origin_y)
    score = map_score(blank, truth)
    assert score.observed_cells == 0 and score.agreement == 0.0


def test_a_coarser_estimate_is_resampled(truth: OccupancyMap) -> None:
    coarse = OccupancyMap(truth.data[::2, ::2].copy(), 0.10, truth.origin_x, truth.origin_y)
    assert map_score(coarse, truth).agreement > 0.9


def test_position_errors_interpolate_truth_in_time() -> None:
    truth = [(0.0, 0.0, 0.0, 0.0), (1.0, 1.0, 0.0, 0.0)]
    errors = position_errors([(0.5, 0.5, 0.1), (2.0, 0.0, 0.0)], truth)
    assert errors.tolist() == pytest.approx([0.1])  # the second is outside truth's span


def test_distance_to_geometry() -> None:
    world = get_world('real_room')
    column = next(o for o in world.obstacles if 'obstacle' in o.name)
    points = np.array([
        [column.x, column.y, column.height + 0.1],  # above its top
        [1.0, 1.0, 0.0],  # on the floor
        [1.0, 1.0, 0.3],  # in the air, 0.3 above the floor
    ])
    d = distance_to_geometry(world, points)
    assert d[0] == pytest.approx(0.1) and d[1] == 0.0
    assert d[2] == pytest.approx(min(0.3, float(world.clearance(np.array([1.0]),
                                                                 np.array([1.0]))[0])))


def test_near_is_exact_against_brute_force() -> None:
    from rory_eval.metrics import near

    rng = np.random.default_rng(3)
    reference = rng.uniform(0, 1, (400, 3))
    reference[:50] = reference[0]  # a crowded cube: many points share one
    points = rng.uniform(-0.1, 1.1, (300, 3))
    d = np.linalg.norm(points[:, None, :] - reference[None, :, :], axis=2).min(axis=1)
    for radius in (0.02, 0.05, 0.1):
        assert np.array_equal(near(points, reference, radius), d <= radius)
    assert not near(points, np.zeros((0, 3)), 0.05).any()
