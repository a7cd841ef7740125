"""``python -m rory_eval.evaluation.judge``: run folders judged from the command line exactly as
the evaluation judges them (what rory_eval/faults/stack_storm.py asks it). No process is
started."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rory_eval.evaluation import judge as judge_module
from rory_eval.runs.plan import BARE, RunSpec
from rory_eval.runs.runner import RunRecord
from sim.worlds import get_world


def _record(folder: Path, target: str, *, method: str = BARE, at_goal: bool = True,
            statuses: tuple[str, ...] = ('DRIVING', 'REACHED')) -> Path:
    world = get_world('real_room')
    goal = world.goals[world.default_goal]
    x = goal.x if at_goal else goal.x + 1.0
    spec = RunSpec(target=target, world='real_room', method=method, repetition=0,
                   crash_at=None if method == BARE else 12.0, duration=40.0)
    folder.mkdir(parents=True)
    RunRecord(run=spec.to_json(), statuses=list(statuses),
              ground_truth=[(0.0, world.start.x, world.start.y, world.start.yaw),
                            (40.0, x, goal.y, goal.yaw)],
              poses=[(40.0, x, goal.y)]).save(folder)
    return folder


def test_pairs_of_folders_are_judged_as_the_evaluation_judges_them(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    reference = _record(tmp_path / 'ref', 'navigator')
    good = _record(tmp_path / 'good', 'navigator', method='rory')
    astray = _record(tmp_path / 'astray', 'amcl', method='rory', at_goal=False)
    amcl_reference = _record(tmp_path / 'amcl_ref', 'amcl')
    assert judge_module.main([str(good), str(reference), str(astray), str(amcl_reference)]) == 0
    lines = capsys.readouterr().out.splitlines()
    verdicts = [json.loads(line) for line in lines]
    expected = [judge_module.judge_folders(good, reference),
                judge_module.judge_folders(astray, amcl_reference)]
    assert verdicts == [{'correct': v.correct, 'measures': v.measures, 'reason': v.reason}
                        for v in expected]
    assert verdicts[0]['correct'] is True
    assert verdicts[1]['correct'] is False and 'goal not reached' in verdicts[1]['reason']
    assert 'final_error' in verdicts[1]['measures']  # judged as a localizer


def test_a_map_folder_is_judged_on_its_map(tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    grid = np.zeros((40, 40), dtype=np.int8)
    grid[0, :] = 100
    folders = []
    for name, data in (('crash', np.full_like(grid, -1)), ('ref', grid)):
        folder = _record(tmp_path / name, 'grid_slam')
        np.savez_compressed(folder / 'final_map.npz', data=data, resolution=0.05, origin_x=0.0,
                            origin_y=0.0)
        folders.append(str(folder))
    assert judge_module.main(folders) == 0
    verdict = json.loads(capsys.readouterr().out)
    assert verdict['correct'] is False and verdict['measures']['coverage'] == 0.0


@pytest.mark.parametrize('make', ['odd', 'missing'])
def test_folders_not_in_pairs_or_without_a_record_exit_2(
        tmp_path: Path, make: str, capsys: pytest.CaptureFixture[str]) -> None:
    one = _record(tmp_path / 'one', 'navigator')
    folders = [str(one)] if make == 'odd' else [str(one), str(tmp_path / 'nothing')]
    with pytest.raises(SystemExit) as exit_:
        judge_module.main(folders)
    assert exit_.value.code == 2
    assert ('in pairs' if make == 'odd' else 'no record.json') in capsys.readouterr().err
