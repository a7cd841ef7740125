"""The output judge of the target crash and fault runs: what counts as missing."""

from __future__ import annotations

from rory_eval.faults.target_crash import compare

S = 100_000_000  # 10 Hz outputs


def outputs(stamps: range | list[int]) -> dict[int, bytes]:
    return {k * S: b'pose%d' % k for k in stamps}


def recovered(n: int) -> list[dict[str, object]]:
    return [{'kind': 'recovered', 'total_ms': 500.0}] * n


def test_a_node_silent_in_each_of_two_recoveries_misses_nothing() -> None:
    # Struck twice, released twice: silent for 10-19 and for 40-44; every other output exact.
    reference = outputs(range(100))
    crashed = outputs([k for k in range(100) if not (10 <= k < 20 or 40 <= k < 45)])
    result = compare(reference, crashed, recovered(2))
    assert result.exact and result.missing_after_release == 0


def test_a_gap_beyond_the_recoveries_is_missing() -> None:
    # One recovery, but outputs 60-64 are gone after the release: lost, not an outage.
    reference = outputs(range(100))
    crashed = outputs([k for k in range(100) if not (10 <= k < 20 or 60 <= k < 65)])
    result = compare(reference, crashed, recovered(1))
    assert not result.exact and result.missing_after_release == 5


def test_outputs_before_the_first_release_are_not_required() -> None:
    reference = outputs(range(100))
    crashed = outputs(range(30, 100))  # joined late; the first outage is the start
    assert compare(reference, crashed, recovered(1)).missing_after_release == 0


def test_a_differing_output_is_not_exact() -> None:
    reference = outputs(range(50))
    crashed = outputs([k for k in range(50) if not 10 <= k < 20])
    crashed[30 * S] = b'other'
    result = compare(reference, crashed, recovered(1))
    assert not result.exact and result.common - result.identical == 1
