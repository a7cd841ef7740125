"""The target fault campaign's short version: grid_slam, unchanged, in the simulator, struck by
an uncaught exception in a callback and, during that recovery, by a hang; its poses after the
release are byte for byte those of a run without faults. The full campaign is `make faults`."""

from __future__ import annotations

from pathlib import Path

import pytest

from rory_eval.faults.target_faults import Case, run_case, run_target
from rory_eval.targets import TARGETS

pytestmark = pytest.mark.ros


def test_an_exception_then_a_hang_during_its_recovery_leave_the_outputs_exact(
    tmp_path: Path, ros_domain: int
) -> None:
    inst = tmp_path / 'inst'
    reference, events, _ = run_target(TARGETS['grid_slam'], 'office_small', tmp_path / 'ref',
                                      domain_id=ros_domain, instrumented=inst)
    assert [e['kind'] for e in events].count('spawn') == 1 and len(reference) > 100
    case = Case('grid_slam', 'office_small', 'raise', 5.0, ('hang', 0.3))
    outcome = run_case(case, reference, tmp_path / 'faulted', domain_id=ros_domain,
                       instrumented=inst)
    assert outcome.correct, (outcome.error, outcome.comparison)
    assert outcome.strikes == 2 and not outcome.gave_up
    comparison = outcome.comparison
    assert comparison is not None and comparison.common > 50
    log = (tmp_path / 'faulted' / 'run' / 'supervisor.log').read_text()
    assert 'RuntimeError: injected fault' in log  # the exception was the program's own
    assert 'hung: no heartbeat' in log  # and the hang was found by the heartbeat
