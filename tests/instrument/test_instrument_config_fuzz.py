"""Fuzzing keyvars.yaml: whatever the text, the parser returns a KeyVars or raises ConfigError."""

from __future__ import annotations

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis_budget import examples

from rory_instrument.config import KeyVars, parse_keyvars
from rory_instrument.errors import ConfigError

# Values of the shapes keyvars.yaml is made of, plus the odd ones a hand-edited file gets.
scalars = (
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True)
    | st.sampled_from(['a.py', 'Node', 'x.y', 'fast', 'paced', '', '..', '1a', 'a b', '/abs.py',
                       'reset', 'keep', 'refuse'])
    | st.text(max_size=12)
)
values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
        st.sampled_from(['nodes', 'file', 'class', 'vars', 'module_vars', 'checkpoint_interval',
                         'replay', 'name', 'max_age', 'on_stale', 'x']) | st.text(max_size=6),
        inner, max_size=5),
    max_leaves=20,
)
node = st.fixed_dictionaries(
    {'file': st.sampled_from(['a.py', 'pkg/b.py', '../c.py', 5])},
    optional={'class': scalars, 'vars': values, 'module_vars': values,
              'checkpoint_interval': scalars, 'replay': scalars, 'extra': scalars},
)
documents = st.fixed_dictionaries({'nodes': st.lists(node, max_size=3) | values}) | values


def _parse(text: str) -> None:
    try:
        result = parse_keyvars(text, 'keyvars.yaml')
    except ConfigError as err:
        assert str(err).startswith('keyvars.yaml:')
        return
    assert isinstance(result, KeyVars)


@settings(max_examples=examples(300), deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(documents)
def test_structured_documents_parse_or_raise_config_error(doc: object) -> None:
    _parse(yaml.safe_dump(doc, allow_unicode=True))


@settings(max_examples=examples(300), deadline=None)
@given(st.text(max_size=200))
def test_any_text_parses_or_raises_config_error(text: str) -> None:
    _parse(text)


@settings(max_examples=examples(200), deadline=None)
@given(st.sampled_from([
    'nodes:\n  - file: a.py\n    class: A\n    vars: [x]\n',
    'nodes:\n  - file: a.py\n    module_vars: [x, y]\n    replay: fast\n',
    'nodes:\n  - file: a.py\n    class: A\n    vars: [x, {name: y, max_age: 5, on_stale: keep}]\n',
]), st.integers(0, 80), st.sampled_from([':', '-', '[', ']', '{', '&a', '*a', '!!python/object',
                                         '\t', '\x00', '"', '\ufeff', '%YAML 1.1\n']))
def test_a_valid_file_mangled_at_any_point_parses_or_raises_config_error(
    base: str, at: int, junk: str
) -> None:
    _parse(base[:at] + junk + base[at:])
