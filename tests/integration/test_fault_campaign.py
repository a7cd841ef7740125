"""The fault campaign's short version: every fault kind, and second strikes during recovery.

Each case strikes the fault-injectable integrator under RORY (SIGKILL, SIGSEGV, SIGABRT, an
uncaught exception, a hang found by the heartbeat); the node must end with exactly 1..N.
The full campaign is ``make faults``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from rory_eval.faults.fault_campaign import Case, run_case, short_plan

pytestmark = pytest.mark.ros


@pytest.mark.parametrize('case', short_plan(), ids=Case.label)
def test_fault_is_recovered_exactly(case: Case, tmp_path: Path, ros_domain: int) -> None:
    outcome = run_case(case, tmp_path / 'run', ros_domain)
    assert outcome.correct, (
        f'lost {outcome.lost} ({outcome.missing}), applied twice {outcome.duplicated}, '
        f'gave up {outcome.gave_up} {outcome.error}'
    )
    # Every strike is covered by exactly one recovery: a second strike before the release
    # continues the same recovery, one after it (a warm standby releases in ~0.1 s) starts its
    # own. (test_recovery_exact strikes deterministically during a replay.)
    assert outcome.strikes == (1 if case.second is None else 2)
    assert outcome.covered == outcome.strikes, outcome
    assert 1 <= outcome.recoveries <= outcome.strikes
