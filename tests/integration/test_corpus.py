"""Node code as people write it: each style is instrumented, run under the supervisor,
SIGKILLed mid-interval, and must end with exactly the state of a run without a crash.

The corpus (tests/integration/corpus) covers lambdas and closures as callbacks, a node written
as functions with module globals, dataclasses, an Enum state machine, numpy arrays, a list of
ROS messages, state inside helper objects (attribute paths), keyword-argument
create_subscription with an (msg, info) callback, and a node class deriving from another Node
subclass holding rclpy Time/Duration values. Per-node settings come from keyvars.yaml.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest
from corpus_progress import PROGRESS

from rory_eval.harness.scenario import Kill, Program, run

pytestmark = pytest.mark.ros

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


@pytest.mark.parametrize('style', STYLES)
def test_style_recovers_exactly(
    style: str, tmp_path: Path, ros_domain: int, more_ros_domains: Callable[[], int]
) -> None:
    file = STYLES[style]
    program = Program(CORPUS, CORPUS / 'keyvars.yaml', file, '/state', style,
                      progress=PROGRESS[file])
    common: dict[str, Any] = {'count': COUNT, 'interval': None, 'pace': None,
                              'program': program}
    # The run without a crash and the crashed run are independent (each its own domain and
    # processes): side by side.
    with ThreadPoolExecutor(2) as pool:
        reference_run = pool.submit(run, 'rory', (), tmp_path / 'reference',
                                    domain_id=more_ros_domains(), **common)
        crashed_run = pool.submit(run, 'rory', (Kill(after_applied=KILL_AFTER_APPLIED),),
                                  tmp_path / 'crashed', domain_id=ros_domain, **common)
        reference, crashed = reference_run.result(), crashed_run.result()
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
