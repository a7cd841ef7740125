"""The node's checkpoints and the log segments they cut (docs/architecture.md, "Checkpoints").

A checkpoint is taken under the runtime's lock, in one step, so that it falls between two
callbacks: the key variables are copied (arrays into the buffers of the last packed checkpoint,
:class:`codec.ArrayPool`, only the chunks that changed), the segment being written is detached
(the *cut*: the highest segment number whose messages the snapshot includes) and the per-topic
windows of applied identities are copied. The rest runs in order on the ``rory-io`` thread
(:class:`IoWorker`): close the detached segment, pack (large arrays by reference), hash the
changed chunks (chunks.py), write the checkpoint atomically with the chunks no kept checkpoint
holds yet, then prune the segments the older checkpoint kept no longer needs.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from typing import Protocol

from rclpy.node import Node

from .. import chunks, codec, freshness
from ..errors import CheckpointError, CodecError, LogError
from ..log import SegmentStore, SegmentWriter
from ..protocol import CheckpointFailure, CheckpointStatus, Method, Status
from ..store import Checkpoint, CheckpointStore
from ..threads import name_this_thread
from . import event_clock
from . import lifecycle as node_lifecycle
from . import parameters as node_parameters
from .state import CheckpointSpec, read_state

_logger = logging.getLogger('rory.runtime')


class AppliedWindow(Protocol):
    """What a checkpoint copies of a topic's window of applied identities: oldest first."""

    def snapshot(self) -> list[tuple[int, int]]: ...


class IoWorker:
    """Runs checkpoint and segment I/O in order, off the node's executor thread.

    Only the snapshot needs the node paused; closing a segment (its MCAP summary and
    metadata.yaml), writing a checkpoint with fsync and pruning can follow in the background.
    Order is what keeps them safe: segments are pruned only after the newer checkpoint is
    durable, so a crash at any point leaves a checkpoint whose segments are all there.
    """

    def __init__(self) -> None:
        self._jobs: queue.SimpleQueue[Callable[[], None] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name='rory-io', daemon=True)
        self._thread.start()

    def submit(self, job: Callable[[], None]) -> None:
        self._jobs.put(job)

    def _run(self) -> None:
        name_this_thread('rory-io')
        while (job := self._jobs.get()) is not None:
            try:
                job()
            except Exception:
                _logger.exception('[rory] background I/O failed')

    def drain(self, timeout: float = 5.0) -> None:
        """Finish queued jobs and stop."""
        self._jobs.put(None)
        self._thread.join(timeout)


def node_clock_reading(node: Node) -> freshness.ClockReading:
    """The node's own ROS clock, read live (never a replayed reading)."""
    clock = node.get_clock()
    sim = bool(getattr(clock, 'ros_time_is_active', False))
    return freshness.ClockReading(int(event_clock.original_now(clock).nanoseconds), sim)


class Checkpointer:
    """The segment being written, its rotation, and the checkpoints that cut the log.

    Args:
        spec: The node's key variables and manifest.
        method: What the node keeps: checkpoints, a log, or both.
        node_id: The node's name in the supervisor config (written into each checkpoint).
        incarnation: This process's number (written into each checkpoint).
        lock: The runtime's lock, under which every user callback runs.
        checkpoints: Where checkpoints are written.
        segments: Where log segments are written.
        error: Reports an error (the runtime's ERROR status): a checkpoint not taken, when
            ``failed`` is not given.
        failed: Reports a checkpoint not taken, and why (the runtime's ERROR status, typed).
        status: Sends a status to the supervisor (CHECKPOINT).
        timers: The node's timers as a checkpoint keeps them (``NodeTimers.snapshot``), read
            under the lock with the variables.
    """

    def __init__(
        self, spec: CheckpointSpec, method: Method, node_id: str, incarnation: int,
        lock: threading.RLock, checkpoints: CheckpointStore, segments: SegmentStore, *,
        error: Callable[[str], None], status: Callable[[Status], None],
        timers: Callable[[Node], bytes] | None = None,
        failed: Callable[[str, CheckpointFailure], None] | None = None,
    ) -> None:
        self.spec = spec
        self.method = method
        self.node_id = node_id
        self.incarnation = incarnation
        self.lock = lock
        self.checkpoints = checkpoints
        self.segments = segments
        self._failed = failed or (lambda message, _why: error(message))
        self._status = status
        self.timers = timers
        self.writer: SegmentWriter | None = None
        self.next_segment = 1
        self.previous_cut: int | None = None
        self._next_seq = 0  # set at start-up from the store (number_from_store)
        self.io = IoWorker()
        # The buffers of the last written checkpoint's large arrays, for the next snapshot,
        # with the digests of their chunks: the next snapshot copies the changed ones only.
        self.array_pool = codec.ArrayPool(chunks.CHUNK_BYTES)
        self.chunker = chunks.Chunker()  # used on the I/O thread only

    def number_from_store(self) -> None:
        """Number the next checkpoint after the newest one on disk (at start-up)."""
        self._next_seq = self.checkpoints.next_seq()

    def resume_after(self, cut: int | None) -> None:
        """The restored checkpoint's cut: the next checkpoint prunes the segments up to it."""
        self.previous_cut = cut

    def log_from(self, next_segment: int) -> None:
        """Number the segments from ``next_segment`` on (the supervisor's, at release: R and
        every segment before it are taken)."""
        self.next_segment = max(self.next_segment, next_segment)

    def segment(self) -> SegmentWriter:
        """The segment being written, opened at the first record after a rotation."""
        if self.writer is None:
            self.writer = self.segments.open(self.next_segment)
            self.next_segment += 1
        return self.writer

    def rotate(self) -> tuple[int, SegmentWriter | None]:
        """Start a new segment at the next message.

        Returns:
            The number of the last segment absorbed so far, and the detached writer of the
            current segment, still to be closed (its messages are already in the OS).
        """
        writer, self.writer = self.writer, None
        return self.next_segment - 1, writer

    def rotate_and_close(self) -> None:
        """Rotate, and close the detached segment on the I/O thread (the replay method: no
        checkpoints, but segments stay bounded in size)."""
        with self.lock:
            _, writer = self.rotate()
        if writer is not None:
            self.io.submit(writer.close)

    def close_segment(self) -> None:
        """Seal the segment being written (at exit), so the bag is complete."""
        with self.lock:
            if self.writer is not None:
                with contextlib.suppress(LogError):
                    self.writer.close()
                self.writer = None

    def prime_array_pool(self, node: Node) -> None:
        """Fill the array pool from the node's variables, so the first snapshot's copies land in
        memory already written (the runtime submits this to the I/O thread at release)."""
        # A variable that cannot be read is the checkpoint's to report.
        with contextlib.suppress(CodecError):
            self.array_pool.prime(read_state(self.spec, node))

    def take(self, node: Node, windows: Mapping[str, AppliedWindow]) -> Callable[[], None] | None:
        """Snapshot the node now, under the lock; returns the job that writes it (None when
        the snapshot was refused)."""
        began = time.perf_counter()
        with self.lock:
            # The snapshot: the only part that needs the node paused between two callbacks.
            # Arrays are copied here and packed by the I/O thread, so a 16 MB grid costs the
            # executor one pass over it (compared with the last snapshot's buffer, the changed
            # chunks copied), not the several copies packing makes.
            try:
                snapshot = codec.snapshot_vars(read_state(self.spec, node), self.array_pool)
            except CodecError as err:
                self._failed(f'checkpoint skipped: {err}', CheckpointFailure.SKIPPED)
                return None
            cut, writer = self.rotate() if self.method.logs else (None, None)
            window_copy = {topic: w.snapshot() for topic, w in windows.items()}
            parameters = node_parameters.snapshot(node)
            lifecycle = node_lifecycle.state_of(node)
            timers = b'' if self.timers is None else self.timers(node)
            taken_on = node_clock_reading(node)
            prune_through, self.previous_cut = self.previous_cut, cut
            seq, self._next_seq = self._next_seq, self._next_seq + 1
        stall_ms = (time.perf_counter() - began) * 1000.0
        created_ns = time.time_ns()

        def persist() -> None:
            if writer is not None:
                writer.close()
            ckpt = Checkpoint(
                node=self.node_id,
                seq=seq,
                incarnation=self.incarnation,
                created_ns=created_ns,
                manifest=self.spec.manifest,
                method=self.method.value,
                cut=cut,
                windows=window_copy,
                vars_blob=b'',  # the variables go to the store as parts
                parameters=parameters,
                lifecycle=lifecycle,
                timers=timers,
                clock_ns=max(taken_on.ns, 0),
                sim_time=taken_on.sim,
                freshness=tuple((r.key, r.max_age, r.on_stale) for r in self.spec.freshness),
            )
            try:
                parts = self.chunker.split(codec.pack_pieces(snapshot))
                self.checkpoints.write(ckpt, parts=parts)
            except (CodecError, OSError, CheckpointError) as err:
                self._failed(f'checkpoint {seq} not written: {err}', CheckpointFailure.NOT_WRITTEN)
                return
            finally:
                # Only now: the chunks written were views of the snapshot's buffers.
                self.array_pool.refill(snapshot)
            # The older checkpoint kept needs the segments after its cut; older ones go.
            if self.method.logs and prune_through is not None:
                self.segments.drop_through(prune_through)
            self._status(CheckpointStatus(
                seq=seq,
                cut=cut,
                size=chunks.size_of(parts),
                stall_ms=stall_ms,
                total_ms=(time.perf_counter() - began) * 1000.0,
            ))

        return persist
