"""Where a timer goes on after a recovery (node/timer_schedule.py): on its old grid, a tick that
fell due while the node was down fired once, never a burst; with a fake clock."""

from __future__ import annotations

from rory_runtime.node.timer_schedule import Resume, resume

MS = 1_000_000
S = 1_000 * MS


def test_killed_in_the_middle_of_a_period() -> None:
    # Ticks at 10, 11, 12 s; killed at 12.4, back at 12.7: the next tick stays at 13.
    assert resume(12 * S, S, 12_700 * MS) == Resume(False, 13 * S)


def test_back_at_the_edge_of_a_period_the_tick_is_due() -> None:
    assert resume(12 * S, S, 13 * S) == Resume(True, 14 * S)


def test_back_just_before_the_edge() -> None:
    assert resume(12 * S, S, 13 * S - 1) == Resume(False, 13 * S)


def test_a_long_outage_fires_once_and_keeps_the_grid() -> None:
    # Down from 12.4 to 17.3 s at 1 Hz: five ticks missed, one fires at release, then 18 s.
    assert resume(12 * S, S, 17_300 * MS) == Resume(True, 18 * S)


def test_simulation_time_that_stands_still_fires_nothing() -> None:
    # The checkpoint's last tick at sim 40 s; /clock has not moved since.
    assert resume(40 * S, 200 * MS, 40 * S) == Resume(False, 40_200 * MS)


def test_a_clock_that_went_back_waits_one_period_from_now() -> None:
    assert resume(40 * S, S, 3 * S) == Resume(False, 4 * S)


def test_the_grid_of_a_fast_timer_over_many_periods() -> None:
    # 50 Hz, first call at 0.02 s, back at 1.234 s: the grid point after it is 1.24 s.
    assert resume(0, 20 * MS, 1_234 * MS) == Resume(True, 1_240 * MS)


def test_a_zero_period_is_ready_now() -> None:
    assert resume(5 * S, 0, 7 * S) == Resume(False, 7 * S)
