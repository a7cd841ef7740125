"""The supervisor's settings as ROS parameters of its node, ``/rory_supervisor``.

Every setting of the configuration file that a robot's operator may want to change per robot is
also a parameter: declared with the file's value, so ``ros2 param list/get/describe`` show what
is in force, and overridden the ROS way, from ``--ros-args`` or a parameters file::

    rory supervise stack.yaml --ros-args -r __ns:=/robot1 \\
        -p rory_supervisor:store:=/var/rory/robot1 -p rory_supervisor:amcl.method:=restart

    rory supervise stack.yaml --ros-args --params-file robot1.yaml

    # robot1.yaml
    rory_supervisor:
      ros__parameters:
        store: /var/rory/robot1
        amcl: {checkpoint_interval: 1.0, replay: fast}

``rory supervise`` appends its ROS arguments to every node's command, so an override meant for
the supervisor is best scoped to it (``rory_supervisor:`` as above, or its key in a parameters
file); a plain ``-p store:=...`` would also be offered to every node. rcl itself matches
``-p rory_supervisor:...`` only in the root namespace; the supervisor takes it in any namespace
(:func:`own_ros_args`). In a parameters file, name it ``/**/rory_supervisor`` or with its
namespace (``/robot1/rory_supervisor``), as for any ROS node.

The parameters are read once at start and are read-only: they decide how a node is run and
recovered, and changing them under a running node would leave it run one way and recovered
another. ``dds`` stays in the file only: it must be in force before this process joins DDS,
before parameters exist.

Parameters (``<node>`` is a node's ``name`` in the file):

=============================== ====== =======================================================
``store``                       string the store's folder (relative: to the working directory)
``<node>.method``               string rory, restart, checkpoint or replay
``<node>.checkpoint_interval``  double seconds (unset: the node's keyvars.yaml, else 2.0)
``<node>.replay``               string paced or fast (unset: the node's keyvars.yaml, else paced)
``<node>.hang_timeout``         double seconds without a heartbeat before it is hung; 0: off
``<node>.start_timeout``        double seconds from spawn to the first heartbeat; 0: off
``<node>.warm_standby``         bool   a started process waits to replace it
``<node>.restart_on_clean_exit`` bool  exit status 0 is restarted too
``<node>.max_restarts``         int    consecutive crashes before giving up
=============================== ====== =======================================================
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node

from ..errors import ParameterError
from ..protocol import Method, ReplayPace
from .config import NodeConfig, SupervisorConfig
from .states import LOG_PREFIX

_logger = logging.getLogger('rory.supervisor')

NODE_NAME = 'rory_supervisor'
_METHODS = tuple(m.value for m in Method)
_PACES = tuple(p.value for p in ReplayPace)


@dataclass(frozen=True)
class _Setting:
    """One per-node parameter: how to read it from a NodeConfig and write it back."""

    name: str
    description: str
    get: Callable[[NodeConfig], Any]  # the file's value, as a parameter value (None: unset)
    parse: Callable[[Any], Any]  # a parameter value -> the NodeConfig field's value (or raises)
    set: Callable[[NodeConfig, Any], NodeConfig]


def _choice(options: tuple[str, ...]) -> Callable[[Any], str]:
    def parse(value: Any) -> str:
        if not isinstance(value, str) or value not in options:
            raise ValueError(f'must be one of {", ".join(options)}, got {value!r}')
        return value

    return parse


def _positive(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f'must be a number, got {value!r}')
    if value <= 0:
        raise ValueError(f'must be > 0, got {value}')
    return float(value)


def _timeout(value: Any) -> float | None:
    # A parameter cannot be null as the file's field can: 0 means off.
    if isinstance(value, int | float) and not isinstance(value, bool) and value == 0:
        return None
    return _positive(value)


def _boolean(value: Any) -> bool:
    if not isinstance(value, bool):
        raise ValueError(f'must be true or false, got {value!r}')
    return value


def _count(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f'must be a positive integer, got {value!r}')
    return value


def _replace(field: str) -> Callable[[NodeConfig, Any], NodeConfig]:
    return lambda cfg, value: dataclasses.replace(cfg, **{field: value})


NODE_SETTINGS: tuple[_Setting, ...] = (
    _Setting('method', 'how a crash is recovered: ' + ', '.join(_METHODS),
             lambda c: c.method.value, _choice(_METHODS),
             lambda c, v: dataclasses.replace(c, method=Method(v))),
    _Setting('checkpoint_interval', 'seconds between checkpoints (unset: keyvars.yaml, else 2)',
             lambda c: c.checkpoint_interval, _positive, _replace('checkpoint_interval')),
    _Setting('replay', 'replay pace after a restore: ' + ', '.join(_PACES)
             + ' (unset: keyvars.yaml, else paced)',
             lambda c: None if c.replay is None else c.replay.value, _choice(_PACES),
             lambda c, v: dataclasses.replace(c, replay=ReplayPace(v))),
    _Setting('hang_timeout', 'seconds without a heartbeat before the node is hung; 0: off',
             lambda c: c.hang_timeout or 0.0, _timeout, _replace('hang_timeout')),
    _Setting('start_timeout', 'seconds from spawn to the first heartbeat; 0: off',
             lambda c: c.start_timeout or 0.0, _timeout, _replace('start_timeout')),
    _Setting('warm_standby', 'a started process waits to replace the node',
             lambda c: c.warm_standby, _boolean, _replace('warm_standby')),
    _Setting('restart_on_clean_exit', 'exit status 0 is restarted too',
             lambda c: c.restart_on_clean_exit, _boolean, _replace('restart_on_clean_exit')),
    _Setting('max_restarts', 'consecutive crashes before giving up',
             lambda c: c.backoff.max_restarts, _count,
             lambda c, v: dataclasses.replace(
                 c, backoff=dataclasses.replace(c.backoff, max_restarts=v))),
)


def own_ros_args(ros_args: Sequence[str]) -> list[str]:
    """The supervisor's own ROS arguments: ``-p rory_supervisor:NAME:=VALUE`` made unscoped.

    rcl matches a node-scoped ``-p`` against the bare node name only in the root namespace, so
    under ``-r __ns:=/robot1`` it would be dropped without a word. The nodes get the arguments
    as given, where the scope keeps the override away from them.
    """
    own = list(ros_args)
    prefix = f'{NODE_NAME}:'
    for i in range(1, len(own)):
        if own[i - 1] in ('-p', '--param') and own[i].startswith(prefix):
            own[i] = own[i].removeprefix(prefix)
    return own


def _descriptor(description: str) -> ParameterDescriptor:
    # Dynamic typing: `-p x.checkpoint_interval:=1` arrives as an integer and an unset value
    # as NOT_SET; the values are checked here, with errors that name the parameter.
    return ParameterDescriptor(description=description, read_only=True, dynamic_typing=True)


def apply_parameters(node: Node, config: SupervisorConfig) -> SupervisorConfig:
    """Declare the settings on the supervisor's node; the config with any overrides applied.

    Raises:
        ParameterError: An override has a value the setting does not take.
    """
    name = node.get_fully_qualified_name()
    store_value = _declare(node, 'store', str(config.store), 'the store folder')
    store = config.store
    if store_value != str(config.store):
        if not isinstance(store_value, str) or not store_value:
            raise ParameterError(name, 'store', f'must be a path, got {store_value!r}')
        store = Path(store_value).resolve()
        _logger.info('%s store %s (parameter)', LOG_PREFIX, store)
    nodes = []
    for cfg in config.nodes:
        for setting in NODE_SETTINGS:
            param = f'{cfg.name}.{setting.name}'
            default = setting.get(cfg)
            value = _declare(node, param, default, setting.description)
            if value == default and type(value) is type(default):  # 1 == True, 2 == 2.0
                continue
            try:
                parsed = setting.parse(value)
            except ValueError as err:
                raise ParameterError(name, param, str(err)) from None
            cfg = setting.set(cfg, parsed)
            _logger.info('%s %s: %s = %r (parameter)', LOG_PREFIX, cfg.name, setting.name, value)
        nodes.append(cfg)
    _refuse_unknown(node, config)
    return dataclasses.replace(config, store=store, nodes=tuple(nodes))


def _declare(node: Node, name: str, default: Any, description: str) -> Any:
    return node.declare_parameter(name, default, _descriptor(description)).value


def _refuse_unknown(node: Node, config: SupervisorConfig) -> None:
    # A misspelt setting (`amcl.methd`) would otherwise be ignored without a word, as an
    # unknown field of the file is refused. Overrides for other nodes (`/**` in a parameters
    # file, global -p) reach this node too, so only names under a supervised node's prefix can
    # be known to be wrong.
    known = {f'{c.name}.{s.name}' for c in config.nodes for s in NODE_SETTINGS}
    prefixes = tuple(f'{c.name}.' for c in config.nodes)
    overrides: dict[str, Any] = getattr(node, '_parameter_overrides', {})
    for param in sorted(overrides):
        if param.startswith(prefixes) and param not in known:
            settings = ', '.join(s.name for s in NODE_SETTINGS)
            raise ParameterError(node.get_fully_qualified_name(), param,
                                 f'unknown setting; known: {settings}')
