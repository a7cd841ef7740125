"""Tests of the supervisor configuration file."""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest

from rory_runtime.errors import ConfigError
from rory_runtime.protocol import Method, ReplayPace
from rory_runtime.supervisor.config import (
    Backoff,
    NodeConfig,
    ReleaseGate,
    SafeAction,
    SupervisorConfig,
    load_config,
)

FULL = """\
nodes:
  - name: integrator
    command: [python, out/integrator.py, --rate, '5']
    method: checkpoint
    checkpoint_interval: 0.5
    replay: fast
    restart_on_clean_exit: true
    warm_standby: true
    env: {FOO: bar, COUNT: 3}
    backoff:
      initial: 0.1
      step: 0.2
      maximum: 4
      stable_after: 3
      max_restarts: 7
  - name: counter_2
    command: ./run.sh --x 1
    method: replay
safe_state:
  - topic: /e_stop
    type: std_msgs/msg/Bool
    hold: {data: true}
    release: {data: false}
    rate: 10
  - topic: /cmd_vel
    type: geometry_msgs/msg/Twist
    hold: {linear: {x: 0.0}}
store: state/rory
dds: inherit
"""

MINIMAL = """\
nodes:
  - name: a
    command: [python3, a.py]
"""


def write(tmp_path: Path, text: str, name: str = 'rory.yaml') -> Path:
    folder = tmp_path / 'conf'
    folder.mkdir(exist_ok=True)
    path = folder / name
    path.write_text(textwrap.dedent(text), encoding='utf-8')
    return path


def refusal(path: Path) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        load_config(path)
    err = info.value
    assert err.path == path.resolve()
    assert str(path.resolve()) in str(err)
    assert err.field in str(err)
    return err


def test_full_example_sets_every_field(tmp_path: Path) -> None:
    path = write(tmp_path, FULL)
    config = load_config(path)
    folder = path.parent.resolve()
    assert config == SupervisorConfig(
        path=path.resolve(),
        folder=folder,
        nodes=(
            NodeConfig(
                name='integrator',
                command=(sys.executable, 'out/integrator.py', '--rate', '5'),
                method=Method.CHECKPOINT,
                checkpoint_interval=0.5,
                replay=ReplayPace.FAST,
                restart_on_clean_exit=True,
                warm_standby=True,
                env={'FOO': 'bar', 'COUNT': '3'},
                backoff=Backoff(
                    initial=0.1, step=0.2, maximum=4.0, stable_after=3.0, max_restarts=7
                ),
            ),
            NodeConfig(
                name='counter_2',
                command=('./run.sh', '--x', '1'),
                method=Method.REPLAY,
            ),
        ),
        safe_state=(
            SafeAction(
                topic='/e_stop',
                msgtype='std_msgs/msg/Bool',
                hold={'data': True},
                release={'data': False},
                rate=10.0,
            ),
            SafeAction(
                topic='/cmd_vel',
                msgtype='geometry_msgs/msg/Twist',
                hold={'linear': {'x': 0.0}},
                release=None,
                rate=None,
            ),
        ),
        store=folder / 'state' / 'rory',
        dds='inherit',
    )
    assert isinstance(config.nodes[0].method, Method)
    assert isinstance(config.nodes[0].replay, ReplayPace)
    assert isinstance(config.nodes[0].backoff.maximum, float)


def test_defaults(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL)
    config = load_config(path)
    (node,) = config.nodes
    assert node.name == 'a'
    assert node.method is Method.RORY
    # unset: the node's own keyvars.yaml setting applies, else the runtime's default (2 s, fast)
    assert node.checkpoint_interval is None
    assert node.replay is None
    assert node.restart_on_clean_exit is False
    assert node.warm_standby is True  # rory's default; the other methods start cold
    assert dict(node.env) == {}
    assert node.backoff == Backoff()
    assert Backoff() == Backoff(
        initial=0.0, step=0.5, maximum=8.0, stable_after=10.0, max_restarts=5
    )
    assert config.safe_state == ()
    assert config.store == path.parent.resolve() / '.rory'
    assert config.dds == 'fast_rediscovery'


def test_empty_optional_sections_are_defaults(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL + '    env:\n    backoff:\nsafe_state:\n')
    config = load_config(path)
    assert config.safe_state == ()
    assert dict(config.nodes[0].env) == {}
    assert config.nodes[0].backoff == Backoff()


@pytest.mark.parametrize('python', ['python', 'python3', 'python3.11'])
def test_python_is_resolved_to_the_running_interpreter(tmp_path: Path, python: str) -> None:
    path = write(tmp_path, f'nodes: [{{name: a, command: [{python}, -m, x]}}]\n')
    assert load_config(path).nodes[0].command == (sys.executable, '-m', 'x')


def test_python_in_a_command_string_is_resolved(tmp_path: Path) -> None:
    path = write(tmp_path, 'nodes: [{name: a, command: python  node.py  --fast}]\n')
    assert load_config(path).nodes[0].command == (sys.executable, 'node.py', '--fast')


@pytest.mark.parametrize('program', ['/usr/bin/python3', 'python2', './python', 'ros2'])
def test_other_programs_are_left_as_written(tmp_path: Path, program: str) -> None:
    path = write(tmp_path, f'nodes: [{{name: a, command: [{program}, python]}}]\n')
    assert load_config(path).nodes[0].command == (program, 'python')


def test_store_is_relative_to_the_config_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = write(tmp_path, MINIMAL + 'store: ../data/./store\n')
    elsewhere = tmp_path / 'elsewhere'
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    config = load_config(Path('..') / 'conf' / 'rory.yaml')
    assert config.path == path.resolve()
    assert config.folder == path.parent.resolve()
    assert config.store == (tmp_path / 'data' / 'store').resolve()


def test_absolute_store_is_kept(tmp_path: Path) -> None:
    store = tmp_path / 'abs' / 'store'
    path = write(tmp_path, MINIMAL + f'store: {store}\n')
    assert load_config(path).store == store.resolve()


def test_config_path_may_be_a_string(tmp_path: Path) -> None:
    path = write(tmp_path, MINIMAL)
    assert load_config(str(path)).path == path.resolve()


# --------------------------------------------------------------------------- errors

NODE = '  - name: a\n    command: [x]\n'

ERRORS = [
    # top level
    ('- a\n- b\n', '(top level)'),
    ('just text\n', '(top level)'),
    ('', '(top level)'),
    (MINIMAL + 'nodez: []\n', 'nodez'),
    ('store: x\n', 'nodes'),
    ('nodes: []\n', 'nodes'),
    ('nodes: {a: 1}\n', 'nodes'),
    ('nodes: a\n', 'nodes'),
    (MINIMAL + 'store: ""\n', 'store'),
    (MINIMAL + 'store: 5\n', 'store'),
    (MINIMAL + 'dds: fast\n', 'dds'),
    (MINIMAL + 'dds: 5\n', 'dds'),
    (MINIMAL + 'safe_state: {topic: /x}\n', 'safe_state'),
    # nodes
    ('nodes: [5]\n', 'nodes[0]'),
    ('nodes:\n' + NODE + '  - 5\n', 'nodes[1]'),
    ('nodes:\n' + NODE + '    respawn: true\n', 'nodes[0].respawn'),
    ('nodes:\n  - command: [x]\n', 'nodes[0].name'),
    ('nodes:\n  - name: 1abc\n    command: [x]\n', 'nodes[0].name'),
    ('nodes:\n  - name: a-b\n    command: [x]\n', 'nodes[0].name'),
    ('nodes:\n  - name: _a\n    command: [x]\n', 'nodes[0].name'),
    ('nodes:\n  - name: 5\n    command: [x]\n', 'nodes[0].name'),
    ('nodes:\n  - name: ""\n    command: [x]\n', 'nodes[0].name'),
    ('nodes:\n' + NODE + NODE, 'nodes[1].name'),
    ('nodes:\n' + NODE + '  - name: b\n    command: [x]\n' + NODE, 'nodes[2].name'),
    ('nodes:\n  - name: a\n', 'nodes[0].command'),
    ('nodes:\n' + NODE + '    hang_timeout: 0\n', 'nodes[0].hang_timeout'),
    ('nodes:\n' + NODE + '    hang_timeout: -1\n', 'nodes[0].hang_timeout'),
    ('nodes:\n' + NODE + '    hang_timeout: soon\n', 'nodes[0].hang_timeout'),
    ('nodes:\n' + NODE + '    start_timeout: .nan\n', 'nodes[0].start_timeout'),
    ('nodes:\n' + NODE + '    hello_timeout: 0\n', 'nodes[0].hello_timeout'),
    ('nodes:\n' + NODE + '    hello_timeout: -3\n', 'nodes[0].hello_timeout'),
    ('nodes:\n' + NODE + '    hello_timeout: later\n', 'nodes[0].hello_timeout'),
    ('nodes:\n' + NODE + '    hello_timeout: null\n', 'nodes[0].hello_timeout'),
    ('nodes:\n' + NODE + '    hello_timeout: .inf\n', 'nodes[0].hello_timeout'),
    ('nodes:\n  - name: a\n    command: []\n', 'nodes[0].command'),
    ('nodes:\n  - name: a\n    command: ""\n', 'nodes[0].command'),
    ('nodes:\n  - name: a\n    command: [x, 1]\n', 'nodes[0].command'),
    ('nodes:\n  - name: a\n    command: 5\n', 'nodes[0].command'),
    ('nodes:\n  - name: a\n    command: {x: 1}\n', 'nodes[0].command'),
    ('nodes:\n' + NODE + '    method: magic\n', 'nodes[0].method'),
    ('nodes:\n' + NODE + '  - name: b\n    command: [x]\n    method: RORY\n', 'nodes[1].method'),
    ('nodes:\n' + NODE + '    replay: slow\n', 'nodes[0].replay'),
    ('nodes:\n' + NODE + '    checkpoint_interval: 0\n', 'nodes[0].checkpoint_interval'),
    ('nodes:\n' + NODE + '    checkpoint_interval: -1\n', 'nodes[0].checkpoint_interval'),
    ('nodes:\n' + NODE + '    checkpoint_interval: fast\n', 'nodes[0].checkpoint_interval'),
    ('nodes:\n' + NODE + '    checkpoint_interval: true\n', 'nodes[0].checkpoint_interval'),
    ('nodes:\n' + NODE + '    checkpoint_interval: .inf\n', 'nodes[0].checkpoint_interval'),
    ('nodes:\n' + NODE + '    checkpoint_interval: .nan\n', 'nodes[0].checkpoint_interval'),
    ('nodes:\n' + NODE + '    restart_on_clean_exit: 1\n', 'nodes[0].restart_on_clean_exit'),
    ('nodes:\n' + NODE + '    warm_standby: yes please\n', 'nodes[0].warm_standby'),
    ('nodes:\n' + NODE + '    restart_on_clean_exit: maybe\n', 'nodes[0].restart_on_clean_exit'),
    ('nodes:\n' + NODE + '    env: [A, B]\n', 'nodes[0].env'),
    ('nodes:\n' + NODE + '    env: {1: a}\n', 'nodes[0].env'),
    ('nodes:\n' + NODE + '    backoff: 5\n', 'nodes[0].backoff'),
    ('nodes:\n' + NODE + '    backoff: {jitter: 1}\n', 'nodes[0].backoff.jitter'),
    ('nodes:\n' + NODE + '    backoff: {max_restarts: 0}\n', 'nodes[0].backoff.max_restarts'),
    ('nodes:\n' + NODE + '    backoff: {max_restarts: -1}\n', 'nodes[0].backoff.max_restarts'),
    ('nodes:\n' + NODE + '    backoff: {max_restarts: 1.5}\n', 'nodes[0].backoff.max_restarts'),
    ('nodes:\n' + NODE + '    backoff: {max_restarts: true}\n', 'nodes[0].backoff.max_restarts'),
    ('nodes:\n' + NODE + '    backoff: {max_restarts: "3"}\n', 'nodes[0].backoff.max_restarts'),
    ('nodes:\n' + NODE + '    backoff: {initial: -1}\n', 'nodes[0].backoff.initial'),
    ('nodes:\n' + NODE + '    backoff: {step: x}\n', 'nodes[0].backoff.step'),
    ('nodes:\n' + NODE + '    backoff: {maximum: -0.5}\n', 'nodes[0].backoff.maximum'),
    ('nodes:\n' + NODE + '    backoff: {stable_after: 0}\n', 'nodes[0].backoff.stable_after'),
    # safe_state
    (MINIMAL + 'safe_state: [5]\n', 'safe_state[0]'),
    (MINIMAL + 'safe_state:\n  - {type: std_msgs/msg/Bool, hold: {}}\n', 'safe_state[0].topic'),
    (
        MINIMAL + 'safe_state:\n  - {topic: e_stop/, type: std_msgs/msg/Bool, hold: {}}\n',
        'safe_state[0].topic',
    ),
    (
        MINIMAL + 'safe_state:\n  - {topic: ~/e_stop, type: std_msgs/msg/Bool, hold: {}}\n',
        'safe_state[0].topic',
    ),
    (
        MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/msg/Bool, hold: {}, nodes: b}\n',
        'safe_state[0].nodes',
    ),
    (
        MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/msg/Bool, hold: {}, nodes: []}\n',
        'safe_state[0].nodes',
    ),
    (
        MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/msg/Bool, hold: {},'
        ' nodes: [a, b]}\n',
        'safe_state[0].nodes[1]',
    ),
    (
        MINIMAL + 'safe_state:\n  - {topic: 5, type: std_msgs/msg/Bool, hold: {}}\n',
        'safe_state[0].topic',
    ),
    (MINIMAL + 'safe_state:\n  - {topic: /e, hold: {}}\n', 'safe_state[0].type'),
    (
        MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/Bool, hold: {}}\n',
        'safe_state[0].type',
    ),
    (
        MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/srv/Empty, hold: {}}\n',
        'safe_state[0].type',
    ),
    (
        MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/msg/bool, hold: {}}\n',
        'safe_state[0].type',
    ),
    (MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/msg/Bool}\n', 'safe_state[0].hold'),
    (
        MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/msg/Bool, hold: [true]}\n',
        'safe_state[0].hold',
    ),
    (
        MINIMAL
        + 'safe_state:\n  - {topic: /e, type: std_msgs/msg/Bool, hold: {}, release: true}\n',
        'safe_state[0].release',
    ),
    (
        MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/msg/Bool, hold: {}, rate: 0}\n',
        'safe_state[0].rate',
    ),
    (
        MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/msg/Bool, hold: {}, rate: -5}\n',
        'safe_state[0].rate',
    ),
    (
        MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/msg/Bool, hold: {}, rate: x}\n',
        'safe_state[0].rate',
    ),
    (
        MINIMAL + 'safe_state:\n  - {topic: /e, type: std_msgs/msg/Bool, hold: {}, qos: 1}\n',
        'safe_state[0].qos',
    ),
    (
        MINIMAL
        + 'safe_state:\n'
        + '  - {topic: /e, type: std_msgs/msg/Bool, hold: {}}\n'
        + '  - {topic: /f, type: x, hold: {}}\n',
        'safe_state[1].type',
    ),
]


@pytest.mark.parametrize(
    ('text', 'field'), ERRORS, ids=[f'{f}-{i}' for i, (_, f) in enumerate(ERRORS)]
)
def test_invalid_field_raises_config_error_naming_file_and_field(
    tmp_path: Path, text: str, field: str
) -> None:
    err = refusal(write(tmp_path, text))
    assert err.field == field
    assert err.reason


def test_unknown_field_lists_the_allowed_ones(tmp_path: Path) -> None:
    err = refusal(write(tmp_path, 'nodes:\n' + NODE + '    respawn: true\n'))
    assert 'allowed' in err.reason
    assert 'checkpoint_interval' in err.reason


def test_duplicate_name_reason_names_the_node(tmp_path: Path) -> None:
    err = refusal(write(tmp_path, 'nodes:\n' + NODE + NODE))
    assert "'a'" in err.reason


def test_missing_file_raises_config_error(tmp_path: Path) -> None:
    path = tmp_path / 'nope.yaml'
    err = refusal(path)
    assert err.field == '(file)'
    assert 'cannot read' in err.reason


def test_directory_instead_of_file_raises_config_error(tmp_path: Path) -> None:
    path = tmp_path / 'dir.yaml'
    path.mkdir()
    err = refusal(path)
    assert err.field == '(file)'


def test_invalid_yaml_raises_config_error(tmp_path: Path) -> None:
    path = write(tmp_path, 'nodes: [a, b\n  x: : y\n')
    with pytest.raises(ConfigError) as info:
        load_config(path)
    err = info.value
    assert err.field == '(file)'
    assert 'not valid YAML' in err.reason
    assert str(err).startswith(f'{path.resolve()}:2:')  # where it stops being YAML


def test_file_that_is_not_utf8_raises_config_error(tmp_path: Path) -> None:
    path = tmp_path / 'latin1.yaml'
    path.write_bytes(b'nodes:\n  - name: n\xe9\n    command: [x]\n')
    err = refusal(path)
    assert err.field == '(file)'


def test_method_of_unhashable_type_raises_config_error(tmp_path: Path) -> None:
    err = refusal(write(tmp_path, 'nodes:\n' + NODE + '    method: [rory]\n'))
    assert err.field == 'nodes[0].method'


def test_replay_of_unhashable_type_raises_config_error(tmp_path: Path) -> None:
    err = refusal(write(tmp_path, 'nodes:\n' + NODE + '    replay: {fast: 1}\n'))
    assert err.field == 'nodes[0].replay'


def test_unknown_keys_of_mixed_types_raise_config_error(tmp_path: Path) -> None:
    err = refusal(write(tmp_path, MINIMAL + '1: x\nfoo: y\n'))
    assert err.field in {'1', 'foo'}


def test_node_name_with_trailing_newline_is_refused(tmp_path: Path) -> None:
    """The name becomes a directory and topic name; '$' also matches before a final newline."""
    err = refusal(write(tmp_path, 'nodes:\n  - name: "a\\n"\n    command: [x]\n'))
    assert err.field == 'nodes[0].name'


def test_safe_state_type_with_trailing_newline_is_refused(tmp_path: Path) -> None:
    text = MINIMAL + 'safe_state:\n  - {topic: /e, type: "std_msgs/msg/Bool\\n", hold: {}}\n'
    err = refusal(write(tmp_path, text))
    assert err.field == 'safe_state[0].type'


def test_hang_start_and_hello_timeouts(tmp_path: Path) -> None:
    default = load_config(write(tmp_path, MINIMAL)).nodes[0]
    assert (default.hang_timeout, default.start_timeout, default.hello_timeout) == (
        10.0, 60.0, 10.0)
    text = ('nodes:\n' + NODE + '    hang_timeout: 2.5\n    start_timeout: null\n'
            '    hello_timeout: 1.5\n')
    node = load_config(write(tmp_path, text, 'b.yaml')).nodes[0]
    assert (node.hang_timeout, node.start_timeout, node.hello_timeout) == (2.5, None, 1.5)


@pytest.mark.parametrize('method', ['restart', 'checkpoint', 'replay'])
def test_only_rory_has_a_warm_standby_by_default(tmp_path: Path, method: str) -> None:
    # restart stands for ROS's respawn and the others for the paper's ablations: cold starts.
    text = f'nodes:\n  - name: a\n    command: [python, a.py]\n    method: {method}\n'
    path = write(tmp_path, text)
    assert load_config(path).nodes[0].warm_standby is False


def test_a_safe_action_may_be_relative_and_scoped_to_some_nodes(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, MINIMAL + textwrap.dedent("""\
        safe_state:
          - {topic: e_stop, type: std_msgs/msg/Bool, hold: {data: true}, nodes: [a]}
          - {topic: /all/stop, type: std_msgs/msg/Bool, hold: {data: true}}
        """)))
    scoped, everyone = config.safe_state
    assert scoped.topic == 'e_stop' and scoped.nodes == ('a',)
    assert everyone.topic == '/all/stop' and everyone.nodes is None


def test_keep_runs_defaults_to_three_and_must_be_a_positive_integer(tmp_path: Path) -> None:
    node = 'nodes: [{name: a, command: [x]}]\n'
    assert load_config(write(tmp_path, node)).keep_runs == 3
    assert load_config(write(tmp_path, node + 'keep_runs: 1\n')).keep_runs == 1
    for bad in ('0', 'true', '2.5', 'many'):
        err = refusal(write(tmp_path, node + f'keep_runs: {bad}\n'))
        assert err.field == 'keep_runs' and 'positive integer' in err.reason


def test_output_is_prefixed_with_several_nodes_unless_told(tmp_path: Path) -> None:
    one = 'nodes: [{name: a, command: [x]}]\n'
    two = 'nodes: [{name: a, command: [x]}, {name: b, command: [y]}]\n'
    assert not load_config(write(tmp_path, one)).prefixes_output
    assert load_config(write(tmp_path, two)).prefixes_output
    assert load_config(write(tmp_path, one + 'prefix_output: true\n')).prefixes_output
    assert not load_config(write(tmp_path, two + 'prefix_output: false\n')).prefixes_output
    err = refusal(write(tmp_path, one + 'prefix_output: sometimes\n'))
    assert err.field == 'prefix_output' and 'true or false' in err.reason


def test_a_release_gate_takes_a_timeout_and_what_to_do_then(tmp_path: Path) -> None:
    def gate(text: str) -> object:
        node = f'nodes: [{{name: a, command: [x], release_gate: {text}}}]\n'
        return load_config(write(tmp_path, node)).nodes[0].release_gate

    assert load_config(write(tmp_path, 'nodes: [{name: a, command: [x]}]\n')).nodes[0] \
        .release_gate is None
    assert gate('false') is None
    assert gate('true') == ReleaseGate(timeout=None, on_timeout='give_up')
    assert gate('{timeout: 30}') == ReleaseGate(timeout=30.0, on_timeout='give_up')
    assert gate('{timeout: 5, on_timeout: release}') == ReleaseGate(5.0, 'release')
    for bad, field, reason in (
        ('{timeout: 5, on_timeout: later}', 'on_timeout', 'give_up or release'),
        ('{on_timeout: release}', 'on_timeout', 'needs a timeout'),
        ('{timeout: -1}', 'timeout', '> 0'),
        ('{wait: 5}', 'wait', 'unknown'),
    ):
        node = f'nodes: [{{name: a, command: [x], release_gate: {bad}}}]\n'
        err = refusal(write(tmp_path, node))
        assert err.field == f'nodes[0].release_gate.{field}'
        assert reason in str(err), err


def test_the_standby_pool_holds_one_per_node_that_wants_one_up_to_three(tmp_path: Path) -> None:
    def nodes(n: int, extra: str = '') -> str:
        return 'nodes: [' + ', '.join(f'{{name: n{i}, command: [x]{extra}}}'
                                      for i in range(n)) + ']\n'
    assert load_config(write(tmp_path, nodes(1))).standby_pool_size == 1
    assert load_config(write(tmp_path, nodes(2))).standby_pool_size == 2
    assert load_config(write(tmp_path, nodes(6))).standby_pool_size == 3
    # nodes without a standby do not count (restart, or warm_standby: false)
    assert load_config(write(tmp_path, nodes(4, ', method: restart'))).standby_pool_size == 1
    assert load_config(write(tmp_path, nodes(6) + 'standbys: 5\n')).standby_pool_size == 5
    for bad in ('0', 'true', '1.5', 'all'):
        err = refusal(write(tmp_path, nodes(1) + f'standbys: {bad}\n'))
        assert err.field == 'standbys' and 'positive integer' in err.reason


def test_spare_forks_are_on_unless_turned_off(tmp_path: Path) -> None:
    two = 'nodes: [{name: a, command: [x]}, {name: b, command: [y]}]\n'
    assert load_config(write(tmp_path, two)).spare_forks
    assert not load_config(write(tmp_path, two + 'spare_forks: false\n')).spare_forks
    err = refusal(write(tmp_path, two + 'spare_forks: 2\n'))
    assert err.field == 'spare_forks' and 'true or false' in err.reason
