"""checkpoint_cpu_bench: the changes it makes, one short run of both paths, and the whole
bench once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rory_eval.bench import checkpoint_cpu_bench as bench
from rory_runtime import chunks
from rory_runtime.codec import decode_vars
from rory_runtime.store import CheckpointStore


def _changed_chunks(before: list[np.ndarray], after: list[np.ndarray], step: int) -> int:
    count = 0
    for old, new in zip(before, after, strict=True):
        a, b = old.reshape(-1).view(np.uint8), new.reshape(-1).view(np.uint8)
        count += sum(not np.array_equal(a[o:o + step], b[o:o + step])
                     for o in range(0, a.size, step))
    return count


def test_a_percentage_changes_that_many_chunks_and_a_room_the_same_window() -> None:
    node = bench._Node(seed=0)
    step = chunks.CHUNK_BYTES
    total = sum(chunks.chunk_count(g.nbytes, step) for g in node.mapper.log_odds)
    rng = np.random.default_rng(0)
    for percent, expected in ((0, 0), (1, 1), (10, round(total / 10)), (100, total)):
        before = [g.copy() for g in node.mapper.log_odds]
        bench.change(node, percent, step, rng)
        assert _changed_chunks(before, node.mapper.log_odds, step) == expected
    before = [g.copy() for g in node.mapper.log_odds]
    bench.change_room(node, (100, 200))
    diff = node.mapper.log_odds[0] != before[0]
    assert diff.sum() == 120 * 160 and diff[100:220, 200:360].all()


def test_both_paths_checkpoint_the_state(tmp_path: Path) -> None:
    node = bench._Node(seed=1)
    checkpointer = bench.new_checkpointer(tmp_path / 'new', chunks.CHUNK_BYTES)
    try:
        times, locked = bench.measure(bench.new_checkpoint(checkpointer, node),
                                      lambda: bench.change(node, 10, chunks.CHUNK_BYTES,
                                                           np.random.default_rng(0)), 2)
    finally:
        checkpointer.io.drain()
    assert len(times) == 2
    assert all(0 < lock < total for lock, total in zip(locked, times, strict=True))
    latest = CheckpointStore(tmp_path / 'new', 'grid_slam').latest_valid()
    assert latest is not None and latest.seq == 4
    grids = decode_vars(latest.vars_blob)['mapper.log_odds']
    assert [g.tobytes() for g in grids] == [g.tobytes() for g in node.mapper.log_odds]
    old_times, _ = bench.measure(bench.old_checkpoint(tmp_path / 'old', node), lambda: None, 1)
    assert len(old_times) == 1
    assert len(list((tmp_path / 'old' / 'grid_slam' / 'checkpoints').glob('*.ckpt'))) == 2


def test_the_bench_runs_both_paths_at_each_pattern_and_prints_its_tables(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Its node is a stand-in (_Node): the runtime's Checkpointer must still take it whole.
    assert bench.main(['--checkpoints', '1', '--changed', '1', '--room',
                       '--dir', str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert out.count('| path | 1 % changed | a room |') == 2
    assert out.count('| old | ') == 2
    assert out.count(f'| chunks of {chunks.CHUNK_BYTES // 1024} KiB | ') == 2
    assert list(tmp_path.iterdir()) == []  # its folder removed
