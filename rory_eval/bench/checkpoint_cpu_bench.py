"""What a checkpoint of grid_slam-sized state costs the node's process in CPU (issue 36).

    python -m rory_eval.bench.checkpoint_cpu_bench [--checkpoints 25] [--changed 0 1 10 100]
        [--room] [--chunk-kib 64] [--dir DIR]

The state is grid_slam's (targets/grid_slam/keyvars.yaml): ``mapper.log_odds``, float32 grids
of 1024x1024, 512x512 and 256x256 cells (5.25 MiB), a pose and a counter. Between two
checkpoints, the given percentage of the grids' chunks changes (one cell in each of them,
picked at random; at least one chunk), or with ``--room`` what a map update in a room does:
every cell of an 8 m x 6 m window (160 x 120 cells of 5 cm, the same area on the coarser
levels), the same window each time (the robot stays in its room). Each checkpoint is the
runtime's own: ``Checkpointer.take`` (the snapshot under the lock) then the job it returns
(what the ``rory-io`` thread runs: packing, hashing, building and writing the files, fsyncs
included), both run here on one thread, timed in process CPU time (``time.process_time``:
user and system, every thread). Medians of ``--checkpoints`` checkpoints, after two not
counted (the first writes everything, the second finds the buffers of the first).

``old`` is the whole-file path it replaced, rebuilt here from the same functions: a plain
copy of the arrays under the lock, the msgpack blob (``codec.pack_snapshot``), a version 1
file with its SHA-256 over everything (``store.serialize``) written to a temporary name,
fsynced, renamed, the folder fsynced. Checkpoints go to ``--dir`` (default: a temporary
folder, on this machine's disk).
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import statistics
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rcl_interfaces.msg import ListParametersResult
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.parameter import Parameter

from rory_runtime import chunk_file, chunks, codec
from rory_runtime.fsutil import fsync_dir, make_private_dir
from rory_runtime.log import SegmentStore
from rory_runtime.node.checkpointer import Checkpointer
from rory_runtime.node.state import CheckpointSpec, read_state
from rory_runtime.protocol import Method
from rory_runtime.store import Checkpoint, CheckpointStore, serialize

CELLS = (1024, 512, 256)  # grid_slam's levels: map_size 1024, three levels
SPEC = CheckpointSpec(('mapper.log_odds', 'mapper.pose', 'mapper.scans_matched'), 'sha256:0')


@dataclass
class _Mapper:
    log_odds: list[np.ndarray[Any, np.dtype[np.float32]]]
    pose: np.ndarray[Any, np.dtype[np.float64]] = field(default_factory=lambda: np.zeros(3))
    scans_matched: int = 0


class _Node:
    """What a checkpoint reads of a node: its key variables, clock and parameters."""

    def __init__(self, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.mapper = _Mapper([rng.standard_normal((n, n)).astype(np.float32) for n in CELLS])

    def get_clock(self) -> Clock:
        return Clock(clock_type=ClockType.ROS_TIME)

    def get_logger(self) -> logging.Logger:
        return logging.getLogger('checkpoint-cpu-bench')

    def list_parameters(self, _prefixes: list[str], _depth: int) -> ListParametersResult:
        return ListParametersResult()

    def get_parameters(self, _names: list[str]) -> list[Parameter]:
        return []


def change(node: _Node, percent: float, chunk_bytes: int, rng: np.random.Generator) -> None:
    """Change one cell in ``percent`` % of the grids' chunks (at least one), picked at random."""
    flats = [grid.reshape(-1) for grid in node.mapper.log_odds]
    per_chunk = chunk_bytes // 4
    chunk_ids = [(i, c) for i, flat in enumerate(flats)
                 for c in range(chunks.chunk_count(flat.nbytes, chunk_bytes))]
    count = max(1, round(len(chunk_ids) * percent / 100)) if percent > 0 else 0
    for pick in rng.choice(len(chunk_ids), size=count, replace=False):
        i, c = chunk_ids[pick]
        cell = c * per_chunk + int(rng.integers(min(per_chunk, flats[i].size - c * per_chunk)))
        flats[i][cell] += 1.0
    node.mapper.scans_matched += 1


ROOM_CELLS = (120, 160)  # rows, columns of the finest level: 6 m x 8 m at 5 cm


def change_room(node: _Node, origin: tuple[int, int]) -> None:
    """A map update in a room: every cell of the room's window, on every level."""
    for level, grid in enumerate(node.mapper.log_odds):
        row, col = origin[0] >> level, origin[1] >> level
        grid[row:row + (ROOM_CELLS[0] >> level), col:col + (ROOM_CELLS[1] >> level)] += 0.1
    node.mapper.scans_matched += 1


def new_checkpointer(folder: Path, chunk_bytes: int) -> Checkpointer:
    def ignore(_: object) -> None:
        pass

    checkpointer = Checkpointer(
        SPEC, Method.CHECKPOINT, 'grid_slam', 1, threading.RLock(),
        CheckpointStore(folder, 'grid_slam'), SegmentStore(folder, 'grid_slam'),
        error=_raise, status=ignore)
    checkpointer.number_from_store()
    checkpointer.array_pool = codec.ArrayPool(chunk_bytes)
    checkpointer.chunker = chunks.Chunker(chunk_bytes)
    return checkpointer


def _raise(message: str) -> None:
    raise RuntimeError(message)


Run = Callable[[], float]
"""Takes one checkpoint; returns the CPU ms of its part under the lock."""


def new_checkpoint(checkpointer: Checkpointer, node: _Node) -> Run:
    """One checkpoint as the runtime takes it: the snapshot, then the I/O thread's job."""

    def run() -> float:
        began = time.process_time()
        persist = checkpointer.take(node, {})  # type: ignore[arg-type]
        locked = time.process_time() - began
        assert persist is not None
        persist()
        return locked * 1000.0

    return run


def old_checkpoint(folder: Path, node: _Node) -> Run:
    """One checkpoint as it was before chunks: a whole version 1 file."""
    pool = codec.ArrayPool()  # no chunks: plain copies into the last buffers
    directory = folder / 'grid_slam' / 'checkpoints'
    make_private_dir(directory)
    seqs = iter(range(1, 10**9))

    def run() -> float:
        began = time.process_time()
        snapshot = codec.snapshot_vars(read_state(SPEC, node), pool)
        locked = time.process_time() - began
        blob = codec.pack_snapshot(snapshot)
        pool.refill(snapshot)
        seq = next(seqs)
        data = serialize(Checkpoint('grid_slam', seq, 1, time.time_ns(), SPEC.manifest,
                                    'checkpoint', None, {}, blob))
        final = directory / f'{seq:010d}.ckpt'
        temp = directory / f'.{final.name}.{os.getpid()}.tmp'
        with open(temp, 'wb') as stream:
            stream.write(data)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temp, final)
        fsync_dir(directory)
        (directory / f'{seq - 2:010d}.ckpt').unlink(missing_ok=True)  # keep two
        return locked * 1000.0

    return run


def measure(run: Run, changes: Callable[[], None], count: int) -> tuple[list[float], list[float]]:
    """CPU ms of each of ``count`` checkpoints, ``changes`` made before each, and of their
    part under the lock."""
    run()
    changes()
    run()
    times, locked = [], []
    for _ in range(count):
        changes()
        began = time.process_time()
        locked.append(run())
        times.append((time.process_time() - began) * 1000.0)
    return times, locked


def main(argv: Sequence[str] | None = None) -> int:
    """Measure old and new at each percentage; print a Markdown table."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.checkpoint_cpu_bench',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--checkpoints', type=int, default=25)
    parser.add_argument('--changed', type=float, nargs='+', default=[0.0, 1.0, 10.0, 100.0],
                        help='percent of the chunks changed between two checkpoints')
    parser.add_argument('--room', action='store_true', help='also a map update in a room')
    parser.add_argument('--chunk-kib', type=int, nargs='+', default=[chunks.CHUNK_BYTES // 1024],
                        help='chunk sizes to compare (KiB)')
    parser.add_argument('--no-old', action='store_true', help='skip the whole-file path')
    parser.add_argument('--dir', type=Path, default=None)
    args = parser.parse_args(argv)
    base = Path(tempfile.mkdtemp(prefix='ckpt-cpu-', dir=args.dir))
    patterns: list[float | None] = [*args.changed, *([None] if args.room else [])]
    header = ['path', *(f'{p:g} % changed' if p is not None else 'a room' for p in patterns)]
    lines = ['| ' + ' | '.join(header) + ' |', '|---' + '|---:' * len(patterns) + '|']
    locked_lines = list(lines)
    configs: list[tuple[str, int]] = [] if args.no_old else [('old', chunks.CHUNK_BYTES)]
    configs += [(f'chunks of {kib} KiB', kib * 1024) for kib in args.chunk_kib]
    try:
        for label, chunk_bytes in configs:
            cells, locked_cells = [], []
            for i, percent in enumerate(patterns):
                folder = base / f'{label.replace(" ", "_")}-{i}'
                node = _Node(seed=i)
                rng = np.random.default_rng(i)
                origin = (int(rng.integers(CELLS[0] - ROOM_CELLS[0])),
                          int(rng.integers(CELLS[0] - ROOM_CELLS[1])))

                def changes(node: _Node = node, percent: float | None = percent,
                            rng: np.random.Generator = rng, chunk_bytes: int = chunk_bytes,
                            origin: tuple[int, int] = origin) -> None:
                    if percent is None:
                        change_room(node, origin)
                    else:
                        change(node, percent, chunk_bytes, rng)

                slot = chunk_file.SLOT_BYTES
                try:
                    chunk_file.SLOT_BYTES = chunk_bytes  # type: ignore[misc]
                    checkpointer = None if label == 'old' else new_checkpointer(folder,
                                                                                chunk_bytes)
                    run = (old_checkpoint(folder, node) if checkpointer is None
                           else new_checkpoint(checkpointer, node))
                    times, locked = measure(run, changes, args.checkpoints)
                finally:
                    chunk_file.SLOT_BYTES = slot  # type: ignore[misc]
                    if checkpointer is not None:
                        checkpointer.io.drain()  # its idle I/O thread
                shutil.rmtree(folder, ignore_errors=True)
                cells.append(f'{statistics.median(times):.2f} ({min(times):.2f}-{max(times):.2f})')
                locked_cells.append(f'{statistics.median(locked):.2f}')
            lines.append(f'| {label} | ' + ' | '.join(cells) + ' |')
            locked_lines.append(f'| {label} | ' + ' | '.join(locked_cells) + ' |')
    finally:
        shutil.rmtree(base, ignore_errors=True)
    print(f'CPU ms per checkpoint of {sum(n * n * 4 for n in CELLS) / 2**20:.2f} MiB, median '
          f'(min-max) of {args.checkpoints}')
    print('\n'.join(lines))
    print('\nOf which under the lock (the snapshot), median:')
    print('\n'.join(locked_lines))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
