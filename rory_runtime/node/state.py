"""Which variables make up a node's state, and how to read and restore them.

A key variable is a dotted path: on the node object (``total``, ``ekf.P``, ``pid.accu_e``) or
in the node's module globals (``counter``, ``state.pose``) for nodes written as functions.
Restoring a path sets its last segment on the object the rest of the path leads to, so
``ekf.P`` replaces the filter's covariance inside the restored node's own ``ekf`` object.

In a checkpoint, node paths are stored under their path and module paths under
``global:<path>`` (a colon cannot occur in an identifier, so the two never clash).
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..errors import CodecError
from ..freshness import Rule

GLOBAL_PREFIX = 'global:'


@dataclass(frozen=True)
class CheckpointSpec:
    """What ``rory-instrument`` wrote into the decorator or the module call."""

    vars: tuple[str, ...]
    manifest: str
    module_vars: tuple[str, ...] = ()
    module: str | None = None  # whose globals module_vars name
    checkpoint_interval: float | None = None
    replay: str | None = None
    freshness: tuple[Rule, ...] = ()  # keyvars.yaml's max_age / on_stale per variable

    def keys(self) -> tuple[str, ...]:
        """The names this node's checkpoints store its variables under."""
        return (*self.vars, *(GLOBAL_PREFIX + path for path in self.module_vars))


class _Globals:
    """A module's globals, addressed like an object's attributes."""

    def __init__(self, module: str | None) -> None:
        if module is None or module not in sys.modules:
            raise CodecError(f'module {module!r} of the module variables is not loaded')
        self.namespace = vars(sys.modules[module])

    def get(self, name: str) -> Any:
        try:
            return self.namespace[name]
        except KeyError:
            raise AttributeError(name) from None

    def set(self, name: str, value: Any) -> None:
        self.namespace[name] = value


def _get(obj: Any, name: str) -> Any:
    return obj.get(name) if isinstance(obj, _Globals) else getattr(obj, name)


def _roots(spec: CheckpointSpec, node: object) -> list[tuple[str, str, Any]]:
    """(checkpoint key, path, root object) for every key variable."""
    roots: list[tuple[str, str, Any]] = [(path, path, node) for path in spec.vars]
    if spec.module_vars:
        module = _Globals(spec.module)
        roots += [(GLOBAL_PREFIX + path, path, module) for path in spec.module_vars]
    return roots


def read_state(spec: CheckpointSpec, node: object) -> dict[str, Any]:
    """The current value of every key variable, by checkpoint key.

    Raises:
        CodecError: A path does not lead to a value (named with the segment that is missing).
    """
    values: dict[str, Any] = {}
    for key, path, root in _roots(spec, node):
        obj = root
        walked: list[str] = []
        for segment in path.split('.'):
            walked.append(segment)
            try:
                obj = _get(obj, segment)
            except AttributeError:
                where = 'module variable' if key.startswith(GLOBAL_PREFIX) else 'variable'
                raise CodecError(
                    f'{where} {path!r} is not set: no {".".join(walked)!r}'
                ) from None
        values[key] = obj
    return values


def write_state(spec: CheckpointSpec, node: object, values: Mapping[str, Any],
                skip: frozenset[str] = frozenset()) -> None:
    """Put restored values back where they were read from; the keys in ``skip`` keep what
    the node has (a stale variable reset, freshness.py).

    Raises:
        CodecError: ``values`` does not hold exactly this node's keys, or a path's parent
            object does not exist in the restored node.
    """
    expected = set(spec.keys())
    if set(values) != expected:
        raise CodecError(
            f'holds variables {sorted(values)}, the node has {sorted(expected)}'
        )
    for key, path, root in _roots(spec, node):
        if key in skip:
            continue
        *parents, leaf = path.split('.')
        obj = root
        for segment in parents:
            try:
                obj = _get(obj, segment)
            except AttributeError:
                raise CodecError(
                    f'cannot restore {path!r}: the node has no {segment!r} to put it in'
                ) from None
        if isinstance(obj, _Globals):
            obj.set(leaf, values[key])
        else:
            setattr(obj, leaf, values[key])
