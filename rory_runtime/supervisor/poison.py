"""Poison messages: a message that kills the node again when it is replayed.

Without this, recovery would replay the message that crashed the node, crash again, and loop
until the restart policy gives up. After each crash the supervisor reads the node's in-flight
slot (see ``inflight.py``): the message the node died applying is a suspect. If the next
process dies applying the same message, it is poison: it is written to
``<store>/<node>/quarantine/`` (topic, type, times, the CDR bytes for a developer to reproduce
the crash), and every later process of the node is told to skip it. So a poison message is
found within three crashes: the live one, the replay that confirms it, then a recovery that
goes past it.
"""

from __future__ import annotations

import base64
import json
import logging
import re
import shutil
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import LogError
from ..fsutil import make_private_dir
from ..inflight import InFlight, read_slot, slot_path
from ..log import LogEntry, SegmentStore
from ..protocol import MessageId
from ..store import CheckpointStore
from .ports import EventSink
from .states import LOG_PREFIX

_logger = logging.getLogger('rory.supervisor')

Key = tuple[str, MessageId]

# Next to each quarantine record, a folder with the checkpoint the node restored from when it
# died on the message twice, and the log segments after its cut (rory bundle takes them).
EVIDENCE_SUFFIX = '.before'


@dataclass(frozen=True)
class Quarantined:
    """One message set aside."""

    topic: str
    ident: MessageId
    path: Path

    def to_json(self) -> dict[str, Any]:
        """For the ``recovered`` event: the message and its quarantine record."""
        return {'topic': self.topic, 'source_ns': self.ident[0], 'seq': self.ident[1],
                'path': str(self.path)}


def died_on_json(inflight: InFlight) -> dict[str, Any]:
    """For the ``recovered`` event: the message a process died applying, and that process."""
    return {'incarnation': inflight.incarnation, 'topic': inflight.topic,
            'source_ns': inflight.ident[0], 'seq': inflight.ident[1]}


class PoisonGuard:
    """Suspects, confirmed poison messages and their quarantine for one node."""

    def __init__(self, store: Path, node_id: str, segments: SegmentStore) -> None:
        self.node_id = node_id
        self._store = store
        self.dir = store / node_id / 'quarantine'
        self._slot = slot_path(store, node_id)
        self._segments = segments
        self._suspect: Key | None = None
        self.keys: set[Key] = set(self._load())

    def _load(self) -> Iterable[Key]:
        if not self.dir.is_dir():
            return []
        keys = []
        for path in sorted(self.dir.glob('*.json')):
            try:
                record = json.loads(path.read_text())
                keys.append((str(record['topic']), (int(record['source_ns']), int(record['seq']))))
            except (OSError, ValueError, KeyError, TypeError) as err:
                _logger.warning('%s %s: unreadable quarantine record %s: %s', LOG_PREFIX,
                                self.node_id, path, err)
        return keys

    def died_on(self, incarnation: int) -> InFlight | None:
        """The message the given process was applying when it died, if any."""
        inflight = read_slot(self._slot)
        if inflight is None or inflight.incarnation != incarnation:
            return None
        return inflight

    def judge(self, incarnation: int, recent: Iterable[LogEntry],
              events: EventSink) -> tuple[InFlight | None, Quarantined | None]:
        """Did the process die applying a message - the same one as last time (poison)? That
        message, and its quarantine if it was (the ``quarantined`` or ``died_on`` event)."""
        suspect = self.died_on(incarnation)
        quarantined = self.on_crash(incarnation, recent)
        if quarantined is not None:
            events.write(
                'quarantined', self.node_id, topic=quarantined.topic,
                source_ns=quarantined.ident[0], seq=quarantined.ident[1],
                path=str(quarantined.path),
            )
        elif suspect is not None:
            events.write(
                'died_on', self.node_id, topic=suspect.topic, source_ns=suspect.ident[0],
                seq=suspect.ident[1], incarnation=incarnation,
            )
        return suspect, quarantined

    def on_crash(self, incarnation: int, recent: Iterable[LogEntry] = ()) -> Quarantined | None:
        """Judge a crash; quarantine the message if it killed the node twice in a row.

        Args:
            incarnation: The process that died.
            recent: Messages not yet in a sealed segment (the recovery log) to search too.
        """
        inflight = self.died_on(incarnation)
        if inflight is None:
            self._suspect = None
            return None
        key = (inflight.topic, inflight.ident)
        if key != self._suspect:
            self._suspect = key
            return None
        self._suspect = None
        return self._quarantine(inflight, recent)

    def _quarantine(self, inflight: InFlight, recent: Iterable[LogEntry]) -> Quarantined:
        entry = self._find(inflight, recent)
        make_private_dir(self.dir)
        name = re.sub(r'[^A-Za-z0-9_]+', '_', inflight.topic).strip('_') or 'topic'
        path = self.dir / f'{name}-{inflight.ident[0]}-{inflight.ident[1]}.json'
        record = {
            'node': self.node_id,
            'topic': inflight.topic,
            'type': entry.msgtype if entry else None,
            'source_ns': inflight.ident[0],
            'seq': inflight.ident[1],
            'recv_ns': inflight.recv_ns,
            'quarantined_ns': time.time_ns(),
            'reason': 'the node died applying this message twice in a row',
            'cdr_base64': base64.b64encode(entry.data).decode() if entry else None,
        }
        tmp = path.with_suffix('.tmp')
        tmp.write_text(json.dumps(record, indent=2) + '\n')
        tmp.chmod(0o600)
        tmp.replace(path)
        self._keep_evidence(path.with_suffix(EVIDENCE_SUFFIX))
        key = (inflight.topic, inflight.ident)
        self.keys.add(key)
        _logger.error(
            '%s %s: poison message on %s (source stamp %d, seq %d) killed it twice; '
            'quarantined to %s and skipped from now on', LOG_PREFIX, self.node_id,
            inflight.topic, inflight.ident[0], inflight.ident[1], path,
        )
        return Quarantined(inflight.topic, inflight.ident, path)

    def _keep_evidence(self, folder: Path) -> None:
        """Copy what the node restores from now (the checkpoint before the message: the node
        never got past it) and the segments after its cut, so that `rory bundle` can take
        the crash home after later checkpoints have gone past the message."""
        checkpoints = CheckpointStore(self._store, self.node_id)
        ckpt = checkpoints.latest_valid()
        if ckpt is None:
            return
        try:
            make_private_dir(folder / 'checkpoints')
            shutil.copy2(checkpoints.path(ckpt.seq), folder / 'checkpoints')
            for n in self._segments.numbers():
                if ckpt.cut is None or n > ckpt.cut:
                    shutil.copytree(self._segments.path(n), folder / 'log' / f'{n:010d}')
        except OSError as err:
            _logger.warning('%s %s: could not keep the checkpoint before the poison message in '
                            '%s: %s', LOG_PREFIX, self.node_id, folder, err)

    def _find(self, inflight: InFlight, recent: Iterable[LogEntry]) -> LogEntry | None:
        # The node logs a message before applying it, so it is in its log or in R.
        for entry in recent:
            if entry.topic == inflight.topic and entry.ident == inflight.ident:
                return entry
        try:
            for entry in self._segments.read_after(None):
                if entry.topic == inflight.topic and entry.ident == inflight.ident:
                    return entry
        except LogError as err:
            _logger.warning('%s %s: searching the log for the poison message: %s', LOG_PREFIX,
                            self.node_id, err)
        return None

    def env_value(self) -> str:
        """The quarantined messages, for the node's environment (JSON)."""
        return json.dumps([[topic, ident[0], ident[1]] for topic, ident in sorted(self.keys)])
