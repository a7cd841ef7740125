"""Durable checkpoint files of one node.

Layout: ``<root>/<node>/checkpoints/<seq:010d>.ckpt``, and ``chunks.dat`` beside them when
a checkpoint's variables are large (chunk_file.py); directories mode 0700, files 0600.

File format, all integers little endian::

    offset  size  field
    0       8     magic b'RORYCKPT'
    8       2     u16 format version: 1, the variables in the file; 2, in parts
    10      4     u32 header length H
    14      H     header: msgpack map of every Checkpoint field except vars_blob (and
                  parameters, lifecycle, timers, clock_ns with sim_time, and freshness when empty
                  or 0), plus
                  'vars_len' (the length of vars_blob), and in version 2
                  'parts': the parts vars_blob is made of, in order, each either
                      n (an int): the next n bytes of the inline bytes below, or
                      [offset, length, SHA-256 (bin 32)]: a chunk in chunks.dat
    14+H    V     version 1: vars_blob, opaque here (codec.encode_vars output);
                  version 2: the inline bytes, V the sum of the int parts
    14+H+V  32    SHA-256 over all bytes before it

Version 1 is written when the variables are small (chunks.INLINE_MAX): the file holds all.
Larger ones are cut into chunks (chunks.py) and each chunk is stored once in chunks.dat, so
a checkpoint writes only the chunks no kept checkpoint holds yet.

A file is written to a temporary name in the same directory, flushed and fsynced, renamed
into place and the directory fsynced, so a final ``.ckpt`` name only ever holds a complete
file; the chunks it names are durable before that. A checkpoint that was nevertheless damaged
later (disk, a hand edit) is caught by its checksum, or a chunk's, and refused with
:class:`CheckpointError` naming the ``.ckpt`` file, and the caller falls back to an older
one. A chunk no kept checkpoint names any more is garbage: its room is reused. So are those
named by the copies of a checkpoint the supervisor keeps beside a quarantined message
(``<node>/quarantine/*/checkpoints/*.ckpt``, supervisor/poison.py), which name the chunks in
this folder. The store is meant for one writing process per node; it is not thread-safe.
"""

from __future__ import annotations

import hashlib
import os
import re
import struct
from collections.abc import Callable, Sequence
from contextlib import suppress
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Final

import msgpack

from rory_runtime import chunk_file, chunks
from rory_runtime.chunk_file import Ref
from rory_runtime.errors import CheckpointError
from rory_runtime.fsutil import fsync_dir, make_private_dir
from rory_runtime.protocol import NODE_ID_RE

MAGIC: Final = b'RORYCKPT'
FORMAT_VERSION: Final = 1
"""The version whose file holds the variables whole."""
CHUNKED_VERSION: Final = 2
"""The version whose variables are parts: inline bytes and chunks in chunks.dat."""

_PREFIX: Final = struct.Struct('<8sHI')
_DIGEST_LEN: Final = 32
_MIN_LEN: Final = _PREFIX.size + _DIGEST_LEN
_CKPT_SUFFIX: Final = '.ckpt'
_NAME_RE: Final = re.compile(r'([0-9]{10})\.ckpt')
_TMP_SUFFIX: Final = '.tmp'
_U64: Final = 2**64
_MAX_SEQ: Final = 10**10 - 1  # file names hold ten digits
_QUARANTINE: Final = 'quarantine'  # supervisor/poison.py keeps checkpoint copies in it
_StatKey = tuple[int, int, int]


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
            (``node/parameters.py``); empty in checkpoints from before they were kept.
        lifecycle: A lifecycle node's primary state (``'active'``, ...); empty for other nodes.
        timers: The node's timers (``node/timers.py``: period, clock, cancelled, grid, the
            method a timer made after start-up calls); empty in checkpoints from before.
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
    timers: bytes = b''
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
        # The chunks each checkpoint file names, by the file's identity: files never change
        # once renamed into place, so only a new file is read (on the writing thread).
        self._refs: dict[Path, tuple[_StatKey, list[Ref]]] = {}

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

    def write(self, ckpt: Checkpoint, *, parts: Sequence[chunks.Part] | None = None) -> Path:
        """Write a checkpoint atomically, then drop all but the newest ``keep``.

        Its variables go inline into the file when they are small, else as chunks into
        chunks.dat, only those no checkpoint on disk holds yet (durable before the file is
        renamed into place); the chunks only dropped checkpoints named become free room.

        Args:
            ckpt: The checkpoint; its node must be this store's and its seq above every
                seq on disk.
            parts: Its variables as ``chunks.Chunker.split`` made them, instead of
                ``ckpt.vars_blob`` (then empty). Chunk data must stay valid until this returns.

        Returns:
            The final path.

        Raises:
            CheckpointError: The checkpoint is invalid or the file cannot be written.

        """
        final = self.path(ckpt.seq)
        if ckpt.node != self.node:
            msg = f'checkpoint of node {ckpt.node!r} in the store of {self.node!r}'
            raise CheckpointError(final, msg)
        if parts is not None and ckpt.vars_blob:
            msg = 'cannot write checkpoint: its variables given twice (vars_blob and parts)'
            raise CheckpointError(final, msg)
        _check_fields(ckpt, final)
        if parts is None:
            parts = chunks.split_blob(ckpt.vars_blob)
        inline = all(isinstance(part, bytes) for part in parts)
        if inline:
            whole = ckpt if len(parts) == 1 and parts[0] is ckpt.vars_blob else replace(
                ckpt, vars_blob=b''.join(part for part in parts if isinstance(part, bytes)))
            data = serialize(whole, final)
        names = self._names()
        seqs = _seqs_in(names)
        newest = max(seqs, default=0)
        if ckpt.seq <= newest:
            msg = f'seq {ckpt.seq} is not above the newest checkpoint on disk ({newest})'
            raise CheckpointError(final, msg)
        roots: dict[Path, list[Ref]] | None = None
        try:
            make_private_dir(self.dir)
            self._remove_stale_temps(names)
            if not inline:
                roots = self._roots(seqs)
                refs = chunk_file.place(self.dir, parts, _all_refs(roots))
                data = _serialize_chunked(ckpt, parts, refs, final)
            written = self._write_atomic(final, data)
        except OSError as err:
            raise CheckpointError(final, f'cannot write: {err}') from None
        if roots is not None:
            roots[final] = refs
            self._refs[final] = (written, refs)
        self._prune([*seqs, ckpt.seq], roots)
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
        ckpt = deserialize(data, path, chunks_at=self.chunk_file_of(Path(path)))
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

    def chunk_file_of(self, path: Path) -> Path:
        """The chunk file whose chunks the checkpoint file ``path`` names: the one beside it,
        else this store's (a copy kept under quarantine names this store's chunks)."""
        beside = Path(path).parent / chunk_file.NAME
        return beside if beside.exists() else self.dir / chunk_file.NAME

    def chunk_bytes(self, path: Path) -> int:
        """How many bytes of the checkpoint file ``path``'s variables are in chunks (0 for one
        that holds them whole, or that cannot be read)."""
        try:
            return sum(ref.length for ref in _parse(Path(path).read_bytes(), path).refs)
        except (OSError, CheckpointError):
            return 0

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
        return _seqs_in(self._names())

    def _names(self) -> list[str]:
        try:
            return os.listdir(self.dir)
        except FileNotFoundError:
            return []
        except OSError as err:
            raise CheckpointError(self.dir, f'cannot list: {err.strerror or err}') from None

    def _write_atomic(self, final: Path, data: bytes) -> _StatKey:
        """Write ``final`` through a temporary file; the identity of the file written."""
        tmp = self.dir / f'.{final.name}.{os.getpid()}.{os.urandom(4).hex()}{_TMP_SUFFIX}'
        # O_EXCL: a name no other writer holds; mode 0600 (a umask only takes bits away).
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
        try:
            try:
                view = memoryview(data)
                while view:
                    view = view[os.write(fd, view):]
                os.fsync(fd)
                written = _stat_key(os.fstat(fd))  # a rename changes none of it
            finally:
                os.close(fd)
            os.replace(tmp, final)
        except BaseException:
            with suppress(OSError):
                tmp.unlink()
            raise
        fsync_dir(self.dir)
        return written

    def _remove_stale_temps(self, names: list[str]) -> None:
        """Delete temporary files of writers that died before renaming them."""
        for name in names:
            if name.startswith('.') and name.endswith(_TMP_SUFFIX):
                pid = _temp_pid(name)
                # Our own pid cannot have a write in flight here (single writer), so a temp
                # file with it is from an earlier incarnation that got the same pid.
                if pid is None or pid == os.getpid() or not _pid_alive(pid):
                    with suppress(FileNotFoundError):
                        os.unlink(self.dir / name)

    def _prune(self, seqs: list[int], roots: dict[Path, list[Ref]] | None) -> None:
        """Drop all but the newest ``keep`` of the checkpoints ``seqs``, then the chunks no
        checkpoint on disk names any more. ``roots``: what :meth:`_roots` found before this
        write, and the checkpoint it wrote (None: not known)."""
        for path in [self.path(seq) for seq in sorted(seqs, reverse=True)[self.keep :]]:
            # A checkpoint that cannot be deleted only costs disk space; never fail a write.
            with suppress(OSError):
                path.unlink()
                if roots is not None:
                    roots.pop(path, None)
        if roots is None:
            if not (self.dir / chunk_file.NAME).exists():
                return  # no chunks: nothing more to drop
            roots = self._roots()
        if roots is not None:
            with suppress(OSError):
                chunk_file.collect(self.dir, [ref for refs in roots.values() for ref in refs])

    def _roots(self, seqs: list[int] | None = None) -> dict[Path, list[Ref]] | None:
        """The chunks each checkpoint on disk names: the files here (``seqs``, else listed)
        and the copies kept under quarantine. None when one of them cannot be read (then
        none is known)."""
        files = [self.path(seq) for seq in (self._seqs() if seqs is None else seqs)]
        files += self._quarantined()
        roots: dict[Path, list[Ref]] = {}
        cache: dict[Path, tuple[_StatKey, list[Ref]]] = {}
        for path in files:
            try:
                key = _stat_key(path.stat())
                cached = self._refs.get(path)
                if cached is not None and cached[0] == key:
                    refs = cached[1]
                else:
                    refs = _refs_of(path.read_bytes(), path)
            except FileNotFoundError:
                continue  # gone since the listing: names nothing
            except OSError:
                return None
            cache[path] = (key, refs)
            roots[path] = refs
        self._refs = cache
        return roots

    def _quarantined(self) -> list[Path]:
        """The checkpoint copies kept beside quarantined messages (supervisor/poison.py)."""
        found: list[Path] = []
        try:
            folders = list(os.scandir(self.root / self.node / _QUARANTINE))
        except OSError:
            return found  # none yet, the common case
        for folder in folders:
            with suppress(OSError):
                copies = os.scandir(Path(folder.path) / 'checkpoints')
                found += (Path(e.path) for e in copies if e.name.endswith(_CKPT_SUFFIX))
        return sorted(found)


def serialize(ckpt: Checkpoint, path: Path | str = '<memory>') -> bytes:
    """Return the file bytes of a checkpoint holding its variables whole (format version 1).

    Args:
        ckpt: The checkpoint.
        path: Named in errors.

    Returns:
        The bytes, checksum included.

    Raises:
        CheckpointError: A field has a value the format cannot hold.

    """
    _check_fields(ckpt, path)
    return _frame(FORMAT_VERSION, _header(ckpt, len(ckpt.vars_blob)), [ckpt.vars_blob])


def _serialize_chunked(
    ckpt: Checkpoint, parts: Sequence[chunks.Part], refs: Sequence[Ref], path: Path | str
) -> bytes:
    """The file bytes of a checkpoint whose variables are ``parts`` (format version 2), its
    chunks at ``refs`` (one per chunk, in order)."""
    _check_fields(ckpt, path)
    entries: list[object] = []
    inline: list[bytes] = []
    placed = iter(refs)
    vars_len = 0
    for part in parts:
        if isinstance(part, bytes):
            entries.append(len(part))
            inline.append(part)
            vars_len += len(part)
        else:
            ref = next(placed)
            entries.append([ref.offset, ref.length, ref.digest])
            vars_len += ref.length
    header = _header(ckpt, vars_len)
    header['parts'] = entries
    return _frame(CHUNKED_VERSION, header, inline)


def _header(ckpt: Checkpoint, vars_len: int) -> dict[str, object]:
    header: dict[str, object] = {
        'node': ckpt.node,
        'seq': ckpt.seq,
        'incarnation': ckpt.incarnation,
        'created_ns': ckpt.created_ns,
        'manifest': ckpt.manifest,
        'method': ckpt.method,
        'cut': ckpt.cut,
        'windows': {topic: [list(ident) for ident in ids] for topic, ids in ckpt.windows.items()},
        'vars_len': vars_len,
    }
    if ckpt.parameters:
        header['parameters'] = ckpt.parameters
    if ckpt.lifecycle:
        header['lifecycle'] = ckpt.lifecycle
    if ckpt.timers:
        header['timers'] = ckpt.timers
    if ckpt.clock_ns:
        header['clock_ns'] = ckpt.clock_ns
        header['sim_time'] = ckpt.sim_time
    if ckpt.freshness:
        header['freshness'] = [list(rule) for rule in ckpt.freshness]
    return header


def _frame(version: int, header: dict[str, object], body: Sequence[bytes]) -> bytes:
    packed: bytes = msgpack.packb(header, use_bin_type=True)
    data = b''.join((_PREFIX.pack(MAGIC, version, len(packed)), packed, *body))
    return data + hashlib.sha256(data).digest()


def deserialize(
    data: bytes, path: Path | str = '<memory>', *, chunks_at: Path | None = None
) -> Checkpoint:
    """Parse and verify the bytes of a checkpoint file.

    Args:
        data: The file contents.
        path: Named in errors.
        chunks_at: The chunk file its chunks are in, if it names any.

    Returns:
        The checkpoint.

    Raises:
        CheckpointError: The bytes are truncated, corrupt or malformed, or a chunk they name
            is missing or corrupt.

    """
    parsed = _parse(data, path)
    refs = parsed.refs
    if refs and chunks_at is None:
        raise CheckpointError(path, 'its variables are in chunks, and no chunk file was given')
    found = iter(chunk_file.read(chunks_at, refs, Path(path)) if chunks_at is not None else [])
    pieces: list[bytes | memoryview] = []
    offset = 0
    for entry in parsed.parts:
        if isinstance(entry, int):
            pieces.append(parsed.inline[offset : offset + entry])
            offset += entry
        else:
            pieces.append(next(found))
    return _checkpoint_from_header(parsed.header, b''.join(pieces), path)


@dataclass(frozen=True)
class _Parsed:
    """A checkpoint file, verified, its chunks not read."""

    header: dict[str, object]
    inline: memoryview
    parts: list[int | Ref]  # version 1: one int, the whole of inline

    @property
    def refs(self) -> list[Ref]:
        return [entry for entry in self.parts if isinstance(entry, Ref)]


def _parse(data: bytes, path: Path | str) -> _Parsed:
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
    if version not in (FORMAT_VERSION, CHUNKED_VERSION):
        msg = (f'unsupported format version {version}, this reader supports '
               f'{FORMAT_VERSION} and {CHUNKED_VERSION}')
        raise CheckpointError(path, msg)
    vars_start = _PREFIX.size + header_len
    if vars_start > len(body):
        raise CheckpointError(path, f'malformed: header length {header_len} exceeds the file')
    header = _unpack_header(bytes(body[_PREFIX.size : vars_start]), path)
    inline = body[vars_start:]
    parts: list[int | Ref] = [len(inline)]
    if version == CHUNKED_VERSION:
        parts = _field_parts(header, len(inline), path)
    vars_len = sum(entry if isinstance(entry, int) else entry.length for entry in parts)
    if header.get('vars_len') != vars_len:
        msg = f'malformed header: vars_len {header.get("vars_len")!r}, file holds {vars_len}'
        raise CheckpointError(path, msg)
    return _Parsed(header, inline, parts)


def _seqs_in(names: list[str]) -> list[int]:
    return [int(match[1]) for name in names if (match := _NAME_RE.fullmatch(name))]


def _all_refs(roots: dict[Path, list[Ref]] | None) -> list[Ref] | None:
    return None if roots is None else [ref for refs in roots.values() for ref in refs]


def _refs_of(data: bytes, path: Path) -> list[Ref]:
    """The chunks a checkpoint file names; none when it is corrupt (it is refused whole)."""
    try:
        return _parse(data, path).refs
    except CheckpointError:
        return []


def _field_parts(header: dict[str, object], inline_len: int, path: Path | str) -> list[int | Ref]:
    value = header.get('parts', _MISSING)
    expected = 'a list of inline lengths and [offset, length, sha256]'
    if type(value) is not list:
        raise _bad_field(path, "'parts'", expected, value)
    parts: list[int | Ref] = []
    inline = 0
    for entry in value:
        if type(entry) is int and entry >= 0:
            parts.append(entry)
            inline += entry
        elif (type(entry) is list and len(entry) == 3
              and all(type(n) is int and 0 <= n < _U64 for n in entry[:2])
              and type(entry[2]) is bytes and len(entry[2]) == chunks.DIGEST_BYTES):
            parts.append(Ref(entry[0], entry[1], entry[2]))
        else:
            raise _bad_field(path, "'parts'", expected, entry)
    if inline != inline_len:
        msg = f'malformed header: parts name {inline} inline bytes, the file holds {inline_len}'
        raise CheckpointError(path, msg)
    return parts


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
        timers=_field_bytes(header, 'timers', path),
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


def _stat_key(info: os.stat_result) -> _StatKey:
    return (info.st_ino, info.st_size, info.st_mtime_ns)
