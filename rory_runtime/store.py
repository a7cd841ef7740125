"""Durable checkpoint files of one node.

Layout: ``<root>/<node>/checkpoints/<seq:010d>.ckpt``, directories mode 0700, files 0600.

File format, all integers little endian::

    offset  size  field
    0       8     magic b'RORYCKPT'
    8       2     u16 format version (1)
    10      4     u32 header length H
    14      H     header: msgpack map of every Checkpoint field except vars_blob (and
                  parameters, lifecycle, clock_ns with sim_time, and freshness when empty
                  or 0), plus
                  'vars_len' (the length of vars_blob)
    14+H    V     vars_blob, opaque here (codec.encode_vars output)
    14+H+V  32    SHA-256 over all bytes before it

A file is written to a temporary name in the same directory, flushed and fsynced, renamed
into place and the directory fsynced, so a final ``.ckpt`` name only ever holds a complete
file. A checkpoint that was nevertheless damaged later (disk, a hand edit) is caught by the
checksum and refused with :class:`CheckpointError`, and the caller falls back to an older
one. The store is meant for one writing process per node; it is not thread-safe.
"""

from __future__ import annotations

import hashlib
import os
import re
import struct
import tempfile
from collections.abc import Callable
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import msgpack

from rory_runtime.errors import CheckpointError
from rory_runtime.fsutil import fsync_dir, make_private_dir
from rory_runtime.protocol import NODE_ID_RE

MAGIC: Final = b'RORYCKPT'
FORMAT_VERSION: Final = 1

_PREFIX: Final = struct.Struct('<8sHI')
_DIGEST_LEN: Final = 32
_MIN_LEN: Final = _PREFIX.size + _DIGEST_LEN
_NAME_RE: Final = re.compile(r'([0-9]{10})\.ckpt')
_TMP_SUFFIX: Final = '.tmp'
_U64: Final = 2**64
_MAX_SEQ: Final = 10**10 - 1  # file names hold ten digits


@dataclass(frozen=True)
class Checkpoint:
    """One checkpoint of a node.

    Attributes:
        node: Node id.
        seq: 1, 2, 3... per node, monotonically increasing.
        incarnation: Which process incarnation wrote it.
        created_ns: Wall clock ``time.time_ns()`` when taken.
        manifest: Hash of the instrumented code version (opaque string).
        method: ``'rory'``, ``'checkpoint'``, ...
        cut: Number of the last log segment whose messages this checkpoint has absorbed;
            None when there is no log.
        windows: Per topic, identities ``(source_ts, seq)`` of recently absorbed messages,
            oldest first.
        vars_blob: ``codec.encode_vars`` output, opaque here.
        parameters: The node's parameters, a serialized ``rcl_interfaces/msg/ParameterEvent``
            (``node_parameters.py``); empty in checkpoints from before they were kept.
        lifecycle: A lifecycle node's primary state (``'active'``, ...); empty for other nodes.
        clock_ns: The node's ROS clock when taken (``freshness.py`` counts ages on it); 0 in
            checkpoints from before it was kept.
        sim_time: Whether that clock was simulation time (``use_sim_time``).
        freshness: The node's freshness rules when taken, ``(key, max_age, on_stale)`` each,
            for ``rory inspect`` (the node judges by the rules its code has now).

    """

    node: str
    seq: int
    incarnation: int
    created_ns: int
    manifest: str
    method: str
    cut: int | None
    windows: dict[str, list[tuple[int, int]]]
    vars_blob: bytes
    parameters: bytes = b''
    lifecycle: str = ''
    clock_ns: int = 0
    sim_time: bool = False
    freshness: tuple[tuple[str, float, str], ...] = ()


class CheckpointStore:
    """The checkpoint files of one node.

    Args:
        root: Directory holding one subdirectory per node.
        node: Node id; used as a directory name, so letters, digits, ``_ . -`` only.
        keep: How many of the newest checkpoints :meth:`write` leaves on disk.

    Raises:
        ValueError: Bad node id or keep below 1.

    """

    def __init__(self, root: Path, node: str, keep: int = 2) -> None:
        if not NODE_ID_RE.fullmatch(node):
            msg = f'{node!r} is not a node id (a letter, then letters, digits or _)'
            raise ValueError(msg)
        if keep < 1:
            msg = f'keep must be at least 1, got {keep}'
            raise ValueError(msg)
        self.root = Path(root)
        self.node = node
        self.keep = keep
        self.dir = self.root / node / 'checkpoints'

    def path(self, seq: int) -> Path:
        """Return the final file name of checkpoint seq."""
        return self.dir / f'{seq:010d}.ckpt'

    def paths(self) -> list[Path]:
        """Return the final checkpoint files, newest (highest seq) first.

        Raises:
            CheckpointError: The directory exists but cannot be listed.

        """
        return [self.path(seq) for seq in sorted(self._seqs(), reverse=True)]

    def next_seq(self) -> int:
        """Return the seq the next checkpoint should get: one above the highest on disk.

        Raises:
            CheckpointError: The directory exists but cannot be listed.

        """
        return max(self._seqs(), default=0) + 1

    def write(self, ckpt: Checkpoint) -> Path:
        """Write a checkpoint atomically, then drop all but the newest ``keep``.

        Args:
            ckpt: The checkpoint; its node must be this store's and its seq above every
                seq on disk.

        Returns:
            The final path.

        Raises:
            CheckpointError: The checkpoint is invalid or the file cannot be written.

        """
        final = self.path(ckpt.seq)
        if ckpt.node != self.node:
            msg = f'checkpoint of node {ckpt.node!r} in the store of {self.node!r}'
            raise CheckpointError(final, msg)
        data = serialize(ckpt, final)
        newest = max(self._seqs(), default=0)
        if ckpt.seq <= newest:
            msg = f'seq {ckpt.seq} is not above the newest checkpoint on disk ({newest})'
            raise CheckpointError(final, msg)
        try:
            make_private_dir(self.dir)
            self._remove_stale_temps()
            self._write_atomic(final, data)
        except OSError as err:
            raise CheckpointError(final, f'cannot write: {err}') from None
        self._prune()
        return final

    def load(
        self,
        path: Path,
        *,
        expect_manifest: str | None = None,
        expect_node: str | None = None,
    ) -> Checkpoint:
        """Read and verify one checkpoint file.

        Args:
            path: The file.
            expect_manifest: Refuse a checkpoint written by another code version.
            expect_node: Refuse a checkpoint of another node.

        Returns:
            The checkpoint.

        Raises:
            CheckpointError: The file is unreadable, truncated, corrupt, malformed or from
                another node or code version.

        """
        try:
            data = Path(path).read_bytes()
        except OSError as err:
            raise CheckpointError(path, f'cannot read: {err.strerror or err}') from None
        ckpt = deserialize(data, path)
        if expect_node is not None and ckpt.node != expect_node:
            msg = f'checkpoint of node {ckpt.node!r}, expected {expect_node!r}'
            raise CheckpointError(path, msg)
        if expect_manifest is not None and ckpt.manifest != expect_manifest:
            msg = (
                'written by a different version of the instrumented code:'
                f' manifest {ckpt.manifest}, expected {expect_manifest}'
            )
            raise CheckpointError(path, msg)
        return ckpt

    def latest_valid(
        self,
        *,
        expect_manifest: str | None = None,
        on_refused: Callable[[CheckpointError], None] | None = None,
    ) -> Checkpoint | None:
        """Return the newest checkpoint that loads, trying older ones after each refusal.

        Args:
            expect_manifest: Refuse checkpoints written by another code version.
            on_refused: Told about every refused checkpoint, newest first.

        Returns:
            The checkpoint, or None if there is no valid one.

        """
        for path in self.paths():
            try:
                return self.load(path, expect_manifest=expect_manifest, expect_node=self.node)
            except CheckpointError as err:
                if on_refused is not None:
                    on_refused(err)
        return None

    def quarantine(self, path: Path) -> Path:
        """Set a refused checkpoint aside (``<name>.refused``) so it no longer counts as one of
        the ``keep`` newest, and a later recovery does not try it again. Returns the new path.
        """
        target = path.with_name(path.name + '.refused')
        with suppress(FileNotFoundError):
            os.replace(path, target)
            fsync_dir(self.dir)
        return target

    def _seqs(self) -> list[int]:
        try:
            names = os.listdir(self.dir)
        except FileNotFoundError:
            return []
        except OSError as err:
            raise CheckpointError(self.dir, f'cannot list: {err.strerror or err}') from None
        return [int(match[1]) for name in names if (match := _NAME_RE.fullmatch(name))]

    def _write_atomic(self, final: Path, data: bytes) -> None:
        # mkstemp creates the file with mode 0600 and a name no other writer can collide with.
        fd, tmp_name = tempfile.mkstemp(
            dir=self.dir, prefix=f'.{final.name}.{os.getpid()}.', suffix=_TMP_SUFFIX
        )
        tmp = Path(tmp_name)
        try:
            with os.fdopen(fd, 'wb') as stream:
                stream.write(data)
                stream.flush()
                os.fsync(stream.fileno())
            os.replace(tmp, final)
        except BaseException:
            with suppress(OSError):
                tmp.unlink()
            raise
        fsync_dir(self.dir)

    def _remove_stale_temps(self) -> None:
        """Delete temporary files of writers that died before renaming them."""
        for entry in os.scandir(self.dir):
            if entry.name.startswith('.') and entry.name.endswith(_TMP_SUFFIX):
                pid = _temp_pid(entry.name)
                # Our own pid cannot have a write in flight here (single writer), so a temp
                # file with it is from an earlier incarnation that got the same pid.
                if pid is None or pid == os.getpid() or not _pid_alive(pid):
                    with suppress(FileNotFoundError):
                        os.unlink(entry.path)

    def _prune(self) -> None:
        for path in self.paths()[self.keep :]:
            # A checkpoint that cannot be deleted only costs disk space; never fail a write.
            with suppress(OSError):
                path.unlink()


def serialize(ckpt: Checkpoint, path: Path | str = '<memory>') -> bytes:
    """Return the file bytes of a checkpoint.

    Args:
        ckpt: The checkpoint.
        path: Named in errors.

    Returns:
        The bytes, checksum included.

    Raises:
        CheckpointError: A field has a value the format cannot hold.

    """
    _check_fields(ckpt, path)
    header = {
        'node': ckpt.node,
        'seq': ckpt.seq,
        'incarnation': ckpt.incarnation,
        'created_ns': ckpt.created_ns,
        'manifest': ckpt.manifest,
        'method': ckpt.method,
        'cut': ckpt.cut,
        'windows': {topic: [list(ident) for ident in ids] for topic, ids in ckpt.windows.items()},
        'vars_len': len(ckpt.vars_blob),
    }
    if ckpt.parameters:
        header['parameters'] = ckpt.parameters
    if ckpt.lifecycle:
        header['lifecycle'] = ckpt.lifecycle
    if ckpt.clock_ns:
        header['clock_ns'] = ckpt.clock_ns
        header['sim_time'] = ckpt.sim_time
    if ckpt.freshness:
        header['freshness'] = [list(rule) for rule in ckpt.freshness]
    packed: bytes = msgpack.packb(header, use_bin_type=True)
    body = b''.join((_PREFIX.pack(MAGIC, FORMAT_VERSION, len(packed)), packed, ckpt.vars_blob))
    return body + hashlib.sha256(body).digest()


def deserialize(data: bytes, path: Path | str = '<memory>') -> Checkpoint:
    """Parse and verify the bytes of a checkpoint file.

    Args:
        data: The file contents.
        path: Named in errors.

    Returns:
        The checkpoint.

    Raises:
        CheckpointError: The bytes are truncated, corrupt or malformed.

    """
    if len(data) < _MIN_LEN:
        msg = f'truncated: {len(data)} bytes, a checkpoint has at least {_MIN_LEN}'
        raise CheckpointError(path, msg)
    magic, version, header_len = _PREFIX.unpack_from(data)
    if magic != MAGIC:
        raise CheckpointError(path, f'not a RORY checkpoint (bad magic {magic!r})')
    # The checksum is checked before any field is believed, so that a flipped bit in the
    # version or a length reads as what it is: corruption.
    body = memoryview(data)[:-_DIGEST_LEN]
    if hashlib.sha256(body).digest() != data[-_DIGEST_LEN:]:
        raise CheckpointError(path, 'checksum mismatch: the file is corrupt or truncated')
    if version != FORMAT_VERSION:
        msg = f'unsupported format version {version}, this reader supports {FORMAT_VERSION}'
        raise CheckpointError(path, msg)
    vars_start = _PREFIX.size + header_len
    if vars_start > len(body):
        raise CheckpointError(path, f'malformed: header length {header_len} exceeds the file')
    header = _unpack_header(bytes(body[_PREFIX.size : vars_start]), path)
    vars_blob = bytes(body[vars_start:])
    if header.get('vars_len') != len(vars_blob):
        msg = f'malformed header: vars_len {header.get("vars_len")!r}, file holds {len(vars_blob)}'
        raise CheckpointError(path, msg)
    return _checkpoint_from_header(header, vars_blob, path)


def _unpack_header(raw: bytes, path: Path | str) -> dict[str, object]:
    try:
        header = msgpack.unpackb(
            raw,
            raw=False,
            use_list=True,
            strict_map_key=True,
            max_bin_len=len(raw),  # the parameters; bounded by the header itself
            max_ext_len=0,
            ext_hook=_refuse_ext,
        )
    except Exception as err:
        # Only msgpack runs here, but its failures span several exception types.
        raise CheckpointError(path, f'malformed header: {type(err).__name__}: {err}') from None
    if type(header) is not dict:
        raise CheckpointError(path, f'malformed header: a {type(header).__name__}, not a map')
    return header


def _refuse_ext(code: int, data: bytes) -> object:
    msg = f'extension type {code} in header'
    raise ValueError(msg)


def _checkpoint_from_header(
    header: dict[str, object], vars_blob: bytes, path: Path | str
) -> Checkpoint:
    cut = header.get('cut')
    if cut is not None:
        cut = _field_int(header, 'cut', path)
    return Checkpoint(
        node=_field_str(header, 'node', path),
        seq=_field_int(header, 'seq', path, minimum=1),
        incarnation=_field_int(header, 'incarnation', path),
        created_ns=_field_int(header, 'created_ns', path),
        manifest=_field_str(header, 'manifest', path),
        method=_field_str(header, 'method', path),
        cut=cut,
        windows=_field_windows(header, path),
        vars_blob=vars_blob,
        parameters=_field_bytes(header, 'parameters', path),
        lifecycle=_field_str(header, 'lifecycle', path) if 'lifecycle' in header else '',
        clock_ns=_field_int(header, 'clock_ns', path) if 'clock_ns' in header else 0,
        sim_time=header.get('sim_time') is True,
        freshness=_field_freshness(header, path),
    )


def _field_freshness(header: dict[str, object],
                     path: Path | str) -> tuple[tuple[str, float, str], ...]:
    value = header.get('freshness', [])
    rules: list[tuple[str, float, str]] = []
    if isinstance(value, list):
        for rule in value:
            if not (isinstance(rule, list) and len(rule) == 3 and type(rule[0]) is str
                    and type(rule[1]) in (int, float) and type(rule[2]) is str):
                break
            rules.append((rule[0], float(rule[1]), rule[2]))
        else:
            return tuple(rules)
    raise _bad_field(path, "'freshness'", 'a list of [key, max_age, on_stale]', value)


_MISSING: Final = object()


def _bad_field(path: Path | str, label: str, expected: str, value: object) -> CheckpointError:
    if value is _MISSING:
        return CheckpointError(path, f'malformed header: field {label} is missing')
    msg = f'malformed header: field {label} should be {expected}, got {value!r}'
    return CheckpointError(path, msg)


def _field_str(header: dict[str, object], name: str, path: Path | str) -> str:
    value = header.get(name, _MISSING)
    if type(value) is not str:
        raise _bad_field(path, repr(name), 'a str', value)
    return value


def _field_bytes(header: dict[str, object], name: str, path: Path | str) -> bytes:
    value = header.get(name, b'')
    if type(value) is not bytes:
        raise _bad_field(path, repr(name), 'bytes', value)
    return value


def _field_int(header: dict[str, object], name: str, path: Path | str, minimum: int = 0) -> int:
    value = header.get(name, _MISSING)
    # type() rather than isinstance(): msgpack booleans are ints to isinstance.
    if type(value) is not int or value < minimum:
        raise _bad_field(path, repr(name), f'an int >= {minimum}', value)
    return value


def _field_windows(header: dict[str, object], path: Path | str) -> dict[str, list[tuple[int, int]]]:
    value = header.get('windows', _MISSING)
    expected = 'a map of topic to [[source_ts, seq], ...]'
    if type(value) is not dict:
        raise _bad_field(path, "'windows'", expected, value)
    windows: dict[str, list[tuple[int, int]]] = {}
    for topic, idents in value.items():
        if type(topic) is not str or type(idents) is not list:
            raise _bad_field(path, "'windows'", expected, {topic: idents})
        windows[topic] = [_ident(ident, topic, path) for ident in idents]
    return windows


def _ident(ident: object, topic: str, path: Path | str) -> tuple[int, int]:
    if (
        type(ident) is not list
        or len(ident) != 2
        or not all(type(part) is int and 0 <= part < _U64 for part in ident)
    ):
        label = f"'windows'[{topic!r}]"
        raise _bad_field(path, label, 'a pair [source_ts, seq] of u64', ident)
    return (ident[0], ident[1])


def _check_fields(ckpt: Checkpoint, path: Path | str) -> None:
    """Refuse at write time what load would refuse, so a written file always loads."""
    problems = [
        name
        for name, ok in (
            ('node', type(ckpt.node) is str),
            ('seq', type(ckpt.seq) is int and 1 <= ckpt.seq <= _MAX_SEQ),
            ('incarnation', type(ckpt.incarnation) is int and 0 <= ckpt.incarnation < _U64),
            ('created_ns', type(ckpt.created_ns) is int and 0 <= ckpt.created_ns < _U64),
            ('manifest', type(ckpt.manifest) is str),
            ('method', type(ckpt.method) is str),
            ('cut', ckpt.cut is None or (type(ckpt.cut) is int and 0 <= ckpt.cut < _U64)),
            ('windows', _windows_ok(ckpt.windows)),
            ('vars_blob', type(ckpt.vars_blob) is bytes),
            ('clock_ns', type(ckpt.clock_ns) is int and 0 <= ckpt.clock_ns < _U64),
        )
        if not ok
    ]
    if problems:
        msg = f'cannot write checkpoint: invalid field(s) {", ".join(problems)}'
        raise CheckpointError(path, msg)


def _windows_ok(windows: object) -> bool:
    if type(windows) is not dict:
        return False
    for topic, idents in windows.items():
        if type(topic) is not str or not isinstance(idents, list):
            return False
        for ident in idents:
            if (
                not isinstance(ident, tuple | list)
                or len(ident) != 2
                or not all(type(part) is int and 0 <= part < _U64 for part in ident)
            ):
                return False
    return True


def _temp_pid(name: str) -> int | None:
    # Names look like '.0000000003.ckpt.<pid>.<random>.tmp'.
    parts = name.split('.')
    if len(parts) >= 5 and parts[3].isdigit():
        return int(parts[3])
    return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by someone else
    return True
