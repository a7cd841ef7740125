"""Running a supervisor from a program: what ``rory supervise`` does, as one call.

A launch system, a test or an application embeds it with the configuration as the YAML
file's path, its content as a mapping, or a :class:`~.config.SupervisorConfig`::

    import rory_runtime

    code = rory_runtime.supervise({
        'nodes': [{'name': 'integrator', 'command': ['python', 'out/integrator.py']}],
        'store': '.rory',
    }, folder='tour')

It blocks until the supervisor stops (SIGINT or SIGTERM to the process, or every node ended)
and returns the exit code ``rory supervise`` would. It must run in the main thread (it
handles SIGINT and SIGTERM) of a process that has not called ``rclpy.init`` (nodes and the
warm standby are forks of a process made before it).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .config import SupervisorConfig, check_commands, load_config, parse_config

# ROS arguments that name a file: relative to where the supervisor is started, as the
# supervisor reads them, not to the config's folder, where its nodes run.
_FILE_ARGUMENTS = frozenset({'--params-file', '--log-config-file'})


def absolute_file_arguments(ros_args: Sequence[str]) -> tuple[str, ...]:
    """``ros_args`` with the file after each of :data:`_FILE_ARGUMENTS` made absolute."""
    out = list(ros_args)
    for i, arg in enumerate(out[:-1]):
        if arg in _FILE_ARGUMENTS:
            out[i + 1] = os.path.abspath(out[i + 1])
    return tuple(out)


def resolve_config(config: SupervisorConfig | Mapping[str, Any] | str | Path,
                   folder: str | Path | None = None) -> SupervisorConfig:
    """A configuration from a path, a mapping (``folder``: where its nodes run, default the
    current directory) or as it is.

    Raises:
        ConfigError: The file or mapping is invalid.
    """
    if isinstance(config, SupervisorConfig):
        return config
    if isinstance(config, str | Path):
        return load_config(config)
    where = Path(folder if folder is not None else '.').resolve()
    return parse_config(dict(config), where / '<mapping>', where)


def supervise(config: SupervisorConfig | Mapping[str, Any] | str | Path, *,
              ros_args: Sequence[str] = (), start: str = 'auto',
              folder: str | Path | None = None) -> int:
    """Check the configuration and what it names, then supervise until stopped.

    Args:
        config: The YAML file's path, its content as a mapping, or a parsed configuration.
        ros_args: ROS arguments for the supervisor and, appended to their commands, for every
            node (what follows ``--ros-args`` on the command line).
        start: ``'auto'``, ``'fresh'`` or ``'resume'`` (``--fresh``, ``--resume``).
        folder: For a mapping: where its nodes run and relative paths resolve.

    Returns:
        The exit code of ``rory supervise``: 0 after a clean stop.

    Raises:
        ConfigError: Anything :func:`~.config.check_commands` refuses, before anything
            starts; a store that cannot be used (:func:`~.config.check_store`, checked once
            ROS parameters have had their say), before any node starts.
    """
    from .supervisor import Supervisor

    if start not in ('auto', 'fresh', 'resume'):
        raise ValueError(f"start must be 'auto', 'fresh' or 'resume', got {start!r}")
    parsed = resolve_config(config, folder)
    check_commands(parsed)
    args = absolute_file_arguments(ros_args)
    if args:
        # Passed through to every node, after its own arguments (a second --ros-args section
        # is valid), as launch passes global arguments.
        parsed = dataclasses.replace(parsed, nodes=tuple(
            dataclasses.replace(node, command=(*node.command, '--ros-args', *args))
            for node in parsed.nodes))
    return Supervisor(parsed, start=start, ros_args=args).run()  # type: ignore[arg-type]
