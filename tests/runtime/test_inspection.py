"""rory inspect: a store listed and a checkpoint shown, from files alone."""

from __future__ import annotations

import dataclasses
import io
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.serialization import serialize_message
from std_msgs.msg import Int64

from rory_runtime.codec import encode_vars
from rory_runtime.inspection import main
from rory_runtime.log import SegmentStore
from rory_runtime.node import parameters as node_parameters
from rory_runtime.store import Checkpoint, CheckpointStore

NODE = 'mapper'


def _checkpoint(seq: int, values: dict[str, object]) -> Checkpoint:
    return Checkpoint(node=NODE, seq=seq, incarnation=2, created_ns=1_800_000_000_000_000_000,
                      manifest='sha256:abc', method='rory', cut=seq + 10,
                      windows={'/scan': [(100, 1), (200, 2)]}, vars_blob=encode_vars(values))


@pytest.fixture
def store(tmp_path: Path) -> Path:
    root = tmp_path / '.rory'
    checkpoints = CheckpointStore(root, NODE, keep=3)
    checkpoints.write(_checkpoint(1, {'grid': np.zeros((4, 4), dtype=np.float32), 'scans': 1}))
    checkpoints.write(_checkpoint(2, {'grid': np.eye(4, dtype=np.float32), 'scans': 2,
                                      'levels': [np.ones(3), np.zeros(2)]}))
    segments = SegmentStore(root, NODE)
    with segments.open(12) as writer:
        for k in range(3):
            writer.write('/scan', 'std_msgs/msg/Int64', 10**18 + k, 10**18 + k, k + 1,
                         serialize_message(Int64(data=k)))
    return root


def _run(*argv: str) -> tuple[int, str]:
    out = io.StringIO()
    return main(list(argv), out=out), out.getvalue()


def test_the_listing_shows_checkpoints_variables_and_segments(store: Path) -> None:
    code, text = _run(str(store))
    assert code == 0
    assert 'node mapper' in text and 'checkpoints: 2' in text
    assert 'seq 2:' in text and 'cut 12' in text and 'manifest sha256:abc' in text
    assert 'grid: ndarray float32 (4, 4)' in text and 'scans: int' in text
    assert 'levels: list of 2' in text
    assert 'log segments: 1' in text and 'segment 12:' in text and '/scan 3' in text


def test_a_corrupt_checkpoint_is_listed_as_refused_with_the_reason(store: Path) -> None:
    path = CheckpointStore(store, NODE).path(2)
    path.write_bytes(path.read_bytes()[:-10])
    code, text = _run(str(store))
    assert code == 0
    assert '0000000002.ckpt' in text and 'REFUSED' in text
    code, text = _run(str(store), '--node', NODE, '--checkpoint', 'latest')
    assert code == 0 and 'seq 1,' in text  # latest falls back to the older valid one


def test_a_checkpoint_is_shown_variable_by_variable(store: Path) -> None:
    code, text = _run(str(store), '--node', NODE, '--checkpoint', 'latest')
    assert code == 0
    assert 'seq 2' in text and 'window /scan: 2 message identities' in text
    assert 'grid = ndarray float32 shape (4, 4), min 0 max 1 mean 0.25, nonzero 4' in text
    assert 'scans = 2' in text
    assert "[0] ndarray float64 shape (3,)" in text  # a list of arrays, one line each


def test_a_checkpoints_parameters_and_lifecycle_state_follow_its_variables(
    tmp_path: Path,
) -> None:
    root = tmp_path / '.rory'
    CheckpointStore(root, NODE).write(dataclasses.replace(
        _checkpoint(1, {'scans': 1}), lifecycle='active',
        parameters=node_parameters.pack([Parameter('gain', value=2.5)])))
    code, text = _run(str(root), '--node', NODE, '--checkpoint', 'latest')
    assert code == 0
    lines = text.splitlines()
    assert lines[-3:] == ['  scans = 1', '  lifecycle state: active', '  parameter gain = 2.5']


def test_a_dataclass_of_code_not_loaded_here_is_shown_by_its_fields(
    store: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    module = types.ModuleType('node_code_elsewhere')

    @dataclasses.dataclass
    class Pose:
        x: float
        y: float

    Pose.__module__ = module.__name__
    Pose.__qualname__ = 'Pose'
    module.Pose = Pose  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, module.__name__, module)
    CheckpointStore(store, NODE, keep=3).write(_checkpoint(3, {'pose': Pose(1.0, 2.0)}))
    monkeypatch.delitem(sys.modules, module.__name__)
    code, text = _run(str(store), '--node', NODE, '--checkpoint', '3')
    assert code == 0
    assert "shown without the node's code" in text
    assert "'<dataclass>': 'node_code_elsewhere.Pose', 'x': 1.0, 'y': 2.0" in text


def test_a_folder_that_is_not_a_node_id_is_not_a_node(store: Path) -> None:
    # No supervisor makes it (protocol.NODE_ID_RE): a folder put there by hand is not listed.
    (store / 'my-node' / 'checkpoints').mkdir(parents=True)
    code, text = _run(str(store))
    assert code == 0 and 'node mapper' in text and 'my-node' not in text


@pytest.mark.parametrize(('argv', 'message'), [
    (['{store}/../nowhere'], 'not a directory'),
    (['{store}', '--node', 'other'], "no node 'other' (nodes here: mapper)"),
    (['{store}', '--node', NODE, '--checkpoint', '7'], 'no checkpoint 7 (kept: 2, 1)'),
    (['{store}', '--node', NODE, '--checkpoint', 'newest'], 'latest or a number'),
    (['{store}', '--checkpoint', 'latest'], '--checkpoint needs --node'),
])
def test_what_is_not_there_is_named(store: Path, argv: list[str], message: str,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    code, _ = _run(*(a.format(store=store) for a in argv))
    assert code == 2
    assert message in capsys.readouterr().err


def test_a_reader_that_stops_early_gets_no_traceback(store: Path) -> None:
    # `rory inspect STORE | head -1`: the pipe closes while the listing is still being written.
    proc = subprocess.Popen([sys.executable, '-m', 'rory_runtime.cli', 'inspect', str(store)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.readline()
    proc.stdout.close()
    assert proc.wait(timeout=30) == 0
    assert proc.stderr.read() == b''


def test_a_checkpoint_in_chunks_is_listed_and_shown_like_any_other(tmp_path: Path) -> None:
    root = tmp_path / '.rory'
    grid = np.zeros((1024, 256), dtype=np.float32)  # 1 MiB: kept in chunks
    grid[5, 5] = 2.0
    CheckpointStore(root, NODE).write(_checkpoint(1, {'grid': grid, 'scans': 3}))
    assert (root / NODE / 'checkpoints' / 'chunks.dat').exists()
    code, text = _run(str(root))
    assert code == 0
    assert 'seq 1:' in text and ' + 1.0 MB in chunks' in text
    assert 'grid: ndarray float32 (1024, 256)' in text and 'scans: int' in text
    code, text = _run(str(root), '--node', NODE, '--checkpoint', 'latest')
    assert code == 0
    assert 'grid = ndarray float32 shape (1024, 256), min 0 max 2' in text
    assert 'scans = 3' in text
    (root / NODE / 'checkpoints' / 'chunks.dat').unlink()
    code, text = _run(str(root))
    assert 'REFUSED' in text and 'missing chunks: cannot open the chunk file' in text
