"""Tests of restart pacing (RestartPolicy) and exit descriptions."""

from __future__ import annotations

import signal

import pytest

from rory_runtime.supervisor.config import Backoff
from rory_runtime.supervisor.process import RestartPolicy, describe_exit

BACKOFF = Backoff(initial=0.25, step=1.0, maximum=5.0, stable_after=10.0, max_restarts=8)


def crash_loop(policy: RestartPolicy, count: int, ran_for: float = 0.0) -> list[float | None]:
    return [policy.on_crash(ran_for) for _ in range(count)]


def test_first_crash_restarts_after_initial_delay() -> None:
    assert RestartPolicy(BACKOFF).on_crash(0.0) == 0.25


def test_first_crash_after_a_stable_run_restarts_after_initial_delay() -> None:
    assert RestartPolicy(BACKOFF).on_crash(3600.0) == 0.25


def test_consecutive_crashes_back_off_exponentially_up_to_maximum() -> None:
    delays = crash_loop(RestartPolicy(BACKOFF), 8, ran_for=1.0)
    assert delays == [0.25, 1.0, 2.0, 4.0, 5.0, 5.0, 5.0, 5.0]


def test_backoff_doubles_from_step() -> None:
    backoff = Backoff(initial=0.0, step=0.5, maximum=100.0, stable_after=10.0, max_restarts=10)
    delays = crash_loop(RestartPolicy(backoff), 7)
    assert delays == [0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0]


def test_default_backoff() -> None:
    delays = crash_loop(RestartPolicy(Backoff()), 6)
    assert delays == [0.0, 0.5, 1.0, 2.0, 4.0, None]


def test_count_resets_after_a_run_of_stable_after() -> None:
    policy = RestartPolicy(BACKOFF)
    assert crash_loop(policy, 3) == [0.25, 1.0, 2.0]
    assert policy.on_crash(10.0) == 0.25  # exactly stable_after counts as stable
    assert policy.consecutive == 1
    assert policy.on_crash(0.5) == 1.0


def test_run_just_short_of_stable_after_does_not_reset() -> None:
    policy = RestartPolicy(BACKOFF)
    assert crash_loop(policy, 2) == [0.25, 1.0]
    assert policy.on_crash(9.999) == 2.0
    assert policy.consecutive == 3


def test_gives_up_after_max_restarts_consecutive_crashes() -> None:
    backoff = Backoff(initial=0.0, step=0.1, maximum=1.0, stable_after=10.0, max_restarts=3)
    policy = RestartPolicy(backoff)
    assert crash_loop(policy, 3) == [0.0, 0.1, 0.2]
    assert policy.on_crash(0.0) is None


@pytest.mark.parametrize('max_restarts', [1, 2, 5])
def test_exactly_max_restarts_restarts_are_granted(max_restarts: int) -> None:
    backoff = Backoff(max_restarts=max_restarts)
    delays = crash_loop(RestartPolicy(backoff), max_restarts + 1)
    assert all(d is not None for d in delays[:-1])
    assert delays[-1] is None


def test_never_gives_up_when_crashes_are_separated_by_stable_runs() -> None:
    """Unlike launch's respawn, whose retry count never resets."""
    backoff = Backoff(initial=0.5, step=1.0, maximum=8.0, stable_after=10.0, max_restarts=2)
    policy = RestartPolicy(backoff)
    for _ in range(50):
        assert policy.on_crash(60.0) == 0.5


def test_short_loops_between_stable_runs_never_give_up() -> None:
    backoff = Backoff(initial=0.0, step=1.0, maximum=8.0, stable_after=10.0, max_restarts=2)
    policy = RestartPolicy(backoff)
    for _ in range(10):
        assert policy.on_crash(30.0) == 0.0  # after a stable run
        assert policy.on_crash(1.0) == 1.0  # crash loop: second consecutive
    assert policy.on_crash(1.0) is None  # third consecutive > max_restarts


@pytest.mark.parametrize(
    ('code', 'text'),
    [
        (-signal.SIGKILL, 'killed by SIGKILL'),
        (-signal.SIGTERM, 'killed by SIGTERM'),
        (-signal.SIGSEGV, 'killed by SIGSEGV'),
        (-signal.SIGABRT, 'killed by SIGABRT'),
        (-200, 'killed by signal 200'),
        (0, 'exit status 0'),
        (1, 'exit status 1'),
        (3, 'exit status 3'),
        (255, 'exit status 255'),
    ],
)
def test_describe_exit(code: int, text: str) -> None:
    assert describe_exit(code) == text
