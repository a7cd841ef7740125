"""Node code as people write it: each style is instrumented, run under the supervisor,
SIGKILLed mid-interval, and must end with exactly the state of a run without a crash.

The corpus (tests/integration/corpus) covers lambdas and closures as callbacks, a node written
as functions with module globals, dataclasses, an Enum state machine, numpy arrays, a list of
ROS messages, state inside helper objects (attribute paths), keyword-argument
create_subscription with an (msg, info) callback, and a node class deriving from another Node
subclass holding rclpy Time/Duration values. Per-node settings come from keyvars.yaml. Each
style's two runs, and the styles, are independent runs: four at a time (side_by_side.py).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from corpus_progress import PROGRESS
from side_by_side import SideBySide, side_by_side

from rory_eval.harness.scenario import Kill, Program, ScenarioResult, run

# The runs are shared (side_by_side.py): the module's tests on one xdist worker.
pytestmark = [pytest.mark.ros, pytest.mark.xdist_group('corpus')]

CORPUS = Path(__file__).parent / 'corpus'


# Each style's file (corpus_progress.PROGRESS: how many numbers its published state shows
# applied; the kill waits for that many, all of them applied ends the run).
STYLES = {
    'closures': 'closures.py',
    'functional': 'functional.py',
    'dataclasses': 'dataclass_state.py',
    'enum_machine': 'enum_machine.py',
    'numpy': 'numpy_state.py',
    'message_list': 'message_list.py',
    'helper_objects': 'helper_objects.py',
    'keyword_subscription': 'kwargs_sub.py',
    'derived_with_time': 'derived.py',
}
COUNT = 150  # 3 s at 50 Hz
# The node checkpoints every 2 s from its start, about 1 s before the first number arrives:
# killed after 90 numbers (1.8 s into them), it is between its first and second checkpoints.
# Timed by the numbers its own state shows applied, not by when this process first heard it:
# a kill 1.8 s after an observer that heard the node late landed after the last number.
KILL_AFTER_APPLIED = 90


# Each run takes about a third of a core (supervisor, node, standby, publisher): four at a
# time, two styles' pairs, leave the other xdist worker its share of the two cores.
AT_ONCE = 4


def _program(style: str) -> Program:
    file = STYLES[style]
    return Program(CORPUS, CORPUS / 'keyvars.yaml', file, '/state', style,
                   progress=PROGRESS[file])


@pytest.fixture(scope='module')
def style_runs(
    module_ros_domains: Callable[[], int], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[SideBySide[ScenarioResult]]:
    """Each style's run without a crash and its crashed run: independent runs (each its own
    domain, folder and processes), four at a time, a style's two together."""
    def style_run(style: str, kills: tuple[Kill, ...]) -> Callable[[int, Path], ScenarioResult]:
        common: dict[str, Any] = {'count': COUNT, 'interval': None, 'pace': None,
                                  'program': _program(style)}
        return lambda domain, folder: run('rory', kills, folder, domain_id=domain, **common)
    runs = {}
    for style in STYLES:
        runs[f'{style}-reference'] = style_run(style, ())
        runs[f'{style}-crashed'] = style_run(style, (Kill(after_applied=KILL_AFTER_APPLIED),))
    with side_by_side(runs, module_ros_domains, tmp_path_factory.mktemp('corpus'),
                      AT_ONCE) as together:
        yield together


@pytest.mark.parametrize('style', STYLES)
def test_style_recovers_exactly(style: str, style_runs: SideBySide[ScenarioResult]) -> None:
    reference, crashed = style_runs[f'{style}-reference'], style_runs[f'{style}-crashed']
    assert reference.state, 'the node published no state'
    assert len(crashed.recoveries) == 1
    assert crashed.recoveries[0]['replayed'] > 0
    assert crashed.state == reference.state
    hello = next(e for e in crashed.events if e['kind'] == 'hello')
    if style == 'functional':  # checkpoint_interval: 1.0 in keyvars.yaml
        assert hello['interval'] == 1.0
    if style == 'closures':  # replay: paced in keyvars.yaml
        assert crashed.recoveries[0]['replay'] == 'paced'
    else:  # the default, and enum_machine's replay: fast
        assert crashed.recoveries[0]['replay'] == 'fast'
