"""Node code as people write it: each style is instrumented, run under the supervisor,
SIGKILLed mid-interval, and must end with exactly the state of a run without a crash.

The corpus (tests/integration/corpus) covers lambdas and closures as callbacks, a node written
as functions with module globals, dataclasses, an Enum state machine, numpy arrays, a list of
ROS messages, state inside helper objects (attribute paths), keyword-argument
create_subscription with an (msg, info) callback, and a node class deriving from another Node
subclass holding rclpy Time/Duration values. Per-node settings come from keyvars.yaml.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from rory_eval.harness.scenario import Kill, Program, run

pytestmark = pytest.mark.ros

CORPUS = Path(__file__).parent / 'corpus'
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
# killed 1.8 s into the numbers, it is between its first and second checkpoints.
KILL_AFTER = 1.8


@pytest.mark.parametrize('style', STYLES)
def test_style_recovers_exactly(style: str, tmp_path: Path, ros_domain: int) -> None:
    program = Program(CORPUS, CORPUS / 'keyvars.yaml', STYLES[style], '/state', style)
    common = {'domain_id': ros_domain, 'count': COUNT, 'interval': None, 'pace': None,
              'program': program}
    reference = run('rory', (), tmp_path / 'reference', **common)  # type: ignore[arg-type]
    crashed = run('rory', (Kill(after=KILL_AFTER),), tmp_path / 'crashed', **common)  # type: ignore[arg-type]
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
