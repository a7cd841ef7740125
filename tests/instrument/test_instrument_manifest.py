"""The manifest digest and rory_manifest.json."""

from __future__ import annotations

import hashlib
import json

from rory_instrument.config import parse_keyvars
from rory_instrument.manifest import ManifestEntry, manifest_digest, render_manifest

SHA = 'ab' * 32


def test_digest_is_sha256_of_canonical_json() -> None:
    canonical = (
        '{"class":"Outer.Inner","file":"pkg/node.py","source_sha256":"' + SHA + '",'
        '"vars":["total","count"]}'
    )
    expected = 'sha256:' + hashlib.sha256(canonical.encode()).hexdigest()
    assert manifest_digest(file='pkg/node.py', class_name='Outer.Inner',
                           vars=('total', 'count'), source_sha256=SHA) == expected


def test_digest_depends_on_every_input() -> None:
    variants = [
        ('a.py', 'A', ('x', 'y'), SHA),
        ('b.py', 'A', ('x', 'y'), SHA),
        ('a.py', 'B', ('x', 'y'), SHA),
        ('a.py', 'A', ('y', 'x'), SHA),
        ('a.py', 'A', ('x', 'y'), 'cd' * 32),
    ]
    digests = {
        manifest_digest(file=f, class_name=c, vars=v, source_sha256=s) for f, c, v, s in variants
    }
    assert len(digests) == len(variants)


def test_render_manifest_sorted_and_stable() -> None:
    b = ManifestEntry('b.py', 'B', ('x',), SHA, 'sha256:2', checkpoint_interval=0.5)
    a2 = ManifestEntry('a.py', 'Z', ('y',), SHA, 'sha256:3', replay='fast')
    a1 = ManifestEntry('a.py', 'A', ('z',), SHA, 'sha256:1')
    text = render_manifest([b, a2, a1])
    assert text == render_manifest([a1, a2, b])
    assert text.endswith('\n') and not text.endswith('\n\n')
    document = json.loads(text)
    assert document == {
        'format': 1,
        'nodes': [
            {'file': 'a.py', 'class': 'A', 'vars': ['z'], 'source_sha256': SHA,
             'manifest': 'sha256:1'},
            {'file': 'a.py', 'class': 'Z', 'vars': ['y'], 'source_sha256': SHA,
             'manifest': 'sha256:3', 'replay': 'fast'},
            {'file': 'b.py', 'class': 'B', 'vars': ['x'], 'source_sha256': SHA,
             'manifest': 'sha256:2', 'checkpoint_interval': 0.5},
        ],
    }
    assert text.startswith('{\n  "format": 1,\n  "nodes": [\n    {\n      "class": "A",\n')


def test_digest_with_module_vars() -> None:
    both = (
        '{"class":"A","file":"a.py","module_vars":["counter"],"source_sha256":"' + SHA + '",'
        '"vars":["x"]}'
    )
    module = '{"file":"a.py","module_vars":["counter","state.pose"],"source_sha256":"' + SHA \
        + '","vars":[]}'
    assert manifest_digest(file='a.py', class_name='A', vars=('x',), source_sha256=SHA,
                           module_vars=('counter',)) == (
        'sha256:' + hashlib.sha256(both.encode()).hexdigest()
    )
    assert manifest_digest(file='a.py', class_name=None, vars=(), source_sha256=SHA,
                           module_vars=('counter', 'state.pose')) == (
        'sha256:' + hashlib.sha256(module.encode()).hexdigest()
    )


def test_module_vars_in_the_digest_and_the_file() -> None:
    digests = {
        manifest_digest(file='a.py', class_name=c, vars=v, source_sha256=SHA, module_vars=mv)
        for c, v, mv in [('A', ('x',), ()), ('A', ('x',), ('n',)), ('A', ('x',), ('m',)),
                         (None, (), ('n',)), (None, (), ('m',)), ('A', (), ('n',))]
    }
    assert len(digests) == 6
    module = ManifestEntry('a.py', None, (), SHA, 'sha256:1', module_vars=('n', 'state.x'))
    both = ManifestEntry('a.py', 'A', ('x',), SHA, 'sha256:2', 1.0, 'fast', ('n',))
    document = json.loads(render_manifest([both, module]))
    assert document['nodes'] == [
        {'file': 'a.py', 'vars': [], 'module_vars': ['n', 'state.x'], 'source_sha256': SHA,
         'manifest': 'sha256:1'},
        {'file': 'a.py', 'class': 'A', 'vars': ['x'], 'module_vars': ['n'],
         'source_sha256': SHA, 'manifest': 'sha256:2', 'checkpoint_interval': 1.0,
         'replay': 'fast'},
    ]


def test_freshness_rules_are_not_in_the_digest() -> None:
    # The same paths, plain and as mappings with and without rules: one digest, so that
    # adding or tuning a rule keeps the checkpoints already written.
    node = 'nodes:\n  - file: a.py\n    class: A\n'
    texts = [
        node + '    vars: [total, history]\n    module_vars: [counter]\n',
        node + '    vars: [total, {name: history}]\n    module_vars: [{name: counter}]\n',
        node + '    vars: [total, {name: history, max_age: 5}]\n'
        '    module_vars: [{name: counter, max_age: 30, on_stale: refuse}]\n',
        node + '    vars: [total, {name: history, max_age: 0.5, on_stale: keep}]\n'
        '    module_vars: [counter]\n',
    ]
    specs = [parse_keyvars(text, 'keyvars.yaml').nodes[0] for text in texts]
    assert len({spec.freshness for spec in specs}) == 3
    digests = {
        manifest_digest(file=s.file, class_name=s.class_name, vars=s.vars, source_sha256=SHA,
                        module_vars=s.module_vars)
        for s in specs
    }
    assert digests == {manifest_digest(file='a.py', class_name='A', vars=('total', 'history'),
                                       source_sha256=SHA, module_vars=('counter',))}
