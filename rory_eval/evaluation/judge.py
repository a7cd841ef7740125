"""Is a crash run's result correct? Judged against the same target's run without a crash.

As in the paper (section IV-B): a map or 3D model must be *complete* compared with the normal
case; a navigating or localizing robot must *reach the goal*. In numbers:

* **map** (grid_slam, graph_slam): the crash run's final ``/map`` against the reference's
  final ``/map``. Each grid's cells are classed occupied (>= 65), free (< 20) or unobserved.
  *coverage*: of the cells the reference observed, the fraction the crash run observed too,
  >= :data:`MAP_COVERAGE`; *agreement*: of the cells both observed, the fraction in the same
  class, >= :data:`MAP_AGREEMENT`; *IoU* of the occupied cells, with a one-cell allowance,
  >= :data:`MAP_IOU`. A map rebuilt from the crash on is incomplete (coverage); one built in
  a frame that jumped is wrong (agreement, IoU).
* **model** (depth_mapper): the crash run's final point model against the reference's:
  *precision*, the fraction of its points within :data:`MODEL_WITHIN` of a reference point,
  >= :data:`MODEL_PRECISION`; *coverage*, the fraction of reference points within that distance
  of one of its points, >= :data:`MODEL_COVERAGE`.
* **navigation** (navigator) and **localization** (amcl, lama_local, driven on by the
  navigator): the robot ends at the goal (the navigator says REACHED and ground truth is
  within 15 cm and 0.2 rad of it) with no collision; for a localizer also its final position
  error against ground truth is <= :data:`LOCALIZATION_ERROR` (the target issue's bar). The
  reference must reach the goal too, or the cell is not judged.

A run whose supervisor gave up is incorrect, whatever it left.

Run folders in the runner's layout (``record.json``, ``final_map.npz``, ``final_model.npy``)
are judged from the command line too, for what cannot import this module (``make faults``'
six-target storm, rory_eval/faults/stack_storm.py, sits in a lower layer): one JSON line per
pair, ``{"correct": ..., "measures": ..., "reason": ...}``::

    python -m rory_eval.evaluation.judge CRASH_DIR REFERENCE_DIR [CRASH_DIR REFERENCE_DIR ...]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

from rory_eval.metrics import FREE_BELOW, OCCUPIED_AT, map_score, near, position_errors
from rory_eval.runs.runner import RunRecord
from rory_eval.targets import Kind
from sim.maps import OccupancyMap
from sim.worlds import get_world

MAP_COVERAGE = 0.90
MAP_AGREEMENT = 0.95
MAP_IOU = 0.80
MODEL_WITHIN = 0.05  # m
MODEL_PRECISION = 0.95
MODEL_COVERAGE = 0.90
LOCALIZATION_ERROR = 0.15  # m
GOAL_XY = 0.15  # m
GOAL_YAW = 0.2  # rad


@dataclass(frozen=True)
class Verdict:
    """The judgement of one crash run.

    ``correct`` is None when it cannot be judged (the run or its reference failed).
    """

    correct: bool | None
    measures: dict[str, float] = field(default_factory=dict)
    reason: str = ''  # why it is not correct, or why it was not judged


def judge(kind: Kind, crash: RunRecord, crash_dir: Path, reference: RunRecord,
          reference_dir: Path) -> Verdict:
    """The crash run against the reference run of the same target, world and repetition."""
    if reference.error:
        return Verdict(None, reason=f'reference run failed: {reference.error}')
    if crash.error:
        return Verdict(None, reason=f'run failed: {crash.error}')
    if crash.gave_up:
        return Verdict(False, reason='the supervisor gave up')
    if kind == Kind.MAP:
        return judge_map(crash_dir, reference_dir)
    if kind == Kind.MODEL:
        return judge_model(crash_dir, reference_dir)
    return judge_goal(kind, crash, reference)


def load_map(folder: Path) -> OccupancyMap | None:
    """The final map a run saved, or None."""
    path = folder / 'final_map.npz'
    if not path.exists():
        return None
    with np.load(path) as z:
        return OccupancyMap(z['data'], float(z['resolution']), float(z['origin_x']),
                            float(z['origin_y']))


def load_model(folder: Path) -> npt.NDArray[np.float64] | None:
    """The final 3D model (N x 3 points in map) a run saved, or None."""
    path = folder / 'final_model.npy'
    return np.load(path).astype(np.float64) if path.exists() else None


def judge_map(crash_dir: Path, reference_dir: Path) -> Verdict:
    """Coverage, agreement and occupied IoU of the crash run's map against the reference's."""
    reference, crash = load_map(reference_dir), load_map(crash_dir)
    if reference is None:
        return Verdict(None, reason='the reference published no map')
    if crash is None:
        return Verdict(False, reason='no map after the crash')
    # Unobserved and in-between cells of the reference are unknown: only what it observed
    # counts, so an identical map scores 1.0 on every measure.
    classes = np.full(reference.data.shape, -1, dtype=np.int8)
    classes[reference.data >= OCCUPIED_AT] = 100
    classes[(reference.data >= 0) & (reference.data < FREE_BELOW)] = 0
    truth = OccupancyMap(classes, reference.resolution, reference.origin_x, reference.origin_y)
    score = map_score(crash, truth, tolerance=1)
    measures = {'coverage': score.observed_fraction, 'agreement': score.agreement,
                'iou': score.iou_occupied}
    failed = [f'{name} {measures[name]:.3f} < {bar}' for name, bar in
              (('coverage', MAP_COVERAGE), ('agreement', MAP_AGREEMENT), ('iou', MAP_IOU))
              if measures[name] < bar]
    return Verdict(not failed, measures, '; '.join(failed))


def judge_model(crash_dir: Path, reference_dir: Path) -> Verdict:
    """Precision and coverage of the crash run's 3D model against the reference's."""
    reference, crash = load_model(reference_dir), load_model(crash_dir)
    if reference is None or len(reference) == 0:
        return Verdict(None, reason='the reference published no model')
    if crash is None or len(crash) == 0:
        return Verdict(False, reason='no model after the crash')
    measures = {'precision': float(np.mean(near(crash, reference, MODEL_WITHIN))),
                'coverage': float(np.mean(near(reference, crash, MODEL_WITHIN))),
                'points': float(len(crash)), 'reference_points': float(len(reference))}
    failed = [f'{name} {measures[name]:.3f} < {bar}' for name, bar in
              (('precision', MODEL_PRECISION), ('coverage', MODEL_COVERAGE))
              if measures[name] < bar]
    return Verdict(not failed, measures, '; '.join(failed))


def reached_goal(record: RunRecord) -> tuple[bool, float]:
    """Whether the run ended at the world's default goal (status and ground truth); the final
    distance to it."""
    spec = record.spec
    world = get_world(spec.world)
    goal = world.goals[world.default_goal]
    if not record.ground_truth:
        return False, math.inf
    _, x, y, yaw = record.ground_truth[-1]
    distance = math.hypot(x - goal.x, y - goal.y)
    heading = abs(math.remainder(yaw - goal.yaw, math.tau))
    at_goal = distance <= GOAL_XY and heading <= GOAL_YAW
    said = bool(record.statuses) and record.statuses[-1] == 'REACHED'
    return at_goal and said, distance


def judge_goal(kind: Kind, crash: RunRecord, reference: RunRecord) -> Verdict:
    """Goal reached with no collision (and, for a localizer, a small final error)."""
    ref_reached, _ = reached_goal(reference)
    if not ref_reached or reference.collisions:
        return Verdict(None, reason='the reference run did not reach the goal cleanly')
    reached, distance = reached_goal(crash)
    measures = {'reached': float(reached), 'goal_distance': distance,
                'collisions': float(crash.collisions)}
    failed = []
    if not reached:
        failed.append(f'goal not reached ({distance:.2f} m away, last status '
                      f'{crash.statuses[-1] if crash.statuses else "none"})')
    if crash.collisions:
        failed.append(f'{crash.collisions} collisions')
    if kind == Kind.LOCALIZATION:
        errors = position_errors(crash.poses, crash.ground_truth)
        final = float(errors[-1]) if errors.size else math.inf
        measures['final_error'] = final
        if final > LOCALIZATION_ERROR:
            failed.append(f'final position error {final:.2f} m > {LOCALIZATION_ERROR} m')
    return Verdict(not failed, measures, '; '.join(failed))


def criteria() -> str:
    """The thresholds as a Markdown list (results.md shows what 'correct' meant)."""
    return '\n'.join([
        f'- map: of the cells the no-crash map observed, >= {MAP_COVERAGE:.0%} observed too '
        f'(coverage); of the cells both observed, >= {MAP_AGREEMENT:.0%} the same free/occupied '
        f'class (agreement); occupied-cell IoU >= {MAP_IOU:.2f} (one-cell allowance).',
        f'- 3D model: >= {MODEL_PRECISION:.0%} of its points within {MODEL_WITHIN * 100:.0f} cm '
        f'of a no-crash model point (precision), >= {MODEL_COVERAGE:.0%} of the no-crash '
        f'points within {MODEL_WITHIN * 100:.0f} cm of one of its points (coverage).',
        f'- navigation: the navigator says REACHED and the robot ends within '
        f'{GOAL_XY * 100:.0f} cm and {GOAL_YAW} rad of the goal, with no collision.',
        f'- localization: the same, driven on the localizer\'s pose, and its final position '
        f'error <= {LOCALIZATION_ERROR * 100:.0f} cm (ground truth).',
        '- a run whose supervisor gave up is wrong; a run whose no-crash reference failed '
        'is not judged.',
    ])


def judge_folders(crash_dir: Path, reference_dir: Path) -> Verdict:
    """The crash run recorded in ``crash_dir`` against the reference in ``reference_dir``
    (each a runner's folder), judged by its target's kind as the evaluation judges it."""
    crash, reference = RunRecord.load(crash_dir), RunRecord.load(reference_dir)
    return judge(crash.spec.spec.kind, crash, crash_dir, reference, reference_dir)


def main(argv: Sequence[str] | None = None) -> int:
    """Judge each pair of folders; print one JSON verdict per pair; exit 2 on bad arguments."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.evaluation.judge',
                                     description='Judge crash runs against their references '
                                                 'as rory eval does: one JSON line per pair.')
    parser.add_argument('folders', type=Path, nargs='+', metavar='CRASH_DIR REFERENCE_DIR')
    args = parser.parse_args(argv)
    if len(args.folders) % 2:
        parser.error('give folders in pairs: CRASH_DIR REFERENCE_DIR')
    missing = [str(f) for f in args.folders if not (f / 'record.json').is_file()]
    if missing:
        parser.error(f'no record.json in {", ".join(missing)}')
    for crash_dir, reference_dir in zip(args.folders[::2], args.folders[1::2], strict=True):
        print(json.dumps(asdict(judge_folders(crash_dir, reference_dir))), flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
