"""A clean stop (SIGINT to ``rory supervise``) takes a last checkpoint of a node run as
``python node.py`` whose variables hold an Enum or a dataclass defined in that script, so in
``__main__``, and prints no error. Issue 35: the checkpoint taken at exit looked the class up
in the zygote's ``__main__`` (runpy had put it back), was skipped, and its error failed to
reach /rosout.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from corpus_progress import PROGRESS

from rory_eval.harness.scenario import Program, run
from rory_runtime.store import CheckpointStore

pytestmark = pytest.mark.ros

CORPUS = Path(__file__).parent / 'corpus'
COUNT = 20  # a short run: the numbers take 0.4 s at 50 Hz


def _shown(file: str, state: dict[str, Any]) -> list[str]:
    """Lines ``rory inspect`` prints of the node's variables in the state it published."""
    if file == 'enum_machine.py':
        return [f"  phase = '<Enum __main__.Phase.{state['phase'].upper()}>'",
                f"  counted = {state['counted']}"]
    return [f"  stats = {{'<dataclass>': '__main__.Stats', 'count': {state['count']}, "
            f"'mean': {state['mean']}, 'm2': {state['m2']}, 'extremes': "
            f"{{'<dataclass>': '__main__.Extremes', 'low': {state['extremes']['low']}, "
            f"'high': {state['extremes']['high']}}}}}"]


@pytest.mark.parametrize('file', ['enum_machine.py', 'dataclass_state.py'])
def test_a_clean_stop_checkpoints_classes_of_main(
    file: str, tmp_path: Path, ros_domain: int
) -> None:
    node = file.removesuffix('.py')
    program = Program(CORPUS, CORPUS / 'keyvars.yaml', file, '/state', node,
                      progress=PROGRESS[file])
    result = run('rory', (), tmp_path, domain_id=ros_domain, count=COUNT, interval=None,
                 pace=None, program=program)
    assert isinstance(result.state, dict), 'the node published no state'
    for wrong in ('[ERROR]', 'checkpoint skipped', 'no checkpoint at exit', 'rosout'):
        assert wrong not in result.log, result.log
    store = tmp_path / 'store-rory'
    latest = CheckpointStore(store, node).paths()[0]
    stopping = next(e['t'] for e in result.events
                    if e['kind'] == 'state' and e['new'] == 'STOPPING')
    assert CheckpointStore(store, node).load(latest).created_ns / 1e9 > stopping
    inspected = subprocess.run(
        [sys.executable, '-m', 'rory_runtime.cli', 'inspect', str(store), '--node', node,
         '--checkpoint', 'latest'],
        capture_output=True, text=True, timeout=60, check=True)
    assert inspected.stdout.startswith(f'{latest}\n'), inspected.stdout
    lines = inspected.stdout.splitlines()
    for line in _shown(file, result.state):
        assert line in lines, inspected.stdout
