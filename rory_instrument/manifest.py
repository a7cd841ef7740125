"""The manifest: which code a checkpoint belongs to, as a digest and as OUT/rory_manifest.json.

The digest covers the file, the class, its vars and the hash of the module's source with
RORY's additions removed. A checkpoint written by one build is therefore recognised as
foreign by a build of different code or a different var list, while re-instrumenting an
output (which strips to the same source) yields the same digest.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

MANIFEST_NAME = 'rory_manifest.json'
MANIFEST_FORMAT = 1
DIGEST_PREFIX = 'sha256:'


def canonical_json(value: object) -> bytes:
    """Encodes a JSON value one way only: sorted keys, no spaces, ASCII, UTF-8."""
    text = json.dumps(value, sort_keys=True, separators=(',', ':'), ensure_ascii=True,
                      allow_nan=False)
    return text.encode('utf-8')


def manifest_digest(
    *, file: str, class_name: str, vars: Sequence[str], source_sha256: str
) -> str:
    """Returns ``sha256:<hex>`` over the canonical JSON of what identifies a node build.

    Args:
        file: Source path relative to SRC, POSIX separators.
        class_name: Dotted class name.
        vars: Checkpointed attribute names, in keyvars.yaml order.
        source_sha256: Hex SHA-256 of the module source with RORY's additions removed.

    Returns:
        The digest, as written into the decorator and the manifest file.
    """
    payload = {'file': file, 'class': class_name, 'vars': list(vars),
               'source_sha256': source_sha256}
    return DIGEST_PREFIX + hashlib.sha256(canonical_json(payload)).hexdigest()


@dataclass(frozen=True)
class ManifestEntry:
    """One instrumented class, as listed in rory_manifest.json.

    Attributes:
        file: Source path relative to OUT, POSIX separators.
        class_name: Dotted class name.
        vars: Checkpointed attribute names.
        source_sha256: Hex SHA-256 of the module source with RORY's additions removed.
        manifest: The digest in the class's decorator.
        checkpoint_interval: Seconds between checkpoints, if keyvars.yaml set it.
        replay: ``'paced'`` or ``'fast'``, if keyvars.yaml set it.
    """

    file: str
    class_name: str
    vars: tuple[str, ...]
    source_sha256: str
    manifest: str
    checkpoint_interval: float | None = None
    replay: str | None = None

    def to_json(self) -> dict[str, object]:
        """Returns the entry as a JSON object; unset optional keys are left out."""
        entry: dict[str, object] = {
            'file': self.file,
            'class': self.class_name,
            'vars': list(self.vars),
            'source_sha256': self.source_sha256,
            'manifest': self.manifest,
        }
        if self.checkpoint_interval is not None:
            entry['checkpoint_interval'] = self.checkpoint_interval
        if self.replay is not None:
            entry['replay'] = self.replay
        return entry


def render_manifest(entries: Iterable[ManifestEntry]) -> str:
    """Returns the text of rory_manifest.json: entries sorted by file and class.

    Args:
        entries: The instrumented classes, in any order.

    Returns:
        JSON with sorted keys, two-space indent and a trailing newline, so that the same
        inputs always give the same bytes.
    """
    nodes = [e.to_json() for e in sorted(entries, key=lambda e: (e.file, e.class_name))]
    document = {'format': MANIFEST_FORMAT, 'nodes': nodes}
    return json.dumps(document, indent=2, sort_keys=True, ensure_ascii=False) + '\n'
