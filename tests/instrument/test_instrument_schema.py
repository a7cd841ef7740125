"""keyvars.schema.json against the hand-written parser: they must agree on what is valid.

Documents are read as editors read them, by YAML 1.2's core schema (``on`` is a string,
``true`` a boolean), with a small converter of its own here, independent of the parser's.
The parser checks a few things a JSON Schema cannot say; those are listed in
``PARSER_ONLY`` and must pass the schema and fail the parser.
"""

from __future__ import annotations

import json
import keyword
import math
import re
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from rory_instrument.config import SCHEMA_NAME, STALE_ACTIONS, keyvars_schema, parse_keyvars
from rory_instrument.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
SCHEMA_FILE = ROOT / 'rory_instrument' / SCHEMA_NAME

_INT = re.compile(r'[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+')
_FLOAT = re.compile(r'[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?')
_INF = re.compile(r'([-+]?)\.(inf|Inf|INF)')
_NAN = re.compile(r'\.(nan|NaN|NAN)')


def yaml12(node: yaml.Node | None) -> Any:
    """Returns the JSON value of a composed YAML node under the YAML 1.2 core schema."""
    if node is None:
        return None
    if isinstance(node, yaml.MappingNode):
        return {str(yaml12(k)): yaml12(v) for k, v in node.value}
    if isinstance(node, yaml.SequenceNode):
        return [yaml12(item) for item in node.value]
    assert isinstance(node, yaml.ScalarNode)
    text = node.value
    if node.style is not None:
        return text
    if text in ('', '~', 'null', 'Null', 'NULL'):
        return None
    if text in ('true', 'True', 'TRUE', 'false', 'False', 'FALSE'):
        return text.lower() == 'true'
    if _INT.fullmatch(text):
        return int(text, 0) if text[:2] in ('0o', '0x') else int(text)
    if _FLOAT.fullmatch(text):
        return float(text)
    if match := _INF.fullmatch(text):
        return -math.inf if match.group(1) == '-' else math.inf
    if _NAN.fullmatch(text):
        return math.nan
    return text


def schema_valid(text: str) -> bool:
    document = yaml12(yaml.compose(text, Loader=yaml.SafeLoader))
    try:
        # A JSON Schema describes JSON: a document with no JSON form (.nan) is not valid.
        json.dumps(document, allow_nan=False)
    except ValueError:
        return False
    return bool(jsonschema.Draft202012Validator(keyvars_schema()).is_valid(document))


def parser_valid(text: str) -> bool:
    try:
        parse_keyvars(text, 'keyvars.yaml')
    except ConfigError:
        return False
    return True


N = 'nodes:\n  - file: a.py\n'
C = N + '    class: A\n'

VALID = [
    ('minimal', C + '    vars: [total, count, history]\n'),
    ('flow_style', 'nodes: [{file: a.py, class: A, vars: [x]}]\n'),
    ('nested_class', N + '    class: Outer.Inner\n    vars: [x]\n'),
    ('settings', C + '    vars: [x]\n    checkpoint_interval: 0.5\n    replay: paced\n'),
    ('settings_int', C + '    vars: [x]\n    checkpoint_interval: 2\n    replay: fast\n'),
    ('interval_exponent', C + '    vars: [x]\n    checkpoint_interval: 1e-3\n'),
    ('interval_hex', C + '    vars: [x]\n    checkpoint_interval: 0x10\n'),
    ('paths', C + '    vars: [total, ekf.P, pid.accu_e, a.b.c]\n'),
    ('module_vars', N + '    module_vars: [counter, state.pose]\n'),
    ('module_vars_settings', N + '    module_vars: [counter]\n    replay: fast\n'),
    ('class_and_module_vars', C + '    vars: [x]\n    module_vars: [counter]\n'),
    ('class_without_vars', C + '    module_vars: [counter]\n'),
    ('yaml11_booleans_are_names', C + '    vars: [on, yes, off, no, y]\n'),
    ('quoted_true', C + "    vars: ['true', \"null\"]\n"),
    ('soft_keywords', C + '    vars: [match, case, type, _]\n'),
    ('unicode_identifiers', C + '    vars: [größe, état.π]\n'),
    ('quoted_number_file', "nodes:\n  - file: '123'\n    class: A\n    vars: [x]\n"),
    ('file_path', 'nodes:\n  - file: pkg/sub/node.py\n    class: A\n    vars: [x]\n'),
    ('two_nodes', C + '    vars: [x]\n  - file: b.py\n    module_vars: [y]\n'),
    ('same_file_module_and_class', C + '    vars: [x]\n  - file: a.py\n    module_vars: [y]\n'),
    ('comments', '# state\nnodes:  # all\n  - file: a.py  # here\n    class: A\n    vars: [x]\n'),
    # Entries written as mappings, with freshness rules.
    ('rules', C + '    vars: [total, {name: history, max_age: 5.0, on_stale: reset}]\n'),
    ('rules_block', C + '    vars:\n      - name: goal\n        max_age: 30\n'
     '        on_stale: refuse\n      - total\n'),
    ('rule_default_action', C + '    vars: [{name: goal, max_age: 30}]\n'),
    ('rule_keep', C + '    vars: [{name: goal, max_age: 1e-3, on_stale: keep}]\n'),
    ('rule_name_only', C + '    vars: [{name: pose}, ekf.P]\n'),
    ('rule_dotted_name', C + '    vars: [{name: ekf.P, max_age: 0x10}]\n'),
    ('rule_yaml11_name', C + '    vars: [{name: on, max_age: 1}]\n'),
    ('rule_module_vars', N + '    module_vars: [n, {name: seen, max_age: 2, on_stale: keep}]\n'),
]

INVALID = [
    ('empty', ''),
    ('null_document', '~\n'),
    ('top_list', '- a.py\n'),
    ('no_nodes', '{}\n'),
    ('unknown_top_key', 'nodes: []\nversion: 1\n'),
    ('nodes_empty', 'nodes: []\n'),
    ('nodes_mapping', 'nodes: {file: a.py}\n'),
    ('node_scalar', 'nodes: [a.py]\n'),
    ('file_only', N),
    ('no_file', 'nodes:\n  - class: A\n    vars: [x]\n'),
    ('file_empty', "nodes:\n  - file: ''\n    class: A\n    vars: [x]\n"),
    ('file_number', 'nodes:\n  - file: 123\n    class: A\n    vars: [x]\n'),
    ('file_list', 'nodes:\n  - file: [a.py]\n    class: A\n    vars: [x]\n'),
    ('class_without_vars', C),
    ('vars_without_class', N + '    vars: [x]\n'),
    ('vars_without_class_with_module_vars', N + '    vars: [x]\n    module_vars: [y]\n'),
    ('unknown_node_key', C + '    vars: [x]\n    var: [y]\n'),
    ('class_not_a_name', N + '    class: 3D\n    vars: [x]\n'),
    ('class_keyword', N + '    class: Outer.class\n    vars: [x]\n'),
    ('class_number', N + '    class: 3\n    vars: [x]\n'),
    ('vars_empty', C + '    vars: []\n'),
    ('vars_scalar', C + '    vars: x\n'),
    ('var_not_identifier', C + '    vars: [2nd]\n'),
    ('var_keyword', C + '    vars: [class]\n'),
    ('var_mapping', C + '    vars: [{x: 1}]\n'),
    ('var_boolean', C + '    vars: [true]\n'),
    ('var_null', C + '    vars: [null]\n'),
    ('var_number', C + '    vars: [1]\n'),
    ('var_duplicate', C + '    vars: [x, y, x]\n'),
    ('path_bad_segment', C + '    vars: [ekf.2P]\n'),
    ('path_empty_segment', C + '    vars: [ekf..P]\n'),
    ('path_trailing_dot', C + '    vars: [ekf.]\n'),
    ('path_keyword_segment', C + '    vars: [pid.None]\n'),
    ('path_space', C + '    vars: [ekf. P]\n'),
    ('module_vars_empty', N + '    module_vars: []\n'),
    ('module_vars_scalar', N + '    module_vars: counter\n'),
    ('module_var_dash', N + '    module_vars: [a-b]\n'),
    ('module_var_duplicate', N + '    module_vars: [n, n]\n'),
    ('interval_zero', C + '    vars: [x]\n    checkpoint_interval: 0\n'),
    ('interval_negative', C + '    vars: [x]\n    checkpoint_interval: -1.5\n'),
    ('interval_string', C + "    vars: [x]\n    checkpoint_interval: '1'\n"),
    ('interval_word', C + '    vars: [x]\n    checkpoint_interval: fast\n'),
    ('interval_underscore', C + '    vars: [x]\n    checkpoint_interval: 1_000\n'),
    ('interval_inf', C + '    vars: [x]\n    checkpoint_interval: .inf\n'),
    ('interval_nan', C + '    vars: [x]\n    checkpoint_interval: .nan\n'),
    ('interval_boolean', C + '    vars: [x]\n    checkpoint_interval: true\n'),
    ('replay_unknown', C + '    vars: [x]\n    replay: slow\n'),
    ('replay_boolean', C + '    vars: [x]\n    replay: true\n'),
    ('replay_list', C + '    vars: [x]\n    replay: [fast]\n'),
    ('rule_unknown_key', C + '    vars: [{name: x, maxage: 5}]\n'),
    ('rule_no_name', C + '    vars: [{max_age: 5}]\n'),
    ('rule_empty', C + '    vars: [{}]\n'),
    ('rule_as_list', C + '    vars: [[x, 5]]\n'),
    ('rule_name_number', C + '    vars: [{name: 1}]\n'),
    ('rule_name_keyword', C + '    vars: [{name: a.class, max_age: 1}]\n'),
    ('rule_name_list', C + '    vars: [{name: [x]}]\n'),
    ('rule_on_stale_without_max_age', C + '    vars: [{name: x, on_stale: keep}]\n'),
    ('rule_max_age_zero', C + '    vars: [{name: x, max_age: 0}]\n'),
    ('rule_max_age_negative', C + '    vars: [{name: x, max_age: -5}]\n'),
    ('rule_max_age_string', C + "    vars: [{name: x, max_age: '5'}]\n"),
    ('rule_max_age_unit', C + '    vars: [{name: x, max_age: 5s}]\n'),
    ('rule_max_age_inf', C + '    vars: [{name: x, max_age: .inf}]\n'),
    ('rule_max_age_nan', C + '    vars: [{name: x, max_age: .nan}]\n'),
    ('rule_max_age_boolean', C + '    vars: [{name: x, max_age: true}]\n'),
    ('rule_on_stale_unknown', C + '    vars: [{name: x, max_age: 5, on_stale: drop}]\n'),
    ('rule_on_stale_case', C + '    vars: [{name: x, max_age: 5, on_stale: RESET}]\n'),
    ('rule_on_stale_null', C + '    vars: [{name: x, max_age: 5, on_stale: null}]\n'),
    ('module_rule_unknown_key', N + '    module_vars: [{name: n, max_age: 5, stale: keep}]\n'),
]

# Rules a JSON Schema cannot say: the schema accepts these, the parser refuses them.
PARSER_ONLY = [
    ('duplicate_key', C + '    vars: [x]\n    class: B\n'),
    ('duplicate_entry', C + '    vars: [x]\n  - file: ./a.py\n    class: A\n    vars: [y]\n'),
    ('duplicate_module_entry', N + '    module_vars: [x]\n  - file: a.py\n    module_vars: [y]\n'),
    ('path_inside_listed', C + '    vars: [ekf, ekf.P]\n'),
    ('module_path_inside_listed', N + '    module_vars: [state.pose, state]\n'),
    # The schema admits any non-ASCII letter-like character; Python's rules are finer.
    ('non_identifier_unicode', C + '    vars: [price€]\n'),
    # uniqueItems compares whole items: a path written both ways is two different items.
    ('rule_duplicates_plain', C + '    vars: [x, {name: x, max_age: 5}]\n'),
    ('rule_overlaps_plain', C + '    vars: [ekf, {name: ekf.P, max_age: 5}]\n'),
    ('rule_duplicate_key', C + '    vars: [{name: x, max_age: 5, max_age: 6}]\n'),
]


@pytest.mark.parametrize('text', [c[1] for c in VALID], ids=[c[0] for c in VALID])
def test_both_accept(text: str) -> None:
    assert (schema_valid(text), parser_valid(text)) == (True, True)


@pytest.mark.parametrize('text', [c[1] for c in INVALID], ids=[c[0] for c in INVALID])
def test_both_reject(text: str) -> None:
    assert (schema_valid(text), parser_valid(text)) == (False, False)


@pytest.mark.parametrize('text', [c[1] for c in PARSER_ONLY], ids=[c[0] for c in PARSER_ONLY])
def test_parser_only_rules(text: str) -> None:
    assert (schema_valid(text), parser_valid(text)) == (True, False)


@pytest.mark.parametrize('word', keyword.kwlist)
def test_every_keyword_is_refused(word: str) -> None:
    for text in (C + f'    vars: [{word}]\n', C + f'    vars: [a.{word}.b]\n',
                 N + f'    class: {word}\n    vars: [x]\n'):
        assert (schema_valid(text), parser_valid(text)) == (False, False), text


def test_schema_is_valid_draft_2020_12() -> None:
    schema = keyvars_schema()
    assert schema['$schema'] == 'https://json-schema.org/draft/2020-12/schema'
    jsonschema.Draft202012Validator.check_schema(schema)
    # The packaged copy is the file in the source tree.
    assert schema == json.loads(SCHEMA_FILE.read_text(encoding='utf-8'))


def test_schema_documents_every_field() -> None:
    schema = keyvars_schema()
    node = schema['$defs']['node']
    assert set(node['properties']) == {
        'file', 'class', 'vars', 'module_vars', 'checkpoint_interval', 'replay'
    }
    rule = schema['$defs']['pathWithRule']
    assert set(rule['properties']) == {'name', 'max_age', 'on_stale'}
    described = [schema, schema['properties']['nodes'], *schema['$defs'].values(),
                 *node['properties'].values(), *rule['properties'].values()]
    for part in described:
        assert part.get('title') and part.get('description'), part


def examples() -> list[Path]:
    return sorted((ROOT / 'examples').glob('**/keyvars.yaml'))


def test_there_are_examples() -> None:
    assert examples()


@pytest.mark.parametrize('path', examples(), ids=lambda p: str(p.relative_to(ROOT)))
def test_examples_validate(path: Path) -> None:
    text = path.read_text(encoding='utf-8')
    assert schema_valid(text)
    assert parser_valid(text)


def test_schema_refuses_an_infinite_interval() -> None:
    # For validators that read YAML's .inf as a number rather than refusing it.
    validator = jsonschema.Draft202012Validator(keyvars_schema())
    node = {'file': 'a.py', 'class': 'A', 'vars': ['x']}
    assert validator.is_valid({'nodes': [{**node, 'checkpoint_interval': 1e308}]})
    assert not validator.is_valid({'nodes': [{**node, 'checkpoint_interval': math.inf}]})
    for max_age, valid in ((1e308, True), (math.inf, False)):
        entry = {**node, 'vars': [{'name': 'x', 'max_age': max_age}]}
        assert validator.is_valid({'nodes': [entry]}) == valid


def test_schema_and_parser_agree_on_the_actions() -> None:
    on_stale = keyvars_schema()['$defs']['pathWithRule']['properties']['on_stale']
    assert tuple(on_stale['enum']) == STALE_ACTIONS
    assert on_stale['default'] == STALE_ACTIONS[0]
