"""Errors raised by the instrumenter; each names the file, line and column it is about."""

from __future__ import annotations


class InstrumentError(Exception):
    """A problem in the input that stops instrumentation; nothing is written.

    Args:
        path: File the problem is in (keyvars.yaml or a node source file).
        line: 1-based line, or 0 when unknown.
        col: 1-based column, or 0 when unknown.
        message: What is wrong, naming the offending name.
    """

    def __init__(self, path: str, line: int, col: int, message: str) -> None:
        self.path = path
        self.line = line
        self.col = col
        self.message = message
        super().__init__(str(self))

    def __str__(self) -> str:
        return f'{self.path}:{self.line}:{self.col}: {self.message}'


class ConfigError(InstrumentError):
    """keyvars.yaml is malformed or names something that does not exist."""


class SourceError(InstrumentError):
    """A node source file does not contain what keyvars.yaml says it does."""


class PathError(InstrumentError):
    """SRC or OUT cannot be used: missing, not a directory, or overlapping each other."""
