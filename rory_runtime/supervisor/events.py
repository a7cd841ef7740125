"""What the supervisor records: ``<store>/events.jsonl`` (:class:`EventLog`), and its log on
``/rosout`` (:class:`RosoutHandler`)."""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from ..fsutil import make_private_dir
from ..protocol import StatusMessage


def status_fields(message: StatusMessage) -> dict[str, Any]:
    """What a node's status carries but its kind and node, as it travelled: the fields of the
    ``hello`` and ``checkpoint`` events."""
    return {k: v for k, v in message.to_json().items() if k not in ('kind', 'node')}


class RosoutHandler(logging.Handler):
    """Forwards RORY's log records to an rclpy logger, so they reach /rosout and ROS's log
    files with the supervisor's node name, as every other node's log does."""

    def __init__(self, ros_logger: Any) -> None:
        super().__init__()
        self._ros = ros_logger

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = record.getMessage()
            if record.levelno >= logging.ERROR:
                self._ros.error(text)
            elif record.levelno >= logging.WARNING:
                self._ros.warning(text)
            elif record.levelno >= logging.INFO:
                self._ros.info(text)
            else:
                self._ros.debug(text)
        except Exception:  # logging must never take the supervisor down
            self.handleError(record)


class EventLog:
    """Machine-readable record of what happened: ``<store>/events.jsonl``."""

    def __init__(self, path: Path) -> None:
        make_private_dir(path.parent)
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
        self._file: TextIO = os.fdopen(fd, 'a', encoding='utf-8')
        self._lock = threading.Lock()
        self.listeners: list[Callable[[dict[str, Any]], None]] = []  # e.g. /rory/events

    def write(self, kind: str, node: str, **fields: Any) -> None:
        """Append one event."""
        record = {'t': time.time(), 'kind': kind, 'node': node, **fields}
        with self._lock:
            self._file.write(json.dumps(record, sort_keys=True) + '\n')
            self._file.flush()
        for listener in self.listeners:
            listener(record)

    def close(self) -> None:
        """Close the file."""
        with self._lock:
            self._file.close()
