"""Whether the previous supervisor run on a store ended cleanly, and who owns the store now.

A supervisor holds an exclusive ``flock`` on ``<store>/supervisor.lock`` for its whole life:
the kernel drops it when the process dies, however it dies, so a second supervisor on the same
store is refused while the first lives and admitted the moment it is gone. Next to it,
``<store>/supervisor.json`` says which run wrote it and whether that run stopped cleanly. A run
that did not (SIGKILL, power loss, OOM killer) left checkpoints and message logs that describe
nodes nobody stopped: the next run resumes them from the store instead of starting them empty.
"""

from __future__ import annotations

import fcntl
import itertools
import json
import os
import shutil
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from ..errors import RoryError
from ..fsutil import make_private_dir

LOCK_NAME = 'supervisor.lock'
MARKER_NAME = 'supervisor.json'


class StoreInUseError(RoryError):
    """Another supervisor is running on this store."""


@dataclass(frozen=True)
class PreviousRun:
    """What the marker says about the run before this one."""

    pid: int
    started: float  # time.time()
    clean: bool
    stopped: float | None


class RunMarker:
    """This run's claim on a store.

    Args:
        store: The store folder (created 0700 if missing).
    """

    def __init__(self, store: Path) -> None:
        self.store = store
        make_private_dir(store)
        self._marker = store / MARKER_NAME
        self._fd: int | None = None
        self._started = 0.0
        self.previous: PreviousRun | None = None

    def acquire(self) -> PreviousRun | None:
        """Lock the store and record this run; what the previous marker said (None: no run).

        Raises:
            StoreInUseError: another live supervisor holds the store.
        """
        fd = os.open(self.store / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = os.pread(fd, 32, 0).decode(errors='replace').strip() or '?'
            os.close(fd)
            msg = f'{self.store}: in use by another supervisor (pid {owner})'
            raise StoreInUseError(msg) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f'{os.getpid()}\n'.encode(), 0)
        self._fd = fd
        self.previous = self._read()
        self._started = time.time()
        self._write({'pid': os.getpid(), 'started': self._started, 'clean': False})
        return self.previous

    def mark_clean(self) -> None:
        """This run stopped its nodes itself: nothing to resume next time."""
        record = {'pid': os.getpid(), 'started': self._started, 'clean': True,
                  'stopped': time.time()}
        self._write(record)

    def release(self) -> None:
        """Drop the lock (also dropped by the kernel if this process dies)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def _read(self) -> PreviousRun | None:
        try:
            doc = json.loads(self._marker.read_text(encoding='utf-8'))
            return PreviousRun(int(doc['pid']), float(doc['started']), bool(doc['clean']),
                               None if doc.get('stopped') is None else float(doc['stopped']))
        except FileNotFoundError:
            return None
        except (OSError, ValueError, KeyError, TypeError):
            # Unreadable: a run wrote it and was cut short writing it; treat as unclean.
            return PreviousRun(0, 0.0, False, None)

    def _write(self, record: Mapping[str, object]) -> None:
        tmp = self._marker.with_suffix('.tmp')
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, 'w', encoding='utf-8') as f:
            json.dump(record, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self._marker)


def make_room_for_previous(store: Path, keep: int) -> list[Path]:
    """Before a fresh run sets the current one aside in ``.previous``: move each earlier run
    one place older (``.previous`` to ``.previous.1``, ...), dropping what would be older
    than ``keep`` runs in all.

    Returns:
        The folders that hold earlier runs now, newest first (empty: there was none).
    """
    previous = store / '.previous'
    if not previous.exists():
        return []
    chain = [previous, *(store / f'.previous.{i}' for i in range(1, keep))]
    for stale in (chain[-1], store / f'.previous.{keep}'):
        if stale.exists():  # the oldest kept is pushed out
            shutil.rmtree(stale)
    for newer, older in reversed(list(itertools.pairwise(chain))):
        if newer.exists():
            newer.rename(older)
    return [folder for folder in chain[1:] if folder.exists()]
