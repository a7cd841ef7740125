"""Judging a crash run against the run without a crash: maps, models, goals."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from rory_eval.evaluation.judge import (
    judge,
    judge_goal,
    judge_map,
    judge_model,
    reached_goal,
)
from rory_eval.runs.plan import BARE, RunSpec
from rory_eval.runs.runner import RunRecord
from rory_eval.targets import Kind
from sim.worlds import get_world


def _save_map(folder: Path, data: np.ndarray, origin: tuple[float, float] = (0.0, 0.0)) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(folder / 'final_map.npz', data=data.astype(np.int8), resolution=0.05,
                        origin_x=origin[0], origin_y=origin[1])
    return folder


@pytest.fixture
def room() -> np.ndarray:
    """A 4 m x 4 m room: free inside, walls around, unknown outside; some in-between cells."""
    grid = np.full((100, 100), -1, dtype=np.int16)
    grid[10:90, 10:90] = 100
    grid[11:89, 11:89] = 0
    grid[40:42, 40:60] = 50  # seen, but neither free nor occupied
    return grid


def test_the_same_map_is_correct_on_every_measure(tmp_path: Path, room: np.ndarray) -> None:
    ref = _save_map(tmp_path / 'ref', room)
    crash = _save_map(tmp_path / 'crash', room)
    verdict = judge_map(crash, ref)
    assert verdict.correct is True
    assert verdict.measures == {'coverage': 1.0, 'agreement': 1.0, 'iou': 1.0}


def test_a_map_missing_what_was_seen_before_the_crash_is_incomplete(
        tmp_path: Path, room: np.ndarray) -> None:
    after_restart = np.full_like(room, -1)
    after_restart[:, 50:] = room[:, 50:]  # only the half seen after the crash
    verdict = judge_map(_save_map(tmp_path / 'crash', after_restart),
                        _save_map(tmp_path / 'ref', room))
    assert verdict.correct is False
    assert verdict.measures['coverage'] == pytest.approx(0.5, abs=0.05)
    assert 'coverage' in verdict.reason and 'agreement' not in verdict.reason


def test_a_map_built_in_a_shifted_frame_disagrees(tmp_path: Path, room: np.ndarray) -> None:
    # Restarted at the start pose while the robot was 40 cm further: the walls land elsewhere.
    verdict = judge_map(_save_map(tmp_path / 'crash', room, origin=(0.4, 0.0)),
                        _save_map(tmp_path / 'ref', room))
    assert verdict.correct is False
    assert verdict.measures['iou'] < 0.8


def test_a_missing_map_is_wrong_and_a_missing_reference_is_not_judged(
        tmp_path: Path, room: np.ndarray) -> None:
    ref = _save_map(tmp_path / 'ref', room)
    (tmp_path / 'none').mkdir()
    assert judge_map(tmp_path / 'none', ref).correct is False
    assert judge_map(ref, tmp_path / 'none').correct is None


def _save_model(folder: Path, points: np.ndarray) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / 'final_model.npy', points.astype(np.float32))
    return folder


def test_models_are_judged_by_precision_and_coverage(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    wall = np.column_stack([rng.uniform(0, 4, 4000), np.full(4000, 2.0), rng.uniform(0, 1, 4000)])
    ref = _save_model(tmp_path / 'ref', wall)
    same = judge_model(_save_model(tmp_path / 'same', wall + rng.normal(0, 0.005, wall.shape)),
                       ref)
    assert same.correct is True and same.measures['precision'] > 0.99
    half = judge_model(_save_model(tmp_path / 'half', wall[wall[:, 0] > 2.0]), ref)
    assert half.correct is False and half.measures['precision'] > 0.99
    assert half.measures['coverage'] == pytest.approx(0.5, abs=0.05)
    moved = judge_model(_save_model(tmp_path / 'moved', wall + np.array([0.0, 0.2, 0.0])), ref)
    assert moved.correct is False and moved.measures['precision'] < 0.05


def _record(world: str, method: str, *, end: tuple[float, float, float], statuses: list[str],
            collisions: int = 0, poses: list[tuple[float, float, float]] | None = None,
            target: str = 'navigator') -> RunRecord:
    spec = RunSpec(target, world, method, 0, None if method == BARE else 9.0, 30.0)
    x, y, yaw = end
    truth = [(0.0, 0.0, 0.0, 0.0), (30.0, x, y, yaw)]
    return RunRecord(run=spec.to_json(), statuses=statuses, collisions=collisions,
                     ground_truth=truth, poses=poses or [])


def test_the_goal_counts_only_when_the_robot_is_there_and_the_node_says_so() -> None:
    goal = get_world('real_room').goals['far_corner']
    at = (goal.x + 0.05, goal.y, goal.yaw)
    assert reached_goal(_record('real_room', BARE, end=at, statuses=['REACHED']))[0]
    assert not reached_goal(_record('real_room', BARE, end=at, statuses=['DRIVING']))[0]
    off = (goal.x + 0.5, goal.y, goal.yaw)
    assert not reached_goal(_record('real_room', BARE, end=off, statuses=['REACHED']))[0]
    turned = (goal.x, goal.y, goal.yaw + 1.0)
    assert not reached_goal(_record('real_room', BARE, end=turned, statuses=['REACHED']))[0]


def test_navigation_fails_when_the_goal_is_lost_or_the_robot_hits_something() -> None:
    goal = get_world('real_room').goals['far_corner']
    at = (goal.x, goal.y, goal.yaw)
    ref = _record('real_room', BARE, end=at, statuses=['DRIVING', 'REACHED'])
    lost = _record('real_room', 'restart', end=(1.0, 1.0, 0.0), statuses=['IDLE'])
    verdict = judge_goal(Kind.NAVIGATION, lost, ref)
    assert verdict.correct is False and 'goal not reached' in verdict.reason
    bumped = _record('real_room', 'rory', end=at, statuses=['REACHED'], collisions=2)
    assert judge_goal(Kind.NAVIGATION, bumped, ref).reason == '2 collisions'
    fine = _record('real_room', 'rory', end=at, statuses=['REACHED'])
    assert judge_goal(Kind.NAVIGATION, fine, ref).correct is True


def test_a_localizer_must_also_end_near_the_truth() -> None:
    goal = get_world('real_room').goals['far_corner']
    at = (goal.x, goal.y, goal.yaw)
    ref = _record('real_room', BARE, end=at, statuses=['REACHED'], target='amcl')
    off = _record('real_room', 'rory', end=at, statuses=['REACHED'], target='amcl',
                  poses=[(30.0, goal.x + 0.3, goal.y)])
    verdict = judge_goal(Kind.LOCALIZATION, off, ref)
    assert verdict.correct is False
    assert verdict.measures['final_error'] == pytest.approx(0.3, abs=1e-6)
    near = _record('real_room', 'rory', end=at, statuses=['REACHED'], target='amcl',
                   poses=[(30.0, goal.x + 0.03, goal.y)])
    assert judge_goal(Kind.LOCALIZATION, near, ref).correct is True


def test_a_reference_that_missed_the_goal_leaves_the_run_unjudged() -> None:
    ref = _record('real_room', BARE, end=(1.0, 1.0, 0.0), statuses=['DRIVING'])
    crash = _record('real_room', 'rory', end=(1.0, 1.0, 0.0), statuses=['DRIVING'])
    assert judge_goal(Kind.NAVIGATION, crash, ref).correct is None


def test_failed_runs_and_give_ups(tmp_path: Path, room: np.ndarray) -> None:
    ref_dir = _save_map(tmp_path / 'ref', room)
    crash_dir = _save_map(tmp_path / 'crash', room)
    spec = RunSpec('grid_slam', 'office_small', 'rory', 0, 9.0, 30.0)
    ref = RunRecord(run=RunSpec('grid_slam', 'office_small', BARE, 0, None, 30.0).to_json())
    gave_up = RunRecord(run=spec.to_json(), events=[{'kind': 'fatal', 'crashes': 5}])
    assert judge(Kind.MAP, gave_up, crash_dir, ref, ref_dir).reason == 'the supervisor gave up'
    failed = RunRecord(run=spec.to_json(), error='SimRunError: the clock never started')
    assert judge(Kind.MAP, failed, crash_dir, ref, ref_dir).correct is None
    assert math.isnan(RunRecord(run=spec.to_json()).cpu_percent)
