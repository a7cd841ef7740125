"""Input errors: exact ``file:line:col: message`` on stderr, exit code 2, and no OUT.

These run ``main`` in-process from a temporary directory, with relative paths, so that
messages are the same on every machine.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rory_instrument.cli import base_candidates, main
from rory_instrument.config import FreshnessRule, Mark, load_keyvars, parse_keyvars
from rory_instrument.errors import ConfigError

INTEGRATOR = '''\
import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64


class Integrator(Node):
    """Sums numbers."""

    def __init__(self):
        super().__init__('integrator')
        self.total = 0  # running sum
        self.count = 0
        self.history = []
'''

PLAIN = '''\
class Integrator:
    def __init__(self):
        self.total = 0
'''

GOOD = '''\
nodes:
  - file: integrator.py
    class: Integrator
    vars: [total, count, history]
'''


@pytest.fixture
def work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A directory with src/integrator.py and src/plain.py, made the current directory."""
    src = tmp_path / 'src'
    src.mkdir()
    (src / 'integrator.py').write_text(INTEGRATOR)
    (src / 'plain.py').write_text(PLAIN)
    (src / 'broken.py').write_text('import os\n\nclass Broken(Node)\n    pass\n')
    (tmp_path / 'outside.py').write_text(INTEGRATOR)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def fails_with(work: Path, capsys: pytest.CaptureFixture[str], keyvars: str | None,
               message: str) -> None:
    """Asserts that instrumenting src with ``keyvars`` prints exactly ``message``."""
    if keyvars is not None:
        (work / 'keyvars.yaml').write_text(keyvars)
    code, out, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'out')
    assert (code, out, err) == (2, '', message + '\n')
    assert not (work / 'out').exists()
    # Nothing else was left next to OUT either (no staging directory).
    assert sorted(p.name for p in work.iterdir()) == sorted(
        ['src', 'outside.py'] + (['keyvars.yaml'] if keyvars is not None else [])
    )


NODE = 'nodes:\n  - file: integrator.py\n    class: Integrator\n'

CONFIG_ERRORS = [
    ('not_yaml', 'nodes: [\n',
     "keyvars.yaml:2:1: not valid YAML: while parsing a flow node expected the node "
     "content, but found '<stream end>'"),
    ('empty', '', "keyvars.yaml:1:1: expected a mapping with key 'nodes', got an empty file"),
    ('top_not_mapping', '- integrator.py\n',
     'keyvars.yaml:1:1: top level: expected a mapping with keys nodes'),
    ('missing_nodes', '{}\n', "keyvars.yaml:1:1: top level: missing required key 'nodes'"),
    ('unknown_top_key', 'node: []\n',
     "keyvars.yaml:1:1: top level: unknown key 'node' (expected: nodes)"),
    ('nodes_not_list', 'nodes: integrator.py\n',
     'keyvars.yaml:1:8: nodes: expected a non-empty list of node entries'),
    ('nodes_empty', 'nodes: []\n',
     'keyvars.yaml:1:8: nodes: expected a non-empty list of node entries'),
    ('node_not_mapping', 'nodes:\n  - integrator.py\n',
     'keyvars.yaml:2:5: nodes[0]: expected a mapping with keys file, class, vars, '
     'module_vars, checkpoint_interval, replay'),
    ('missing_file', 'nodes:\n  - class: Integrator\n    vars: [total]\n',
     "keyvars.yaml:2:5: nodes[0]: missing required key 'file'"),
    ('missing_class', 'nodes:\n  - file: integrator.py\n    vars: [total]\n',
     "keyvars.yaml:2:5: nodes[0]: missing required key 'class'"),
    ('missing_vars', NODE, "keyvars.yaml:2:5: nodes[0]: missing required key 'vars'"),
    ('vars_empty', NODE + '    vars: []\n',
     'keyvars.yaml:4:11: nodes[0].vars: expected a non-empty list of attribute names'),
    ('vars_not_list', NODE + '    vars: total\n',
     'keyvars.yaml:4:11: nodes[0].vars: expected a non-empty list of attribute names'),
    ('var_not_identifier', NODE + '    vars: [total, 2nd]\n',
     "keyvars.yaml:4:19: nodes[0].vars[1]: '2nd' is not a Python identifier"),
    ('var_keyword', NODE + '    vars:\n      - total\n      - class\n',
     "keyvars.yaml:6:9: nodes[0].vars[1]: 'class' is not a Python identifier"),
    ('var_not_scalar', NODE + '    vars: [total, [count]]\n',
     'keyvars.yaml:4:19: nodes[0].vars[1]: expected an attribute name or a mapping with keys '
     'name, max_age, on_stale'),
    ('var_duplicate', NODE + '    vars: [total, count, total]\n',
     "keyvars.yaml:4:26: nodes[0].vars[2]: duplicate var 'total'"),
    ('unknown_node_key', NODE + '    var: [total]\n',
     "keyvars.yaml:4:5: nodes[0]: unknown key 'var' (expected: file, class, vars, "
     "module_vars, checkpoint_interval, replay)"),
    ('duplicate_key', NODE + '    vars: [total]\n    class: Other\n',
     "keyvars.yaml:5:5: nodes[0]: duplicate key 'class'"),
    ('duplicate_entry', NODE + '    vars: [total]\n'
     '  - file: ./integrator.py\n    class: Integrator\n    vars: [count]\n',
     'keyvars.yaml:5:5: nodes[1]: duplicate entry for integrator.py:Integrator '
     '(first at line 2)'),
    ('file_not_string', 'nodes:\n  - file: [integrator.py]\n    class: I\n    vars: [total]\n',
     'keyvars.yaml:2:11: nodes[0].file: expected a path relative to SRC'),
    ('class_not_a_name', 'nodes:\n  - file: integrator.py\n    class: 3D\n    vars: [total]\n',
     "keyvars.yaml:3:12: nodes[0].class: '3D' is not a class name (use Outer.Inner if "
     "nested)"),
    ('interval_negative', NODE + '    vars: [total]\n    checkpoint_interval: -1\n',
     "keyvars.yaml:5:26: nodes[0].checkpoint_interval: expected a positive number of "
     "seconds, got '-1'"),
    ('interval_quoted', NODE + '    vars: [total]\n    checkpoint_interval: "1"\n',
     "keyvars.yaml:5:26: nodes[0].checkpoint_interval: expected a positive number of "
     "seconds, got the string '1'"),
    ('interval_infinite', NODE + '    vars: [total]\n    checkpoint_interval: .inf\n',
     "keyvars.yaml:5:26: nodes[0].checkpoint_interval: expected a positive number of "
     "seconds, got '.inf'"),
    ('replay_unknown', NODE + '    vars: [total]\n    replay: slow\n',
     "keyvars.yaml:5:13: nodes[0].replay: expected 'paced' or 'fast', got 'slow'"),
    # Attribute paths, module vars and the combinations of class, vars and module_vars.
    ('file_only', 'nodes:\n  - file: integrator.py\n',
     "keyvars.yaml:2:5: nodes[0]: expected 'class' and 'vars' (a Node subclass and its "
     "attributes), 'module_vars' (module globals), or both"),
    ('vars_without_class', 'nodes:\n  - file: integrator.py\n    vars: [total]\n'
     '    module_vars: [counter]\n',
     "keyvars.yaml:2:5: nodes[0]: missing required key 'class'"),
    ('path_not_identifiers', NODE + '    vars: [total, ekf.2P]\n',
     "keyvars.yaml:4:19: nodes[0].vars[1]: 'ekf.2P' is not an attribute path (Python "
     'identifiers separated by dots, e.g. ekf.P)'),
    ('path_empty_segment', NODE + '    vars: [ekf.]\n',
     "keyvars.yaml:4:12: nodes[0].vars[0]: 'ekf.' is not an attribute path (Python "
     'identifiers separated by dots, e.g. ekf.P)'),
    ('path_keyword', NODE + '    vars: [pid.lambda]\n',
     "keyvars.yaml:4:12: nodes[0].vars[0]: 'pid.lambda' is not an attribute path (Python "
     'identifiers separated by dots, e.g. ekf.P)'),
    ('path_inside_listed', NODE + '    vars: [ekf, total, ekf.P]\n',
     "keyvars.yaml:4:24: nodes[0].vars[2]: 'ekf.P' overlaps 'ekf' (vars[0]); list either the "
     'whole object or parts of it'),
    ('path_around_listed', NODE + '    vars: [ekf.P, ekf]\n',
     "keyvars.yaml:4:19: nodes[0].vars[1]: 'ekf' overlaps 'ekf.P' (vars[0]); list either the "
     'whole object or parts of it'),
    ('module_vars_empty', NODE + '    module_vars: []\n',
     'keyvars.yaml:4:18: nodes[0].module_vars: expected a non-empty list of attribute names'),
    ('module_vars_not_list', 'nodes:\n  - file: integrator.py\n    module_vars: counter\n',
     'keyvars.yaml:3:18: nodes[0].module_vars: expected a non-empty list of attribute names'),
    ('module_var_not_identifier', 'nodes:\n  - file: a.py\n    module_vars: [counter, a-b]\n',
     "keyvars.yaml:3:28: nodes[0].module_vars[1]: 'a-b' is not a Python identifier"),
    ('module_var_duplicate', 'nodes:\n  - file: a.py\n    module_vars: [n, state.x, n]\n',
     "keyvars.yaml:3:31: nodes[0].module_vars[2]: duplicate var 'n'"),
    ('module_var_overlap', 'nodes:\n  - file: a.py\n    module_vars: [state.x, state]\n',
     "keyvars.yaml:3:28: nodes[0].module_vars[1]: 'state' overlaps 'state.x' "
     '(module_vars[0]); list either the whole object or parts of it'),
    ('duplicate_module_entry', 'nodes:\n  - file: a.py\n    module_vars: [n]\n'
     '  - file: ./a.py\n    module_vars: [m]\n',
     'keyvars.yaml:4:5: nodes[1]: duplicate module_vars entry for a.py (first at line 2)'),
    # Plain scalars are typed as YAML 1.2 (as editors and the schema see them).
    ('var_boolean', NODE + '    vars: [total, true]\n',
     'keyvars.yaml:4:19: nodes[0].vars[1]: expected an attribute name, got the boolean true '
     '(quote it if it is meant as a name)'),
    ('var_null', NODE + '    vars: [~]\n',
     'keyvars.yaml:4:12: nodes[0].vars[0]: expected an attribute name, got null (quote it if '
     'it is meant as a name)'),
    ('file_number', 'nodes:\n  - file: 123\n    class: I\n    vars: [total]\n',
     'keyvars.yaml:2:11: nodes[0].file: expected a path relative to SRC, got the number 123 '
     '(quote it if it is meant as a name)'),
    ('interval_underscore', NODE + '    vars: [total]\n    checkpoint_interval: 1_000\n',
     "keyvars.yaml:5:26: nodes[0].checkpoint_interval: expected a positive number of "
     "seconds, got '1_000'"),
    ('interval_boolean', NODE + '    vars: [total]\n    checkpoint_interval: true\n',
     "keyvars.yaml:5:26: nodes[0].checkpoint_interval: expected a positive number of "
     "seconds, got 'true'"),
    # Entries written as mappings, with freshness rules.
    ('rule_unknown_key', NODE + '    vars: [total, {count: 1}]\n',
     "keyvars.yaml:4:20: nodes[0].vars[1]: unknown key 'count' (expected: name, max_age, "
     "on_stale)"),
    ('rule_unknown_key_block', NODE + '    vars:\n      - total\n      - name: history\n'
     '        maxage: 5\n',
     "keyvars.yaml:7:9: nodes[0].vars[1]: unknown key 'maxage' (expected: name, max_age, "
     "on_stale)"),
    ('rule_duplicate_key', NODE + '    vars:\n      - name: history\n        max_age: 5\n'
     '        max_age: 6\n',
     "keyvars.yaml:7:9: nodes[0].vars[0]: duplicate key 'max_age'"),
    ('rule_missing_name', NODE + '    vars: [total, {max_age: 5}]\n',
     "keyvars.yaml:4:19: nodes[0].vars[1]: missing required key 'name'"),
    ('rule_name_not_identifier', NODE + '    vars: [{name: 2nd, max_age: 5}]\n',
     "keyvars.yaml:4:19: nodes[0].vars[0].name: '2nd' is not a Python identifier"),
    ('rule_name_boolean', NODE + '    vars: [{name: true}]\n',
     'keyvars.yaml:4:19: nodes[0].vars[0].name: expected an attribute name, got the boolean '
     'true (quote it if it is meant as a name)'),
    ('rule_max_age_negative', NODE + '    vars:\n      - total\n'
     '      - {name: history, max_age: -1}\n',
     "keyvars.yaml:6:34: nodes[0].vars[1].max_age: expected a positive number of seconds, "
     "got '-1'"),
    ('rule_max_age_zero', NODE + '    vars: [{name: history, max_age: 0}]\n',
     "keyvars.yaml:4:37: nodes[0].vars[0].max_age: expected a positive number of seconds, "
     "got '0'"),
    ('rule_max_age_quoted', NODE + "    vars: [{name: history, max_age: '5'}]\n",
     "keyvars.yaml:4:37: nodes[0].vars[0].max_age: expected a positive number of seconds, "
     "got the string '5'"),
    ('rule_max_age_nan', NODE + '    vars: [{name: history, max_age: .nan}]\n',
     "keyvars.yaml:4:37: nodes[0].vars[0].max_age: expected a positive number of seconds, "
     "got '.nan'"),
    ('rule_max_age_unit', NODE + '    vars: [{name: history, max_age: 5s}]\n',
     "keyvars.yaml:4:37: nodes[0].vars[0].max_age: expected a positive number of seconds, "
     "got '5s'"),
    ('rule_max_age_list', NODE + '    vars: [{name: history, max_age: [5]}]\n',
     'keyvars.yaml:4:37: nodes[0].vars[0].max_age: expected a positive number of seconds'),
    ('rule_on_stale_unknown', NODE + '    vars:\n      - name: history\n        max_age: 5\n'
     '        on_stale: drop\n',
     "keyvars.yaml:7:19: nodes[0].vars[0].on_stale: expected 'reset', 'keep' or 'refuse', "
     "got 'drop'"),
    ('rule_on_stale_case', NODE + '    vars: [{name: history, max_age: 5, on_stale: Keep}]\n',
     "keyvars.yaml:4:50: nodes[0].vars[0].on_stale: expected 'reset', 'keep' or 'refuse', "
     "got 'Keep'"),
    ('rule_on_stale_without_max_age', NODE + '    vars:\n      - total\n'
     '      - name: history\n        on_stale: keep\n',
     'keyvars.yaml:7:9: nodes[0].vars[1].on_stale: needs max_age; without it the variable '
     'is never stale'),
    # Duplicates and overlaps count across plain and mapping entries, at the path.
    ('rule_duplicates_plain', NODE + '    vars: [history, {name: history, max_age: 5}]\n',
     "keyvars.yaml:4:28: nodes[0].vars[1]: duplicate var 'history'"),
    ('plain_duplicates_rule', NODE + '    vars: [{name: history, max_age: 5}, total, history]\n',
     "keyvars.yaml:4:48: nodes[0].vars[2]: duplicate var 'history'"),
    ('rule_overlaps_plain', NODE + '    vars:\n      - ekf\n      - {name: ekf.P, max_age: 5}\n',
     "keyvars.yaml:6:16: nodes[0].vars[1]: 'ekf.P' overlaps 'ekf' (vars[0]); list either the "
     'whole object or parts of it'),
    ('module_rule_max_age', 'nodes:\n  - file: a.py\n'
     '    module_vars: [counter, {name: seen, max_age: .inf}]\n',
     "keyvars.yaml:3:50: nodes[0].module_vars[1].max_age: expected a positive number of "
     "seconds, got '.inf'"),
    ('module_rule_on_stale_without_max_age', 'nodes:\n  - file: a.py\n    module_vars:\n'
     '      - name: counter\n        on_stale: refuse\n',
     'keyvars.yaml:5:9: nodes[0].module_vars[0].on_stale: needs max_age; without it the '
     'variable is never stale'),
    ('module_rule_overlap', 'nodes:\n  - file: a.py\n'
     '    module_vars: [{name: state.pose, max_age: 1}, state]\n',
     "keyvars.yaml:3:51: nodes[0].module_vars[1]: 'state' overlaps 'state.pose' "
     '(module_vars[0]); list either the whole object or parts of it'),
]


@pytest.mark.parametrize(('yaml_text', 'message'), [c[1:] for c in CONFIG_ERRORS],
                         ids=[c[0] for c in CONFIG_ERRORS])
def test_config_error(work: Path, capsys: pytest.CaptureFixture[str], yaml_text: str,
                      message: str) -> None:
    fails_with(work, capsys, yaml_text, message)


def test_keyvars_unreadable(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    fails_with(work, capsys, None,
               'keyvars.yaml:0:0: cannot read keyvars file: No such file or directory')


SOURCE_ERRORS = [
    ('file_missing', 'integratr.py', 'Integrator', '[total]',
     "keyvars.yaml:2:11: file 'integratr.py' not found in SRC (src)"),
    ('file_outside', '../outside.py', 'Integrator', '[total]',
     "keyvars.yaml:2:11: file '../outside.py' is outside SRC (src)"),
    ('file_absolute', '/etc/hostname', 'Integrator', '[total]',
     "keyvars.yaml:2:11: file '/etc/hostname' must be relative to SRC"),
    ('file_is_directory', '.', 'Integrator', '[total]',
     "keyvars.yaml:2:11: file '.' is not a regular file"),
    ('syntax_error', 'broken.py', 'Broken', '[x]',
     "src/broken.py:3:19: syntax error: expected ':'"),
    ('class_not_found', 'integrator.py', 'Integrater', '[total]',
     "keyvars.yaml:3:12: class 'Integrater' not found in integrator.py; "
     'classes there: Integrator'),
    ('not_a_node', 'plain.py', 'Integrator', '[total]',
     "src/plain.py:1:1: class 'Integrator' does not derive from rclpy.node.Node "
     '(bases: none)'),
    ('var_never_assigned', 'integrator.py', 'Integrator', '[total, count, histroy]',
     'src/integrator.py:6:1: Integrator never assigns self.histroy '
     '(vars: total, count, histroy)'),
]


@pytest.mark.parametrize(('file', 'class_name', 'vars', 'message'),
                         [c[1:] for c in SOURCE_ERRORS], ids=[c[0] for c in SOURCE_ERRORS])
def test_source_error(work: Path, capsys: pytest.CaptureFixture[str], file: str,
                      class_name: str, vars: str, message: str) -> None:
    keyvars = f'nodes:\n  - file: {file}\n    class: {class_name}\n    vars: {vars}\n'
    fails_with(work, capsys, keyvars, message)


def test_error_in_second_file_writes_nothing(work: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    keyvars = GOOD + '  - file: plain.py\n    class: Integrator\n    vars: [total]\n'
    fails_with(work, capsys, keyvars,
               "src/plain.py:1:1: class 'Integrator' does not derive from rclpy.node.Node "
               '(bases: none)')


def test_src_not_a_directory(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    code, _, err = run(capsys, 'outside.py', '--vars', 'keyvars.yaml', '-o', 'out')
    assert (code, err) == (2, 'outside.py:0:0: SRC is not a directory\n')
    assert not (work / 'out').exists()


@pytest.mark.parametrize('out', ['src', 'src/out', './src/../src/sub/out'])
def test_out_inside_src(work: Path, capsys: pytest.CaptureFixture[str], out: str) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    before = sorted(p.name for p in (work / 'src').iterdir())
    code, _, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', out)
    assert code == 2
    assert err == f'{out}:0:0: OUT must not be SRC or inside it (SRC is {work / "src"})\n'
    assert sorted(p.name for p in (work / 'src').iterdir()) == before


def test_out_containing_src(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    (work / 'rory_manifest.json').write_text('{}\n')
    code, _, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', '.')
    assert (code, err) == (2, '.:0:0: OUT contains SRC; refusing to replace it\n')
    assert (work / 'src' / 'integrator.py').read_text() == INTEGRATOR


def test_out_exists_and_is_not_an_output(work: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    (work / 'out').mkdir()
    (work / 'out' / 'precious.txt').write_text('keep me')
    code, _, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'out')
    assert code == 2
    assert err == ('out:0:0: OUT exists and is not a rory-instrument output '
                   '(no rory_manifest.json); refusing to replace it\n')
    assert [p.name for p in (work / 'out').iterdir()] == ['precious.txt']


def test_out_is_a_file(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    code, _, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'outside.py')
    assert (code, err) == (2, 'outside.py:0:0: OUT exists and is not a directory\n')


def test_previous_output_is_replaced(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    (work / 'out').mkdir()
    (work / 'out' / 'rory_manifest.json').write_text('{}\n')
    (work / 'out' / 'stale.py').write_text('')
    code, out, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'out')
    assert (code, err) == (0, '')
    assert out == 'instrumented integrator.py:Integrator vars=total,count,history\n'
    assert sorted(p.name for p in (work / 'out').iterdir()) == [
        'broken.py', 'integrator.py', 'plain.py', 'rory_manifest.json'
    ]


def test_empty_out_directory_is_used(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    (work / 'out').mkdir()
    code, _, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'out')
    assert (code, err) == (0, '')
    assert (work / 'out' / 'rory_manifest.json').is_file()


def test_out_parent_is_created(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    code, _, _ = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'build/deep/out')
    assert code == 0
    assert (work / 'build' / 'deep' / 'out' / 'integrator.py').is_file()
    assert [p.name for p in (work / 'build' / 'deep').iterdir()] == ['out']


def test_check_writes_nothing(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    code, out, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '--check')
    assert (code, err) == (0, '')
    assert out == 'checked integrator.py:Integrator vars=total,count,history\n'
    code, out, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '--check', '-o', 'out')
    assert code == 0
    assert not (work / 'out').exists()


def test_out_required_without_check(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    with pytest.raises(SystemExit) as exited:
        main(['src', '--vars', 'keyvars.yaml'])
    assert exited.value.code == 2
    assert 'the following arguments are required: -o/--out' in capsys.readouterr().err


def test_manifest_file(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'src' / 'pkg').mkdir()
    (work / 'src' / 'pkg' / 'nodes.py').write_text(
        'from rclpy.node import Node\n\n\nclass Outer:\n    class Inner(Node):\n'
        '        def __init__(self):\n            self.x = 1\n'
    )
    (work / 'keyvars.yaml').write_text(
        GOOD + '    replay: paced\n'
        '  - file: pkg/nodes.py\n    class: Outer.Inner\n    vars: [x]\n'
        '    checkpoint_interval: 2\n'
    )
    code, out, _ = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'out')
    assert code == 0
    assert out.splitlines() == [
        'instrumented integrator.py:Integrator vars=total,count,history',
        'instrumented pkg/nodes.py:Outer.Inner vars=x',
    ]
    text = (work / 'out' / 'rory_manifest.json').read_text()
    assert text.endswith('}\n')
    document = json.loads(text)
    assert text == json.dumps(document, indent=2, sort_keys=True) + '\n'
    assert document['format'] == 1
    first, second = document['nodes']
    assert set(first) == {'file', 'class', 'vars', 'source_sha256', 'manifest', 'replay'}
    assert (first['file'], first['class'], first['vars'], first['replay']) == (
        'integrator.py', 'Integrator', ['total', 'count', 'history'], 'paced'
    )
    assert (second['file'], second['class'], second['checkpoint_interval']) == (
        'pkg/nodes.py', 'Outer.Inner', 2.0
    )
    for entry in (first, second):
        assert f'manifest="{entry["manifest"]}"' in (work / 'out' / entry['file']).read_text()


def test_interval_and_replay_are_not_hashed(work: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    assert run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'a')[0] == 0
    (work / 'keyvars.yaml').write_text(GOOD + '    replay: fast\n    checkpoint_interval: 1\n')
    assert run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'b')[0] == 0
    first, second = (json.loads((work / d / 'rory_manifest.json').read_text())['nodes'][0]
                     for d in ('a', 'b'))
    assert first['manifest'] == second['manifest']
    # The settings go into the decorator, next to the same digest.
    a, b = ((work / d / 'integrator.py').read_text() for d in ('a', 'b'))
    assert b == a.replace(' manifest=', ' checkpoint_interval=1.0, replay="fast", manifest=')
    assert a != b


def test_freshness_rules_are_not_hashed(work: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'keyvars.yaml').write_text(GOOD)
    assert run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'a')[0] == 0
    (work / 'keyvars.yaml').write_text(GOOD.replace(
        'history]', '{name: history, max_age: 5, on_stale: keep}]'
    ))
    code, out, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'b')
    assert (code, err) == (0, '')
    assert out == 'instrumented integrator.py:Integrator vars=total,count,history\n'
    # The manifest file is the same byte for byte; only the decorator gains the rule.
    a, b = ((work / d / 'rory_manifest.json').read_text() for d in ('a', 'b'))
    assert a == b
    a, b = ((work / d / 'integrator.py').read_text() for d in ('a', 'b'))
    assert b == a.replace(' manifest=', ' freshness=(("history", 5.0, "keep"),), manifest=')
    assert a != b


def test_node_spec_keeps_positions() -> None:
    keyvars = parse_keyvars(
        'nodes:\n  - file: a.py\n    class: A\n    vars: [on, yes]\n'
        '    checkpoint_interval: 1e-3\n',
        'k.yaml',
    )
    (spec,) = keyvars.nodes
    # Attribute names are taken as written, not as YAML 1.1 booleans.
    assert (spec.file, spec.class_name, spec.vars) == ('a.py', 'A', ('on', 'yes'))
    assert spec.checkpoint_interval == 0.001
    assert spec.replay is None
    assert spec.mark() == Mark(2, 5)
    assert spec.mark('class') == Mark(3, 12)
    assert spec.mark('vars[1]') == Mark(4, 16)
    assert spec.mark('replay') == Mark(2, 5)  # absent: falls back to the node
    assert spec.field_path('vars') == 'nodes[0].vars'
    assert str(keyvars.error(spec, 'vars[1]', 'x')) == 'k.yaml:4:16: x'


def test_new_fields_and_their_positions() -> None:
    keyvars = parse_keyvars(
        'nodes:\n'
        '  - file: counter.py\n'
        '    module_vars: [counter, state.pose]\n'
        '    checkpoint_interval: 0x10\n'
        '    replay: fast\n'
        '  - file: counter.py\n'
        '    class: Outer.Inner\n'
        "    vars: [ekf.P, 'true', pid.accu_e]\n"
        '    module_vars: [counter]\n',
        'k.yaml',
    )
    module, both = keyvars.nodes
    assert (module.class_name, module.vars, module.module_vars) == (
        None, (), ('counter', 'state.pose')
    )
    assert (module.checkpoint_interval, module.replay) == (16.0, 'fast')
    assert module.label == 'counter.py'
    assert module.mark('module_vars[1]') == Mark(3, 28)
    assert (both.class_name, both.vars, both.module_vars) == (
        'Outer.Inner', ('ekf.P', 'true', 'pid.accu_e'), ('counter',)
    )
    assert both.label == 'counter.py:Outer.Inner'


def test_freshness_rules_and_their_positions() -> None:
    keyvars = parse_keyvars(
        'nodes:\n'
        '  - file: a.py\n'
        '    class: A\n'
        '    module_vars:\n'
        '      - {name: counter, max_age: 30, on_stale: refuse}\n'
        '    vars:\n'
        '      - total\n'
        '      - {name: history, max_age: 5.0, on_stale: reset}\n'
        '      - {name: goal, max_age: 0x1e}\n'
        '      - {name: pose}\n'
        '      - name: ekf.P\n'
        '        on_stale: keep\n'
        '        max_age: 1e-1\n',
        'k.yaml',
    )
    (spec,) = keyvars.nodes
    # The paths are plain strings whichever way they were written.
    assert spec.vars == ('total', 'history', 'goal', 'pose', 'ekf.P')
    assert spec.module_vars == ('counter',)
    # Only entries with max_age make a rule; those of vars come first, each in list order.
    assert spec.freshness == (
        FreshnessRule('history', 5.0, 'reset', module=False),
        FreshnessRule('goal', 30.0, 'reset', module=False),
        FreshnessRule('ekf.P', 0.1, 'keep', module=False),
        FreshnessRule('counter', 30.0, 'refuse', module=True),
    )
    # A mapping entry's own position is its name's, so messages about the path point there.
    assert spec.mark('vars[1]') == spec.mark('vars[1].name') == Mark(8, 16)
    assert spec.mark('vars[1].max_age') == Mark(8, 34)
    assert spec.mark('vars[1].on_stale') == Mark(8, 49)
    assert spec.mark('vars[4]') == Mark(11, 15)
    assert spec.mark('vars[4].max_age') == Mark(13, 18)
    assert spec.mark('module_vars[0].on_stale') == Mark(5, 48)
    assert spec.mark('vars[2].on_stale') == Mark(2, 5)  # absent: falls back to the node


def test_a_mapping_without_max_age_is_a_plain_entry() -> None:
    plain = parse_keyvars(GOOD, 'k.yaml')
    mapped = parse_keyvars(
        GOOD.replace('[total, count, history]', '\n      - total\n      - {name: count}\n'
                     '      - name: history'),
        'k.yaml',
    )
    assert mapped.nodes == plain.nodes
    assert mapped.nodes[0].freshness == ()


def test_class_without_vars_needs_module_vars() -> None:
    spec, = parse_keyvars(
        'nodes:\n  - file: a.py\n    class: A\n    module_vars: [n]\n', 'k.yaml'
    ).nodes
    assert (spec.class_name, spec.vars, spec.module_vars) == ('A', (), ('n',))


@pytest.mark.parametrize(
    ('text', 'value'),
    [('2', 2.0), ('0.5', 0.5), ('1e-3', 0.001), ('+.5', 0.5), ('0o10', 8.0), ('1.', 1.0)],
)
def test_interval_numbers(text: str, value: float) -> None:
    keyvars = parse_keyvars(GOOD + f'    checkpoint_interval: {text}\n', 'k.yaml')
    assert keyvars.nodes[0].checkpoint_interval == value


def test_module_var_not_found_through_the_command(work: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'src' / 'counter.py').write_text('import rclpy\n\ncounter = 0\n')
    fails_with(
        work, capsys, 'nodes:\n  - file: counter.py\n    module_vars: [counter, histroy]\n',
        "keyvars.yaml:3:28: module variable 'histroy' not found in counter.py: it is never "
        "assigned at module level or after 'global histroy' in a function (globals there: "
        'counter)',
    )


def test_not_state_through_the_command(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'src' / 'integrator.py').write_text(
        INTEGRATOR + "        self.pub = self.create_publisher(Int64, 'sum', 10)\n"
    )
    fails_with(
        work, capsys, GOOD.replace('history]', 'history, pub]'),
        'src/integrator.py:14:9: Integrator.pub holds a Publisher (self.create_publisher(...)), '
        'which is not state; list the data it publishes instead',
    )


def test_module_entry_through_the_command(work: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'src' / 'counter.py').write_text(
        'import rclpy\n\ncounter = 0\n\n\ndef main():\n    global history\n'
        '    history = []\n'
    )
    (work / 'src' / 'integrator.py').write_text(INTEGRATOR + '\n\ncounter = 0\n')
    (work / 'keyvars.yaml').write_text(
        GOOD + '    module_vars: [counter]\n'
        '  - file: counter.py\n    module_vars: [counter, history]\n    replay: fast\n'
    )
    code, out, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'out')
    assert (code, err) == (0, '')
    assert out.splitlines() == [
        'instrumented integrator.py:Integrator vars=total,count,history module_vars=counter',
        'instrumented counter.py module_vars=counter,history',
    ]
    document = json.loads((work / 'out' / 'rory_manifest.json').read_text())
    module, integrator = document['nodes']  # sorted by file
    assert set(module) == {'file', 'vars', 'module_vars', 'source_sha256', 'manifest', 'replay'}
    assert (module['file'], module['vars'], module['module_vars'], module['replay']) == (
        'counter.py', [], ['counter', 'history'], 'fast'
    )
    assert integrator['module_vars'] == ['counter']
    text = (work / 'out' / 'counter.py').read_text()
    assert text == (
        'import rclpy\nimport rory_runtime\nrory_runtime.checkpoint_module(__name__, '
        f'vars=("counter", "history"), replay="fast", manifest="{module["manifest"]}")\n'
        '\ncounter = 0\n\n\ndef main():\n    global history\n    history = []\n'
    )
    assert 'module_vars=("counter",), manifest=' in (work / 'out' / 'integrator.py').read_text()


BASE = """\
import threading

from rclpy.node import Node


class BaseNode(Node):
    def __init__(self, name):
        super().__init__(name)
        self.count = 0
        self.lock = threading.Lock()
"""

CHILD = """\
from my_pkg.base import BaseNode
from .base import BaseNode as Relative


class Child(BaseNode):
    def __init__(self):
        super().__init__('child')
        self.total = 0


class Bare(Relative):
    pass
"""


@pytest.fixture
def package(work: Path) -> Path:
    """src/my_pkg/my_pkg/{base,child}.py: a ROS package whose node derives from another file."""
    root = work / 'src' / 'my_pkg' / 'my_pkg'
    root.mkdir(parents=True)
    (root / '__init__.py').write_text('')
    (root / 'base.py').write_text(BASE)
    (root / 'child.py').write_text(CHILD)
    return work


def child_entry(class_name: str, vars: str) -> str:
    return f'nodes:\n  - file: my_pkg/my_pkg/child.py\n    class: {class_name}\n    vars: {vars}\n'


def test_base_class_in_another_file(package: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (package / 'keyvars.yaml').write_text(
        child_entry('Child', '[total, count]')
        + '  - file: my_pkg/my_pkg/child.py\n    class: Bare\n    vars: [count]\n'
    )
    code, out, err = run(capsys, 'src', '--vars', 'keyvars.yaml', '-o', 'out')
    assert (code, err) == (0, '')
    assert out.splitlines() == [
        'instrumented my_pkg/my_pkg/child.py:Child vars=total,count',
        'instrumented my_pkg/my_pkg/child.py:Bare vars=count',
    ]
    # The base's file is copied as it is.
    assert (package / 'out/my_pkg/my_pkg/base.py').read_text() == BASE


@pytest.mark.parametrize(
    ('class_name', 'vars', 'message'),
    [
        ('Child', '[total, missing]',
         'src/my_pkg/my_pkg/child.py:5:1: Child never assigns self.missing '
         '(vars: total, missing)'),
        # Refused where the base's file shows it.
        ('Bare', '[lock]',
         'src/my_pkg/my_pkg/base.py:10:9: Bare.lock holds a Lock (threading.Lock()), which is '
         'not state; list the data it guards instead'),
    ],
)
def test_base_class_in_another_file_errors(package: Path, capsys: pytest.CaptureFixture[str],
                                           class_name: str, vars: str, message: str) -> None:
    fails_with(package, capsys, child_entry(class_name, vars), message)


def test_base_class_file_not_in_src(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (work / 'src' / 'child.py').write_text(CHILD.replace('\nfrom .base import BaseNode as '
                                                         'Relative\n', '\n'))
    fails_with(work, capsys, 'nodes:\n  - file: child.py\n    class: Child\n    vars: [total]\n',
               "src/child.py:4:1: class 'Child' does not derive from rclpy.node.Node "
               '(bases: BaseNode)')


def test_base_candidates() -> None:
    assert list(base_candidates('pkg/sub/node.py', '.base.BaseNode')) == [
        ('pkg/sub/base.py', 'BaseNode'), ('pkg/sub/base/__init__.py', 'BaseNode'),
    ]
    # Longest module path first; `..` is the parent package.
    assert list(base_candidates('pkg/sub/node.py', '..common.base.Outer.Inner')) == [
        ('pkg/common/base/Outer.py', 'Inner'), ('pkg/common/base/Outer/__init__.py', 'Inner'),
        ('pkg/common/base.py', 'Outer.Inner'), ('pkg/common/base/__init__.py', 'Outer.Inner'),
        ('pkg/common.py', 'base.Outer.Inner'), ('pkg/common/__init__.py', 'base.Outer.Inner'),
    ]
    # Absolute: from the file's folder, then each folder above it.
    assert list(base_candidates('pkg/node.py', 'pkg.base.B')) == [
        ('pkg/pkg/base.py', 'B'), ('pkg/pkg/base/__init__.py', 'B'),
        ('pkg/pkg.py', 'base.B'), ('pkg/pkg/__init__.py', 'base.B'),
        ('pkg/base.py', 'B'), ('pkg/base/__init__.py', 'B'),
        ('pkg.py', 'base.B'), ('pkg/__init__.py', 'base.B'),
    ]
    # Above SRC: nothing to look at.
    assert list(base_candidates('node.py', '..base.B')) == []


def test_load_keyvars_reads_file(tmp_path: Path) -> None:
    path = tmp_path / 'k.yaml'
    path.write_text(GOOD)
    assert load_keyvars(path).nodes[0].vars == ('total', 'count', 'history')
    path.write_bytes(b'\xff\xfe')
    with pytest.raises(ConfigError, match='cannot read keyvars file'):
        load_keyvars(path, 'k.yaml')
