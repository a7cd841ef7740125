"""A node's checkpoints failing, as the supervisor reads it: an ERROR status whose ``checkpoint``
says a checkpoint was not taken (ErrorStatus.checkpoint_failed) marks them failing, in the node's
health and /diagnostics, until a CHECKPOINT status; any other error does not. Driven with fakes
(fake_supervisor.py): no ROS process."""

from __future__ import annotations

from pathlib import Path

import pytest
from fake_supervisor import Harness

from rory_runtime.protocol import CheckpointFailure, CheckpointStatus, ErrorStatus
from rory_runtime.supervisor.states import NodeState

SKIPPED = ErrorStatus(message="checkpoint skipped: variable 'seen' is a defaultdict",
                      checkpoint=CheckpointFailure.SKIPPED)
NOT_WRITTEN = ErrorStatus(message='checkpoint 12 not written: [Errno 28] No space left on device',
                          checkpoint=CheckpointFailure.NOT_WRITTEN)
WRITTEN = CheckpointStatus(seq=13, cut=None, size=64, stall_ms=0.1, total_ms=1.0)


def _running(tmp_path: Path) -> Harness:
    h = Harness(tmp_path, method='checkpoint')
    h.node.start()
    h.beat()
    h.up()
    assert h.node.sm.state == NodeState.RUNNING
    return h


@pytest.mark.parametrize('failure', [SKIPPED, NOT_WRITTEN], ids=['skipped', 'not_written'])
def test_a_checkpoint_not_taken_marks_the_checkpoints_failing_until_one_is_written(
    tmp_path: Path, failure: ErrorStatus,
) -> None:
    h = _running(tmp_path)
    assert h.node.current.checkpoint_error is None
    h.status(failure)
    assert h.node.current.checkpoint_error == failure.message
    assert h.sup.events_log.of('error')[-1]['message'] == failure.message
    h.status(WRITTEN)
    assert h.node.current.checkpoint_error is None


@pytest.mark.parametrize('message', [
    'cannot log a message of /scan: disk full',
    'checkpoint refused: /store/n/checkpoints/0000000003.ckpt: bad checksum',
])
def test_any_other_error_leaves_the_checkpoints_as_they_were(tmp_path: Path,
                                                             message: str) -> None:
    h = _running(tmp_path)
    h.status(ErrorStatus(message=message))
    assert h.node.current.checkpoint_error is None
    assert h.sup.events_log.of('error')[-1]['message'] == message  # logged all the same
    h.status(SKIPPED)
    h.status(ErrorStatus(message=message))
    assert h.node.current.checkpoint_error == SKIPPED.message


def test_the_supervisor_reads_the_field_not_the_message(tmp_path: Path) -> None:
    h = _running(tmp_path)
    h.status(ErrorStatus(message=SKIPPED.message))  # the words of a failure, not its kind
    assert h.node.current.checkpoint_error is None
    h.status(ErrorStatus(message='the disk is full', checkpoint=CheckpointFailure.NOT_WRITTEN))
    assert h.node.current.checkpoint_error == 'the disk is full'
