"""Exceptions of rory_runtime; low-level failures are turned into these at the boundary."""

from __future__ import annotations

from pathlib import Path


class RoryError(Exception):
    """Base class of every error rory_runtime raises on purpose."""


class CodecError(RoryError):
    """A value cannot be encoded as checkpoint data, or bytes do not decode to one."""


class CheckpointError(RoryError):
    """A checkpoint file is refused: unreadable, truncated, corrupt or from other code.

    Args:
        path: The checkpoint file.
        reason: Why it is refused.
    """

    def __init__(self, path: Path | str, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f'{self.path}: {reason}')


class LogError(RoryError):
    """A message log segment cannot be written or read.

    Args:
        path: The segment (bag directory or .mcap file).
        reason: What went wrong, naming the topic where one is involved.
    """

    def __init__(self, path: Path | str, reason: str) -> None:
        self.path = Path(path)
        self.reason = reason
        super().__init__(f'{self.path}: {reason}')


class ConfigError(RoryError):
    """The supervisor configuration is invalid.

    Args:
        path: The configuration file.
        field: Dotted path of the offending field, e.g. ``nodes[0].method``.
        reason: What is wrong with it.
        at: Line and column (1-based) where the file stops being YAML; then the message is
            ``file:line:col: reason``, as an editor jumps to.
    """

    def __init__(self, path: Path | str, field: str, reason: str,
                 at: tuple[int, int] | None = None) -> None:
        self.path = Path(path)
        self.field = field
        self.reason = reason
        where = f'{self.path}: {field}' if at is None else f'{self.path}:{at[0]}:{at[1]}'
        super().__init__(f'{where}: {reason}')


class ParameterError(RoryError):
    """A ROS parameter of the supervisor has a value its setting does not take.

    Args:
        node: The supervisor's node, fully qualified (``/robot1/rory_supervisor``).
        name: The parameter, e.g. ``amcl.method``.
        reason: What is wrong with it.
    """

    def __init__(self, node: str, name: str, reason: str) -> None:
        self.node = node
        self.name = name
        self.reason = reason
        super().__init__(f'parameter {name} of {node}: {reason}')


class ProtocolError(RoryError):
    """A control or replay message between runtime and supervisor is malformed."""
