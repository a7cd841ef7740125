"""File-system helpers shared by the checkpoint store, the message log and the supervisor."""

from __future__ import annotations

import os
from contextlib import suppress
from pathlib import Path


def make_private_dir(path: Path) -> None:
    """Create ``path`` and its missing parents with mode 0700, whatever the umask.

    Checkpoints and logs hold a robot's state and everything it heard; no one else reads them.
    """
    missing: list[Path] = []
    current = path
    while not current.exists():
        missing.append(current)
        current = current.parent
    for directory in reversed(missing):
        with suppress(FileExistsError):
            directory.mkdir(mode=0o700)
            os.chmod(directory, 0o700)


def fsync_dir(path: Path) -> None:
    """Make a rename or unlink in ``path`` durable."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
