"""``rory inspect STORE``: what a store holds, read without running anything.

    rory inspect .rory                                   # nodes, checkpoints, log segments
    rory inspect .rory --node mapper --checkpoint latest # the variables of one checkpoint

A store is what ``rory supervise`` writes (``store:`` in its config): per node a
``checkpoints/`` folder of ``<seq>.ckpt`` files (and ``chunks.dat``, the chunks of large ones)
and a ``log/`` folder of numbered rosbag2 MCAP segments, plus ``events.jsonl``. The listing
verifies every checkpoint as a restore would (checksum, format, node, chunks) and says why one
is refused. Variables are decoded as a restore would decode them; a value whose class (a
dataclass or Enum of the node's code) is not importable here is shown by its stored fields
instead, so nothing of the node is imported or run to inspect its state.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, TextIO

import msgpack
import numpy as np

from . import codec
from .errors import CheckpointError, CodecError, LogError
from .log import SegmentStore, read_segment
from .node import parameters as node_parameters
from .protocol import NODE_ID_RE
from .store import Checkpoint, CheckpointStore

EXT_NAMES = {
    codec.EXT_TUPLE: 'tuple', codec.EXT_SET: 'set', codec.EXT_FROZENSET: 'frozenset',
    codec.EXT_BYTEARRAY: 'bytearray', codec.EXT_BIGINT: 'int', codec.EXT_NDARRAY: 'ndarray',
    codec.EXT_NPSCALAR: 'numpy scalar', codec.EXT_ROSMSG: 'ROS message',
    codec.EXT_ENUM: 'Enum', codec.EXT_DATACLASS: 'dataclass', codec.EXT_TIME: 'rclpy Time',
    codec.EXT_DURATION: 'rclpy Duration', codec.EXT_DEQUE: 'deque',
    codec.EXT_ORDEREDDICT: 'OrderedDict', codec.EXT_NPRANDOM: 'numpy Generator',
    codec.EXT_PYRANDOM: 'random.Random',
}


class InspectError(Exception):
    """The store, node or checkpoint asked for is not there; the message names it."""


@dataclass(frozen=True)
class CheckpointInfo:
    """One checkpoint file as listed."""

    path: Path
    size: int
    checkpoint: Checkpoint | None
    refused: str  # why it would not be restored ('' when valid)
    chunked: int = 0  # bytes of its variables in the chunk file (store.py), not in the file


def nodes_in(store: Path) -> list[str]:
    """The node ids that have checkpoints or logs in the store."""
    if not store.is_dir():
        raise InspectError(f'{store}: not a directory (a store is the `store:` folder of a '
                           'supervisor config, .rory by default)')
    return sorted(
        p.name for p in store.iterdir()
        if p.is_dir() and NODE_ID_RE.fullmatch(p.name)
        and ((p / 'checkpoints').is_dir() or (p / 'log').is_dir())
    )


def checkpoints_of(store: Path, node: str) -> list[CheckpointInfo]:
    """The node's checkpoint files, newest first, each verified."""
    found = []
    checkpoints = CheckpointStore(store, node)
    for path in checkpoints.paths():
        try:
            ckpt: Checkpoint | None = checkpoints.load(path, expect_node=node)
            refused = ''
        except CheckpointError as err:
            ckpt, refused = None, str(err)
        found.append(CheckpointInfo(path, path.stat().st_size if path.exists() else 0, ckpt,
                                    refused, checkpoints.chunk_bytes(path)))
    return found


# -- describing values without the node's code --------------------------------------------------


@dataclass(frozen=True)
class _Ext:
    code: int
    data: bytes


def _raw(blob: bytes) -> Any:
    return msgpack.unpackb(blob, ext_hook=lambda code, data: _Ext(code, data), raw=False,
                           strict_map_key=False)


def kind_of(value: Any) -> str:
    """A short description of a raw (undecoded) value: its type, size or shape."""
    if isinstance(value, _Ext):
        name = EXT_NAMES.get(value.code, f'extension {value.code}')
        try:
            inner = _raw(value.data) if value.code not in (
                codec.EXT_BYTEARRAY, codec.EXT_BIGINT) else None
        except (ValueError, msgpack.ExtraData):
            inner = None
        if value.code == codec.EXT_NDARRAY and isinstance(inner, list) and len(inner) == 3:
            return f'ndarray {np.dtype(inner[0]).name} {tuple(inner[1])}'
        if value.code in (codec.EXT_ROSMSG, codec.EXT_DATACLASS) and isinstance(inner, list):
            return f'{name} {inner[0] if value.code == codec.EXT_ROSMSG else inner[1]}'
        if isinstance(inner, list | dict):
            return f'{name} of {len(inner)}'
        return name
    if isinstance(value, list | dict | str | bytes):
        return f'{type(value).__name__} of {len(value)}'
    return type(value).__name__


def variable_kinds(blob: bytes) -> dict[str, str]:
    """Variable name -> short description, read from the checkpoint's bytes alone."""
    raw = _raw(blob)
    if not isinstance(raw, dict):
        raise CodecError('the variables are not a map')
    return {str(k): kind_of(v) for k, v in raw.items()}


def decode_for_display(blob: bytes) -> tuple[dict[str, Any], str]:
    """The variables as a restore would decode them, else field by field; and a note."""
    try:
        return codec.decode_vars(blob), ''
    except CodecError as err:
        raw = _raw(blob)
        return ({str(k): _plain(v) for k, v in raw.items()},
                f'shown without the node\'s code ({err}); extension values as stored')


def _plain(value: Any) -> Any:
    """A raw value with ndarrays and containers decoded, everything else named."""
    if isinstance(value, list):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, _Ext):
        if value.code == codec.EXT_NDARRAY:
            return codec.decode(msgpack.packb(msgpack.ExtType(value.code, value.data)))
        if value.code in (codec.EXT_TUPLE, codec.EXT_SET, codec.EXT_FROZENSET,
                          codec.EXT_DEQUE):
            return _plain(_raw(value.data))
        if value.code == codec.EXT_DATACLASS:
            module, qualname, fields = _raw(value.data)
            return {'<dataclass>': f'{module}.{qualname}', **{k: _plain(v)
                                                                 for k, v in fields.items()}}
        if value.code == codec.EXT_ENUM:
            return '<Enum ' + '.'.join(str(p) for p in _raw(value.data)) + '>'
        return f'<{kind_of(value)}>'
    return value


def _array_head(value: np.ndarray[Any, Any]) -> str:
    head = f'ndarray {value.dtype} shape {value.shape}'
    if value.size and value.dtype.kind in 'biuf':
        finite = value[np.isfinite(value)] if value.dtype.kind == 'f' else value
        if finite.size:
            head += (f', min {finite.min():.6g} max {finite.max():.6g} '
                     f'mean {float(finite.mean()):.6g}, nonzero {np.count_nonzero(value)}')
    return head


def _has_array(value: Any) -> bool:
    if isinstance(value, np.ndarray):
        return True
    if isinstance(value, list | tuple):
        return any(_has_array(v) for v in value)
    if isinstance(value, dict):
        return any(_has_array(v) for v in value.values())
    return False


def render(value: Any, indent: str = '    ', width: int = 96) -> str:
    """Readable text for one variable: arrays summarised, long containers cut."""
    if isinstance(value, np.ndarray):
        body = np.array2string(value, threshold=24, edgeitems=3, max_line_width=width)
        return _array_head(value) + '\n' + '\n'.join(indent + line for line in body.splitlines())
    if _has_array(value) and isinstance(value, list | tuple | dict):
        # One line per element, arrays by shape and range: a grid pyramid stays readable.
        items = value.items() if isinstance(value, dict) else enumerate(value)
        lines = [f'{type(value).__name__} of {len(value)}']
        for key, item in items:
            text = _array_head(item) if isinstance(item, np.ndarray) else repr(item)
            lines.append(f'{indent}[{key!r}] {text[:width * 2]}')
        return '\n'.join(lines)
    text = repr(value)
    if len(text) > 2000:
        text = text[:2000] + f'... ({len(text)} characters)'
    return text


# -- the listing ------------------------------------------------------------------------------


def _when(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9).isoformat(sep=' ', timespec='milliseconds')


def age_line(ckpt: Checkpoint, now_ns: int) -> str:
    """A checkpoint's age on the system clock; under simulation time, the time it was taken
    too (only the node knows the clock it judges freshness by)."""
    sim = (f'; taken at {ckpt.clock_ns / 1e9:.3f} s of simulation time, the clock a node under '
           'use_sim_time judges it by') if ckpt.sim_time else ''
    return f'age {(now_ns - ckpt.created_ns) / 1e9:.1f} s{sim}'


def variable_ages(ckpt: Checkpoint, now_ns: int) -> dict[str, str]:
    """Each variable's age and rule (freshness.py), as a recovery now would judge it."""
    age_s = (now_ns - ckpt.created_ns) / 1e9
    rules = {key: (max_age, on_stale) for key, max_age, on_stale in ckpt.freshness}
    try:
        names = list(variable_kinds(ckpt.vars_blob))
    except (CodecError, ValueError):
        names = list(rules)
    ages = {}
    for name in names:
        if name not in rules:
            ages[name] = f'age {age_s:.1f} s, no rule (always restored)'
            continue
        max_age, on_stale = rules[name]
        verdict = ('stale' if age_s > max_age else 'fresh') if not ckpt.sim_time else 'see above'
        ages[name] = f'age {age_s:.1f} s, max_age {max_age:g} s, on_stale {on_stale}: {verdict}'
    return ages


def _size(n: float) -> str:
    for unit in ('B', 'kB', 'MB', 'GB'):
        if n < 1000 or unit == 'GB':
            return f'{n:.0f} {unit}' if unit == 'B' else f'{n:.1f} {unit}'
        n /= 1000
    return f'{n} B'  # unreachable


def _segments(store: Path, node: str) -> Iterator[str]:
    segments = SegmentStore(store, node)
    for n in segments.numbers():
        path = segments.path(n)
        size = sum(f.stat().st_size for f in path.rglob('*') if f.is_file())
        counts: dict[str, int] = {}
        first = last = None
        try:
            for entry in read_segment(path):
                counts[entry.topic] = counts.get(entry.topic, 0) + 1
                first = entry.recv_ns if first is None else first
                last = entry.recv_ns
        except LogError as err:
            yield f'    segment {n}: {_size(size)}, UNREADABLE: {err}'
            continue
        span = '' if first is None or last is None else (
            f', {_when(first)} .. +{(last - first) / 1e9:.1f} s')
        topics = ', '.join(f'{t} {c}' for t, c in sorted(counts.items())) or 'no messages'
        yield f'    segment {n}: {_size(size)}{span}: {topics}'


def _last_states(store: Path) -> dict[str, str]:
    states: dict[str, str] = {}
    path = store / 'events.jsonl'
    if not path.exists():
        return states
    for line in path.read_text(encoding='utf-8', errors='replace').splitlines():
        try:
            record = json.loads(line)
        except ValueError:
            continue
        if isinstance(record, dict) and record.get('kind') == 'state':
            states[str(record.get('node'))] = (f'{record.get("new")} since '
                                               f'{_when(int(float(record["t"]) * 1e9))}')
    return states


def listing(store: Path, out: TextIO, only: str | None = None) -> None:
    """Print every node's (or only one node's) checkpoints and segments."""
    nodes = nodes_in(store)
    if only is not None:
        if only not in nodes:
            raise InspectError(f'{store}: no node {only!r} (nodes here: '
                               f'{", ".join(nodes) or "none"})')
        nodes = [only]
    if not nodes:
        print(f'{store}: no node has checkpoints or logs here', file=out)
        return
    states = _last_states(store)
    now_ns = time.time_ns()
    for node in nodes:
        print(f'node {node}' + (f' (last state {states[node]})' if node in states else ''),
              file=out)
        infos = checkpoints_of(store, node)
        print(f'  checkpoints: {len(infos)}', file=out)
        for info in infos:
            ckpt = info.checkpoint
            if ckpt is None:
                print(f'    {info.path.name}: {_size(info.size)}, REFUSED: {info.refused}',
                      file=out)
                continue
            chunked = f' + {_size(info.chunked)} in chunks' if info.chunked else ''
            print(f'    seq {ckpt.seq}: {_when(ckpt.created_ns)}, {_size(info.size)}{chunked}, '
                  f'incarnation {ckpt.incarnation}, method {ckpt.method}, cut {ckpt.cut}, '
                  f'manifest {ckpt.manifest}', file=out)
            try:
                kinds = variable_kinds(ckpt.vars_blob)
            except (CodecError, ValueError) as err:
                print(f'      variables unreadable: {err}', file=out)
                continue
            ages = variable_ages(ckpt, now_ns)
            for name, kind in kinds.items():
                print(f'      {name}: {kind}; {ages.get(name, "")}'.rstrip('; '), file=out)
        lines = list(_segments(store, node))
        print(f'  log segments: {len(lines)}', file=out)
        for line in lines:
            print(line, file=out)


def show_checkpoint(store: Path, node: str, which: str, out: TextIO) -> None:
    """Print one checkpoint's header and variables."""
    nodes = nodes_in(store)
    if node not in nodes:
        raise InspectError(f'{store}: no node {node!r} (nodes here: {", ".join(nodes) or "none"})')
    infos = checkpoints_of(store, node)
    if which == 'latest':
        chosen = next((i for i in infos if i.checkpoint is not None), None)
        if chosen is None:
            reasons = '; '.join(f'{i.path.name}: {i.refused}' for i in infos) or 'none on disk'
            raise InspectError(f'{store}/{node}: no valid checkpoint ({reasons})')
    else:
        try:
            seq = int(which)
        except ValueError:
            raise InspectError(f'--checkpoint must be latest or a number, got {which!r}') from None
        chosen = next((i for i in infos if i.path.name == f'{seq:010d}.ckpt'), None)
        if chosen is None:
            kept = ', '.join(i.path.stem.lstrip('0') for i in infos) or 'none'
            raise InspectError(f'{store}/{node}: no checkpoint {seq} (kept: {kept})')
        if chosen.checkpoint is None:
            raise InspectError(f'{chosen.path}: refused: {chosen.refused}')
    ckpt = chosen.checkpoint
    assert ckpt is not None
    print(f'{chosen.path}\n  node {ckpt.node}, seq {ckpt.seq}, taken {_when(ckpt.created_ns)}, '
          f'incarnation {ckpt.incarnation}, method {ckpt.method}\n  cut {ckpt.cut}, '
          f'manifest {ckpt.manifest}, {_size(len(ckpt.vars_blob))} of variables', file=out)
    for topic, idents in ckpt.windows.items():
        print(f'  window {topic}: {len(idents)} message identities', file=out)
    now_ns = time.time_ns()
    print(f'  {age_line(ckpt, now_ns)}', file=out)
    for name, age in variable_ages(ckpt, now_ns).items():
        print(f'    {name}: {age}', file=out)
    values, note = decode_for_display(ckpt.vars_blob)
    if note:
        print(f'  ({note})', file=out)
    for name, value in values.items():
        print(f'  {name} = {render(value)}', file=out)
    if ckpt.lifecycle:
        print(f'  lifecycle state: {ckpt.lifecycle}', file=out)
    if ckpt.parameters:
        try:
            parameters = node_parameters.unpack(ckpt.parameters)
        except ValueError as err:
            print(f'  parameters: unreadable ({err})', file=out)
        else:
            for parameter in parameters:
                print(f'  parameter {parameter.name} = {parameter.value!r}', file=out)


def main(argv: Sequence[str] | None = None, out: TextIO | None = None) -> int:
    """``rory inspect``; 0, or 2 with a message naming what is missing."""
    out = sys.stdout if out is None else out
    parser = argparse.ArgumentParser(prog='rory inspect', description=__doc__.split('\n\n')[0])
    parser.add_argument('store', type=Path, help='the store folder (.rory by default)')
    parser.add_argument('--node', help='one node')
    parser.add_argument('--checkpoint', help='latest, or a checkpoint number (needs --node)')
    args = parser.parse_args(argv)
    try:
        if args.checkpoint is not None:
            if args.node is None:
                raise InspectError('--checkpoint needs --node')
            show_checkpoint(args.store, args.node, args.checkpoint, out)
        else:
            listing(args.store, out, only=args.node)
    except InspectError as err:
        print(f'rory inspect: {err}', file=sys.stderr)
        return 2
    except BrokenPipeError:
        # `rory inspect ... | head`: the reader has all it wanted. Point stdout at /dev/null so
        # the interpreter's final flush does not raise again.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    return 0
