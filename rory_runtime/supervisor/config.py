"""The supervisor's configuration file (``rory supervise CONFIG.yaml``).

Example::

    nodes:
      - name: integrator
        command: [python, out/integrator.py]   # run in this file's folder
        method: rory              # rory | restart | checkpoint | replay
        checkpoint_interval: 2.0  # seconds; default: keyvars.yaml's, else 2.0
        replay: fast              # fast | paced; default: keyvars.yaml's, else fast
        hang_timeout: 10.0        # s without a heartbeat: hung, killed, recovered (null: off)
        start_timeout: 60.0       # s from spawn to the first heartbeat (null: off)
        hello_timeout: 10.0       # s beating without its HELLO heard: replaced (a new process)
        warm_standby: true        # a started process waits to replace it (default: rory only)
        release_gate:             # after a recovery, hold S4 until /rory/<name>/release is called
          timeout: 60.0           # s; null: wait for the call however long
          on_timeout: give_up     # give_up (FATAL, the safe state held) | release
    safe_state:                   # held from S1 until S4, while any node recovers
      - topic: /e_stop            # relative (e_stop): in the supervisor's namespace
        type: std_msgs/msg/Bool
        hold: {data: true}
        release: {data: false}
        nodes: [integrator]       # only while one of these recovers (default: every node)
    store: .rory
    dds: fast_rediscovery         # fast_rediscovery (default) | inherit
    standbys: 3                   # warm standbys kept for the nodes that share an rclpy.init
                                  # (default: one per node with warm_standby, at most 3)
    spare_forks: true             # a fork held ready for each node beyond the standbys
    prefix_output: true           # node lines as "[name] ..." (default: with several nodes)

Every error names the file and the field (``nodes[0].method``).
"""

from __future__ import annotations

import importlib.metadata
import math
import os
import re
import shutil
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ..errors import ConfigError
from ..msgtypes import TYPE_NAME_RE
from ..protocol import NODE_ID_RE, Method, ReplayPace

# A ROS topic name, absolute or relative (no ~ or substitutions: the supervisor publishes it).
_TOPIC_RE = re.compile(r'/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*')
_PYTHON_NAMES = frozenset({'python', 'python3', 'python3.11'})

DEFAULT_MAX_STANDBYS = 3
"""The default pool's ceiling: three nodes struck together all start warm."""


@dataclass(frozen=True)
class Backoff:
    """Restart pacing for crash loops."""

    initial: float = 0.0  # delay before the first restart after a stable run
    step: float = 0.5  # delay before the second consecutive restart, doubled after
    maximum: float = 8.0
    stable_after: float = 10.0  # a start that runs this long resets the count
    max_restarts: int = 5  # consecutive crashes before giving up (FATAL)


GATE_OUTCOMES = ('give_up', 'release')


@dataclass(frozen=True)
class ReleaseGate:
    """S4 of a recovery waits for a ``std_srvs/Trigger`` call on ``/rory/<node>/release``
    (docs/architecture.md, "The release gate")."""

    timeout: float | None = None  # seconds from reaching the gate; None: no limit
    on_timeout: str = 'give_up'  # 'give_up' (FATAL, safe state held) or 'release'


@dataclass(frozen=True)
class NodeConfig:
    """One supervised node."""

    name: str
    command: tuple[str, ...]
    method: Method = Method.RORY
    # None: the node's own setting from keyvars.yaml (via rory-instrument), else the default
    checkpoint_interval: float | None = None
    replay: ReplayPace | None = None
    restart_on_clean_exit: bool = False
    env: Mapping[str, str] = field(default_factory=dict)
    backoff: Backoff = Backoff()
    # A node whose executor stops beating this long is hung: killed, then recovered.
    hang_timeout: float | None = 10.0
    # From spawn to the first beat (imports, rclpy.init, the node's constructor).
    start_timeout: float | None = 60.0
    # A process that beats this long without its HELLO reaching the supervisor cannot reach
    # it: killed and replaced (watchdog.py, Unheard).
    hello_timeout: float = 10.0
    # A fork of the zygote that has already joined DDS waits to become the node at its next
    # start (supervisor/standby.py): restart without the ~2 s of DDS discovery.
    warm_standby: bool = False
    # None: a recovered node is released as soon as it has caught up.
    release_gate: ReleaseGate | None = None


@dataclass(frozen=True)
class SafeAction:
    """A message published at S1 and held until S4, then a release message."""

    topic: str
    msgtype: str
    hold: Mapping[str, Any]
    release: Mapping[str, Any] | None
    rate: float | None  # republish the hold message at this rate (Hz); None: once, latched
    nodes: tuple[str, ...] | None = None  # held while one of these recovers; None: any node


@dataclass(frozen=True)
class SupervisorConfig:
    """The whole file."""

    path: Path
    folder: Path
    nodes: tuple[NodeConfig, ...]
    safe_state: tuple[SafeAction, ...]
    store: Path
    dds: str = 'fast_rediscovery'
    # Earlier runs a fresh start keeps in the store (.previous, .previous.1, ...).
    keep_runs: int = 3
    # Node output lines prefixed with ``[name] ``; None: when there is more than one node.
    prefix_output: bool | None = None
    # Warm standbys kept per rclpy.init signature (supervisor/standby.py); None: the default,
    # :attr:`standby_pool_size`.
    standbys: int | None = None
    # A spare fork for each node beyond the pool (supervisor/standby.py, StandbyPool): its
    # start after a crash takes no round trip to the zygote on the main loop.
    spare_forks: bool = True

    @property
    def standby_pool_size(self) -> int:
        """How many warm standbys each group of nodes that can share one keeps waiting.

        One bug often takes down every node that reads a message at once (issue 38): each
        node struck beyond the pool starts cold. By default one per node that wants a standby,
        at most :data:`DEFAULT_MAX_STANDBYS` (each costs memory and CPU at rest:
        docs/performance.md, "The standby pool").
        """
        if self.standbys is not None:
            return self.standbys
        wanting = sum(1 for node in self.nodes if node.warm_standby)
        return max(1, min(DEFAULT_MAX_STANDBYS, wanting))

    @property
    def prefixes_output(self) -> bool:
        """Whether node output lines get their node's name in front (supervisor/output.py)."""
        return self.prefix_output if self.prefix_output is not None else len(self.nodes) > 1


class _Fields:
    """Reads one mapping, remembering where it is for error messages."""

    def __init__(self, path: Path, where: str, obj: Any, allowed: set[str]) -> None:
        self.path = path
        self.where = where
        if not isinstance(obj, dict):
            raise ConfigError(path, where or '(top level)', 'must be a mapping')
        unknown = sorted(str(key) for key in set(obj) - allowed)
        if unknown:
            allowed_list = ', '.join(sorted(allowed))
            raise ConfigError(
                path, self._at(str(unknown[0])), f'unknown field; allowed: {allowed_list}'
            )
        self.obj: dict[str, Any] = obj

    def _at(self, key: str) -> str:
        return f'{self.where}.{key}' if self.where else key

    def error(self, key: str, reason: str) -> ConfigError:
        return ConfigError(self.path, self._at(key), reason)

    def required(self, key: str) -> Any:
        if key not in self.obj:
            raise self.error(key, 'is required')
        return self.obj[key]

    def number(
        self, key: str, default: float, *, minimum: float = 0.0, strict: bool = True
    ) -> float:
        value = self.obj.get(key, default)
        is_number = isinstance(value, int | float) and not isinstance(value, bool)
        if not is_number or not math.isfinite(value):
            raise self.error(key, f'must be a number, got {value!r}')
        if value < minimum or (strict and value == minimum):
            raise self.error(key, f'must be {">" if strict else ">="} {minimum}, got {value}')
        return float(value)

    def optional_number(self, key: str, default: float | None) -> float | None:
        """A positive number, or null for 'off'."""
        if key in self.obj and self.obj[key] is None:
            return None
        if key not in self.obj:
            return default
        return self.number(key, 0.0)

    def boolean(self, key: str, default: bool) -> bool:
        value = self.obj.get(key, default)
        if not isinstance(value, bool):
            raise self.error(key, f'must be true or false, got {value!r}')
        return value


def load_config(path: Path | str) -> SupervisorConfig:
    """Read and validate a supervisor configuration file.

    Raises:
        ConfigError: The file is unreadable, not YAML, or a field is invalid.
    """
    path = Path(path).resolve()
    try:
        text = path.read_text(encoding='utf-8')
    except OSError as err:
        raise ConfigError(path, '(file)', f'cannot read: {err.strerror}') from None
    except UnicodeDecodeError as err:
        raise ConfigError(path, '(file)', f'not UTF-8 text: {err.reason}') from None
    try:
        doc = yaml.safe_load(text)
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark
        problem = ' '.join(part for part in (err.problem, err.context and f'({err.context})')
                           if part)
        at = None if mark is None else (mark.line + 1, mark.column + 1)
        raise ConfigError(path, '(file)', f'not valid YAML: {problem or err}', at=at) from None
    except yaml.YAMLError as err:
        raise ConfigError(path, '(file)', f'not valid YAML: {err}') from None
    return parse_config(doc, path, path.parent)


def parse_config(doc: Any, path: Path, folder: Path) -> SupervisorConfig:
    """Validate a configuration already read (a YAML document, or a program's own mapping).

    Args:
        doc: The document: a mapping with ``nodes`` and the optional top-level keys.
        path: Names it in errors (the file, or a label for a mapping).
        folder: Where nodes run and relative paths (``store``, scripts) resolve.

    Raises:
        ConfigError: A field is invalid.
    """
    top = _Fields(path, '', doc, {'nodes', 'safe_state', 'store', 'dds', 'keep_runs', 'standbys',
                                  'spare_forks', 'prefix_output'})

    nodes_raw = top.required('nodes')
    if not isinstance(nodes_raw, list) or not nodes_raw:
        raise top.error('nodes', 'must be a non-empty list')
    nodes = tuple(_node(path, folder, f'nodes[{i}]', item) for i, item in enumerate(nodes_raw))
    seen: set[str] = set()
    for i, node in enumerate(nodes):
        if node.name in seen:
            raise ConfigError(path, f'nodes[{i}].name', f'duplicate node name {node.name!r}')
        seen.add(node.name)

    safe_raw = top.obj.get('safe_state') or []
    if not isinstance(safe_raw, list):
        raise top.error('safe_state', 'must be a list')
    safe = tuple(_safe_action(path, f'safe_state[{i}]', item) for i, item in enumerate(safe_raw))
    for i, action in enumerate(safe):
        for k, name in enumerate(action.nodes or ()):
            if name not in seen:
                raise ConfigError(path, f'safe_state[{i}].nodes[{k}]',
                                  f'no node is named {name!r}')

    store_raw = top.obj.get('store', '.rory')
    if not isinstance(store_raw, str) or not store_raw:
        raise top.error('store', 'must be a path')
    store = (folder / store_raw).resolve()
    dds = top.obj.get('dds', 'fast_rediscovery')
    if dds not in ('fast_rediscovery', 'inherit'):
        raise top.error('dds', f'must be fast_rediscovery or inherit, got {dds!r}')
    keep_runs = top.obj.get('keep_runs', SupervisorConfig.keep_runs)
    if isinstance(keep_runs, bool) or not isinstance(keep_runs, int) or keep_runs < 1:
        raise top.error('keep_runs', f'must be a positive integer, got {keep_runs!r}')
    prefix_output = top.obj.get('prefix_output')
    if prefix_output is not None and not isinstance(prefix_output, bool):
        raise top.error('prefix_output', f'must be true or false, got {prefix_output!r}')
    standbys = top.obj.get('standbys')
    if standbys is not None and (isinstance(standbys, bool) or not isinstance(standbys, int)
                                 or standbys < 1):
        raise top.error('standbys', f'must be a positive integer (warm_standby: false on a '
                                    f'node turns its standby off), got {standbys!r}')
    spare_forks = top.obj.get('spare_forks', True)
    if not isinstance(spare_forks, bool):
        raise top.error('spare_forks', f'must be true or false, got {spare_forks!r}')
    return SupervisorConfig(
        path=path, folder=folder, nodes=nodes, safe_state=safe, store=store, dds=dds,
        keep_runs=keep_runs, prefix_output=prefix_output, standbys=standbys,
        spare_forks=spare_forks,
    )


def check_commands(config: SupervisorConfig) -> None:
    """Before anything starts: every node's program exists where its command says.

    A command's first word is looked up on PATH (the node's own ``env`` PATH if it sets one),
    or, with a slash, relative to the config's folder, where nodes run; for ``python FILE``,
    FILE is. ``python -m MODULE`` is left to Python (finding a module would import its
    packages).

    Raises:
        ConfigError: One line naming the node, its command and what is missing.
    """
    for i, node in enumerate(config.nodes):
        where = f'nodes[{i}].command'
        program = node.command[0]
        if '/' in program:
            found = config.folder / program
            if not (found.is_file() and os.access(found, os.X_OK)):
                raise ConfigError(config.path, where, f'node {node.name}: {program} is not an '
                                  f'executable file (looked in {config.folder})')
        elif shutil.which(program, path=node.env.get('PATH', os.environ.get('PATH'))) is None:
            raise ConfigError(config.path, where, f'node {node.name}: {program} is not on PATH')
        script = node.command[1] if len(node.command) > 1 else '-'
        if program == sys.executable and not script.startswith('-') and not (
                config.folder / script).is_file():
            raise ConfigError(config.path, where, f'node {node.name}: {script}: no such file '
                              f'(looked in {config.folder}, where nodes run)')


def check_store(config: SupervisorConfig) -> None:
    """Before the store is claimed: it is a folder this process can write, or can be made in
    one. Nothing is created (a ROS parameter may still name another store).

    Raises:
        ConfigError: One line naming the store and why it cannot be used.
    """
    store = config.store
    probe = store
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise store_error(config, f'{probe} is not a folder')
    if not os.access(probe, os.W_OK | os.X_OK):
        raise store_error(config, f'{probe}: permission denied')


def store_error(config: SupervisorConfig, reason: str) -> ConfigError:
    """The one line saying the store cannot be used."""
    return ConfigError(config.path, 'store', f'{config.store}: cannot create or write: {reason}')


def _node(path: Path, folder: Path, where: str, obj: Any) -> NodeConfig:
    f = _Fields(
        path,
        where,
        obj,
        {
            'name', 'command', 'method', 'checkpoint_interval', 'replay',
            'restart_on_clean_exit', 'env', 'backoff', 'hang_timeout', 'start_timeout',
            'hello_timeout', 'warm_standby', 'release_gate',
        },
    )
    name = f.required('name')
    if not isinstance(name, str) or not NODE_ID_RE.fullmatch(name):
        raise f.error('name', f'must be a letter then letters, digits or _, got {name!r}')
    command = f.required('command')
    if isinstance(command, str):
        command = command.split()
    if not isinstance(command, list) or not command or not all(isinstance(a, str) for a in command):
        raise f.error('command', 'must be a non-empty list of strings')
    method = f.obj.get('method', Method.RORY.value)
    if not isinstance(method, str) or method not in {m.value for m in Method}:
        methods = ', '.join(m.value for m in Method)
        raise f.error('method', f'must be one of {methods}, got {method!r}')
    replay = f.obj.get('replay')
    if replay is not None and (
        not isinstance(replay, str) or replay not in {p.value for p in ReplayPace}
    ):
        raise f.error('replay', f'must be paced or fast, got {replay!r}')
    env = f.obj.get('env') or {}
    if not isinstance(env, dict) or not all(isinstance(k, str) for k in env):
        raise f.error('env', 'must be a mapping of names to values')
    return NodeConfig(
        name=name,
        command=_resolve_command(command),
        method=Method(method),
        checkpoint_interval=(
            None
            if f.obj.get('checkpoint_interval') is None
            else f.number('checkpoint_interval', 2.0)
        ),
        replay=None if replay is None else ReplayPace(replay),
        restart_on_clean_exit=f.boolean('restart_on_clean_exit', False),
        env={str(k): str(v) for k, v in env.items()},
        backoff=_backoff(path, f'{where}.backoff', f.obj.get('backoff') or {}),
        hang_timeout=f.optional_number('hang_timeout', NodeConfig.hang_timeout),
        start_timeout=f.optional_number('start_timeout', NodeConfig.start_timeout),
        hello_timeout=f.number('hello_timeout', NodeConfig.hello_timeout),
        # Default on for rory only: restart stands for ROS's respawn, and checkpoint and
        # replay for the paper's ablations, all cold starts.
        warm_standby=f.boolean('warm_standby', method == Method.RORY.value),
        release_gate=_release_gate(path, f'{where}.release_gate', f.obj.get('release_gate')),
    )


def _release_gate(path: Path, where: str, obj: Any) -> ReleaseGate | None:
    """``release_gate: {timeout: 60, on_timeout: release}``; ``true`` is a gate without a
    timeout; absent, ``false`` or null: none."""
    if obj is None or obj is False:
        return None
    if obj is True:
        return ReleaseGate()
    f = _Fields(path, where, obj, {'timeout', 'on_timeout'})
    on_timeout = f.obj.get('on_timeout', ReleaseGate.on_timeout)
    if on_timeout not in GATE_OUTCOMES:
        raise f.error('on_timeout', f'must be give_up or release, got {on_timeout!r}')
    timeout = f.optional_number('timeout', None)
    if timeout is None and 'on_timeout' in f.obj:
        raise f.error('on_timeout', 'needs a timeout (seconds) to apply')
    return ReleaseGate(timeout=timeout, on_timeout=on_timeout)


def _resolve_command(command: list[str]) -> tuple[str, ...]:
    # 'python' means the interpreter running the supervisor: it has rclpy and rory_runtime.
    # `[package, executable]`, as `ros2 run` takes them, is the package's console script.
    # Everything else is left as written; the node runs with the config file's folder as its
    # working directory, so relative paths resolve against that folder.
    if command[0] in _PYTHON_NAMES:
        return (sys.executable, *command[1:])
    if len(command) >= 2 and shutil.which(command[0]) is None:
        script = package_executable(command[0], command[1])
        if script is not None:
            return (script, *command[2:])
    return tuple(command)


def package_executable(package: str, executable: str) -> str | None:
    """The console script ``executable`` of the installed distribution ``package`` (as
    ``ros2 run package executable`` finds it), if this interpreter has it on PATH."""
    try:
        dist = importlib.metadata.distribution(package)
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return None
    if not any(ep.name == executable for ep in dist.entry_points
               if ep.group == 'console_scripts'):
        return None
    return shutil.which(executable)


def _backoff(path: Path, where: str, obj: Any) -> Backoff:
    f = _Fields(path, where, obj, {'initial', 'step', 'maximum', 'stable_after', 'max_restarts'})
    default = Backoff()
    max_restarts = f.obj.get('max_restarts', default.max_restarts)
    if isinstance(max_restarts, bool) or not isinstance(max_restarts, int) or max_restarts < 1:
        raise f.error('max_restarts', f'must be a positive integer, got {max_restarts!r}')
    return Backoff(
        initial=f.number('initial', default.initial, strict=False),
        step=f.number('step', default.step, strict=False),
        maximum=f.number('maximum', default.maximum, strict=False),
        stable_after=f.number('stable_after', default.stable_after),
        max_restarts=max_restarts,
    )


def _safe_action(path: Path, where: str, obj: Any) -> SafeAction:
    f = _Fields(path, where, obj, {'topic', 'type', 'hold', 'release', 'rate', 'nodes'})
    topic = f.required('topic')
    if not isinstance(topic, str) or not _TOPIC_RE.fullmatch(topic):
        raise f.error('topic', f'must be a topic name (/e_stop, or e_stop in the supervisor\'s '
                               f'namespace), got {topic!r}')
    msgtype = f.required('type')
    if not isinstance(msgtype, str) or not TYPE_NAME_RE.fullmatch(msgtype):
        raise f.error('type', f'must look like pkg/msg/Name, got {msgtype!r}')
    hold = f.required('hold')
    if not isinstance(hold, dict):
        raise f.error('hold', 'must be a mapping of message fields')
    release = f.obj.get('release')
    if release is not None and not isinstance(release, dict):
        raise f.error('release', 'must be a mapping of message fields')
    rate = None if f.obj.get('rate') is None else f.number('rate', 0.0)
    nodes = f.obj.get('nodes')
    if nodes is not None and (not isinstance(nodes, list) or not nodes
                              or not all(isinstance(n, str) for n in nodes)):
        raise f.error('nodes', f'must be a non-empty list of node names, got {nodes!r}')
    return SafeAction(topic=topic, msgtype=msgtype, hold=hold, release=release, rate=rate,
                      nodes=None if nodes is None else tuple(nodes))
