"""rory bundle carries a checkpoint kept in chunks whole: its tar needs no chunk file."""

from __future__ import annotations

import json
import shutil
import struct
import tarfile
from pathlib import Path

import numpy as np
from rclpy.serialization import serialize_message
from std_msgs.msg import Int64

from rory_runtime.bundle import make_bundle
from rory_runtime.codec import decode_vars, encode_vars
from rory_runtime.log import SegmentStore
from rory_runtime.store import FORMAT_VERSION, Checkpoint, CheckpointStore

NODE = 'mapper'


def _write(store: CheckpointStore, seq: int, grid: np.ndarray) -> Path:
    ckpt = Checkpoint(node=NODE, seq=seq, incarnation=1, created_ns=seq, manifest='m',
                      method='rory', cut=seq, windows={}, vars_blob=encode_vars({'grid': grid}))
    return store.write(ckpt)


def _bundled(tmp_path: Path, root: Path) -> tuple[dict[str, object], Checkpoint]:
    out = tmp_path / 'crash.tar'
    manifest = make_bundle(root, NODE, out)
    with tarfile.open(out) as tar:
        names = tar.getnames()
        tar.extractall(tmp_path / 'x', filter='data')
    assert not [name for name in names if 'chunks' in name]
    seq = manifest['checkpoint']['seq']  # type: ignore[index]
    path = tmp_path / 'x' / 'store' / NODE / 'checkpoints' / f'{seq:010d}.ckpt'
    assert struct.unpack_from('<H', path.read_bytes(), 8)[0] == FORMAT_VERSION  # whole
    return manifest, CheckpointStore(tmp_path / 'x' / 'store', NODE).load(path)


def test_the_newest_checkpoint_goes_whole_into_the_bundle(tmp_path: Path) -> None:
    root = tmp_path / '.rory'
    store = CheckpointStore(root, NODE)
    grid = np.arange(1024 * 256, dtype=np.float32).reshape(1024, 256)  # 1 MiB: in chunks
    _write(store, 1, grid)
    grid[3] = -1.0
    newest = _write(store, 2, grid)
    assert (store.dir / 'chunks.dat').exists()
    _, bundled = _bundled(tmp_path, root)
    assert bundled == store.load(newest)
    assert decode_vars(bundled.vars_blob)['grid'].tobytes() == grid.tobytes()


def test_the_copy_kept_at_a_quarantine_still_bundles_after_later_checkpoints(
    tmp_path: Path,
) -> None:
    root = tmp_path / '.rory'
    store = CheckpointStore(root, NODE)
    grid = np.arange(1024 * 256, dtype=np.float32).reshape(1024, 256)
    before = _write(store, 1, grid)
    # What supervisor/poison.py keeps: a copy of the checkpoint file (its chunks stay in the
    # store's chunk file) and the segment holding the message the node died on.
    evidence = root / NODE / 'quarantine' / '_scan-0-9.before'
    (evidence / 'checkpoints').mkdir(parents=True)
    shutil.copy2(before, evidence / 'checkpoints')
    with SegmentStore(tmp_path / 'seg', NODE).open(2) as writer:
        writer.write('/scan', 'std_msgs/msg/Int64', 5, 5, 9, serialize_message(Int64(data=9)))
    shutil.copytree(tmp_path / 'seg' / NODE / 'log' / f'{2:010d}', evidence / 'log' / f'{2:010d}')
    (root / 'events.jsonl').write_text(json.dumps(
        {'kind': 'quarantined', 'node': NODE, 't': 1.0, 'topic': '/scan', 'source_ns': 5,
         'seq': 9}) + '\n')
    for seq in range(2, 6):  # the store's checkpoints go past the message, every chunk changed
        grid += 1.0
        _write(store, seq, grid)
    manifest, bundled = _bundled(tmp_path, root)
    assert manifest['checkpoint']['seq'] == 1  # type: ignore[index]
    assert manifest['note'] is None
    assert bundled == store.load(evidence / 'checkpoints' / before.name)
    assert decode_vars(bundled.vars_blob)['grid'].tobytes() == (grid - 4.0).tobytes()
