"""What the node tells its supervisor (node/reporting.py): each error once, as an ERROR status."""

from __future__ import annotations

from rory_runtime.node.reporting import Reporter
from rory_runtime.protocol import CheckpointFailure, ErrorStatus, Status


def test_an_error_is_sent_once_and_says_whether_a_checkpoint_was_not_taken() -> None:
    reporter = Reporter('n', 1, None, None)
    sent: list[Status] = []
    reporter.status = sent.append  # type: ignore[method-assign]
    reporter.error('checkpoint skipped: x', CheckpointFailure.SKIPPED)
    reporter.error('checkpoint skipped: x', CheckpointFailure.SKIPPED)
    reporter.error('cannot log a message of /scan: disk full')
    assert sent == [ErrorStatus(message='checkpoint skipped: x',
                                checkpoint=CheckpointFailure.SKIPPED),
                    ErrorStatus(message='cannot log a message of /scan: disk full')]
    assert reporter.reported_errors == {'checkpoint skipped: x',
                                        'cannot log a message of /scan: disk full'}


def test_without_the_supervisors_socket_statuses_are_dropped() -> None:
    reporter = Reporter('n', 1, None, None)
    reporter.status(ErrorStatus(message='nobody hears this'))  # no socket: nothing to send to
    reporter.close()
