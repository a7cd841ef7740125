"""Node shapes RORY refuses, found in the source before anything runs.

RORY logs one subscription per topic (a message's identity is per topic, and two readers of one
topic would log each message twice), and runs callbacks under its lock in the executor's
thread, which an ``async def`` callback would leave at its first ``await``. The runtime refuses
both when the node starts (``NodeRuntime.adopt_subscription``); this pass says so at
``rory-instrument`` time, with file:line:col, for what the source shows plainly:

* two ``create_subscription`` calls with the same literal topic in one node class (or among
  the module-level functions of a node written as functions);
* a ``create_subscription``, ``create_timer`` or ``create_service`` whose callback is an
  ``async def`` method of the class (``self.on_scan``) or an ``async def`` function of the
  module.

Factories are recognised by method name on whatever object they are called, as in
``checks.py``; a topic or callback the source computes is left to the runtime.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import libcst as cst
import libcst.matchers as m
from libcst.metadata import MetadataWrapper, PositionProvider

from rory_instrument.errors import SourceError

# Where each factory takes its topic (or service name) and its callback: (index, keyword).
TOPIC_ARGUMENT = {'create_subscription': (1, 'topic')}
CALLBACK_ARGUMENT = {
    'create_subscription': (2, 'callback'),
    'create_timer': (1, 'callback'),
    'create_service': (2, 'callback'),
}
FACTORY_CALL = m.Call(func=m.Attribute(attr=m.Name(
    m.MatchIfTrue(lambda name: name in CALLBACK_ARGUMENT))))
SELF_METHOD = m.Attribute(value=m.Name('self'), attr=m.Name())


@dataclass(frozen=True)
class _FactoryCall:
    scope: str | None  # the enclosing class's dotted name; None at module level
    factory: str
    topic: str | None  # a literal topic, if the source gives one
    callback: cst.BaseExpression | None
    line: int
    col: int


def _argument(call: cst.Call, index: int, keyword: str) -> cst.BaseExpression | None:
    for arg in call.args:
        if arg.keyword is not None and arg.keyword.value == keyword:
            return arg.value
    positional = [arg for arg in call.args if arg.keyword is None and not arg.star]
    return positional[index].value if index < len(positional) else None


class _Collector(cst.CSTVisitor):
    METADATA_DEPENDENCIES = (PositionProvider,)

    def __init__(self) -> None:
        super().__init__()
        self._classes: list[str] = []
        self.calls: list[_FactoryCall] = []
        # async def methods per class dotted name ('' for module-level functions)
        self.async_defs: dict[str, set[str]] = {}

    def visit_ClassDef(self, node: cst.ClassDef) -> None:
        self._classes.append(node.name.value)

    def leave_ClassDef(self, original_node: cst.ClassDef) -> None:
        self._classes.pop()

    def visit_FunctionDef(self, node: cst.FunctionDef) -> None:
        if node.asynchronous is not None:
            self.async_defs.setdefault('.'.join(self._classes), set()).add(node.name.value)

    def visit_Call(self, node: cst.Call) -> None:
        if not m.matches(node, FACTORY_CALL):
            return
        factory = cst.ensure_type(node.func, cst.Attribute).attr.value
        topic_expr = (_argument(node, *TOPIC_ARGUMENT[factory])
                      if factory in TOPIC_ARGUMENT else None)
        topic = None
        if isinstance(topic_expr, cst.SimpleString):
            value = topic_expr.evaluated_value
            topic = value if isinstance(value, str) else None
        start = self.get_metadata(PositionProvider, node).start
        self.calls.append(_FactoryCall(
            '.'.join(self._classes) or None, factory, topic,
            _argument(node, *CALLBACK_ARGUMENT[factory]), start.line, start.column + 1))


def check_entities(wrapper: MetadataWrapper, display: str, scopes: Sequence[str | None]) -> None:
    """Raise the first refused shape in the node classes ``scopes`` (None: module functions).

    Raises:
        SourceError: Two subscriptions to one literal topic, or an async callback.
    """
    collector = _Collector()
    wrapper.visit(collector)
    for scope in dict.fromkeys(scopes):
        first_at: dict[str, int] = {}
        for call in (c for c in collector.calls if c.scope == scope):
            _check_callback(call, collector.async_defs, display)
            if call.topic is None:
                continue
            if call.topic in first_at:
                raise SourceError(
                    display, call.line, call.col,
                    f'second subscription to {call.topic} (the first is at line '
                    f'{first_at[call.topic]}): RORY logs one subscription per topic; subscribe '
                    'once and call both handlers from its callback')
            first_at[call.topic] = call.line


def _check_callback(call: _FactoryCall, async_defs: dict[str, set[str]], display: str) -> None:
    callback = call.callback
    name = None
    if call.scope is not None and callback is not None and m.matches(callback, SELF_METHOD):
        method = cst.ensure_type(callback, cst.Attribute).attr.value
        if method in async_defs.get(call.scope, set()):
            name = f'self.{method}'
    elif isinstance(callback, cst.Name) and callback.value in async_defs.get('', set()):
        name = callback.value
    if name is not None:
        what = call.factory.removeprefix('create_')
        raise SourceError(
            display, call.line, call.col,
            f'{name} is an async def callback (of a {what}): RORY runs callbacks under its '
            'lock on the executor thread and does not support async ones yet; make it a plain '
            'def')
