"""The manifest: which code a checkpoint belongs to, as a digest and as OUT/rory_manifest.json.

The digest covers the file, the class, its vars, its module vars and the hash of the
module's source with RORY's additions removed. A checkpoint written by one build is
therefore recognised as foreign by a build of different code or a different var list,
while re-instrumenting an output (which strips to the same source) yields the same digest.
The per-node settings (``checkpoint_interval``, ``replay``) and the freshness rules of vars
are not hashed: changing them keeps the checkpoints valid (a var written as a mapping is
passed here as its plain path).
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
    *,
    file: str,
    class_name: str | None,
    vars: Sequence[str],
    source_sha256: str,
    module_vars: Sequence[str] = (),
) -> str:
    """Returns ``sha256:<hex>`` over the canonical JSON of what identifies a node build.

    The JSON object has the keys ``file``, ``class`` (when set), ``vars``, ``module_vars``
    (when set) and ``source_sha256``; a class entry without module vars hashes exactly as
    before module vars existed.

    Args:
        file: Source path relative to SRC, POSIX separators.
        class_name: Dotted class name, or None for a node written as functions.
        vars: Checkpointed attribute paths, in keyvars.yaml order.
        source_sha256: Hex SHA-256 of the module source with RORY's additions removed.
        module_vars: Checkpointed module globals, in keyvars.yaml order.

    Returns:
        The digest, as written into the decorator (or module call) and the manifest file.
    """
    payload: dict[str, object] = {'file': file, 'vars': list(vars),
                                  'source_sha256': source_sha256}
    if class_name is not None:
        payload['class'] = class_name
    if module_vars:
        payload['module_vars'] = list(module_vars)
    return DIGEST_PREFIX + hashlib.sha256(canonical_json(payload)).hexdigest()


@dataclass(frozen=True)
class ManifestEntry:
    """One instrumented node, as listed in rory_manifest.json.

    Attributes:
        file: Source path relative to OUT, POSIX separators.
        class_name: Dotted class name, or None for a node written as functions.
        vars: Checkpointed attribute paths (empty without a class).
        source_sha256: Hex SHA-256 of the module source with RORY's additions removed.
        manifest: The digest in the class's decorator or the module call.
        checkpoint_interval: Seconds between checkpoints, if keyvars.yaml set it.
        replay: ``'paced'`` or ``'fast'``, if keyvars.yaml set it.
        module_vars: Checkpointed module globals, if keyvars.yaml set them.
    """

    file: str
    class_name: str | None
    vars: tuple[str, ...]
    source_sha256: str
    manifest: str
    checkpoint_interval: float | None = None
    replay: str | None = None
    module_vars: tuple[str, ...] = ()

    def to_json(self) -> dict[str, object]:
        """Returns the entry as a JSON object; unset optional keys are left out."""
        entry: dict[str, object] = {
            'file': self.file,
            'vars': list(self.vars),
            'source_sha256': self.source_sha256,
            'manifest': self.manifest,
        }
        if self.class_name is not None:
            entry['class'] = self.class_name
        if self.module_vars:
            entry['module_vars'] = list(self.module_vars)
        if self.checkpoint_interval is not None:
            entry['checkpoint_interval'] = self.checkpoint_interval
        if self.replay is not None:
            entry['replay'] = self.replay
        return entry


def render_manifest(entries: Iterable[ManifestEntry]) -> str:
    """Returns the text of rory_manifest.json: entries sorted by file and class.

    A file's module entry (no class) comes before its classes.

    Args:
        entries: The instrumented classes, in any order.

    Returns:
        JSON with sorted keys, two-space indent and a trailing newline, so that the same
        inputs always give the same bytes.
    """
    nodes = [e.to_json() for e in sorted(entries, key=lambda e: (e.file, e.class_name or ''))]
    document = {'format': MANIFEST_FORMAT, 'nodes': nodes}
    return json.dumps(document, indent=2, sort_keys=True, ensure_ascii=False) + '\n'
