"""Real targets SIGKILLed under RORY in the simulator publish, after their release, exactly
(byte for byte) what they publish in a run without a crash."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from rory_eval.faults.target_crash import compare, run_under_rory
from rory_eval.targets import TARGETS

pytestmark = pytest.mark.ros


# grid_slam is struck with injected faults in test_target_faults.py.
@pytest.mark.parametrize(('target', 'world'), [('amcl', 'real_room')])
def test_killed_target_goes_on_exactly_as_without_the_crash(
    target: str, world: str, tmp_path: Path, ros_domain: int,
    more_ros_domains: Callable[[], int]
) -> None:
    spec = TARGETS[target]
    # The run without a crash and the crashed run are independent: side by side, each in its
    # own domain (their outputs are stamped with sim time, the same in both).
    with ThreadPoolExecutor(2) as pool:
        reference_run = pool.submit(run_under_rory, spec, world, tmp_path / 'reference',
                                    domain_id=ros_domain, duration=16.0, kill_at=None)
        crashed_run = pool.submit(run_under_rory, spec, world, tmp_path / 'crash',
                                  domain_id=more_ros_domains(), duration=16.0, kill_at=6.0)
        reference, _ = reference_run.result()
        crashed, events = crashed_run.result()
    assert [e['code'] for e in events if e['kind'] == 'exit'] == [-9]
    result = compare(reference, crashed, events)
    assert result.recovered_ms is not None
    # Outputs are muted while it is down; from a warm standby that is ~0.2 s, which may fall
    # between two outputs, so none need be missing.
    assert result.common > 80 and result.crashed <= result.reference
    assert result.exact, result
