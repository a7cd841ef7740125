"""Shared fixtures. Tests that start ROS processes must not hear each other: each gets its own
ROS_DOMAIN_ID (disjoint ranges per pytest-xdist worker) and discovery stays on localhost.

Tests that start ROS processes are marked ``ros``; `make unit` runs the others (-m 'not ros').
A test not marked ``ros`` runs with a ROS_DOMAIN_ID that is not a number (no_ros_process): a
process it starts with its environment (every unmarked test's processes do, 2026-11-28) that
joins ROS (rclpy.init, a node, the supervisor) fails at rcl's init ("ROS_DOMAIN_ID is not an
integral number") instead of passing unmarked. Importing rclpy, serializing messages, and an
in-process context made with an explicit domain_id (the ros_domain fixture) stay allowed."""

from __future__ import annotations

import fcntl
import itertools
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

import pytest

_next = itertools.count()
# Keep every id <= 100: a domain's ports are 7400 + 250 x id, and above 100 they lie in
# Linux's ephemeral range (32768-60999), which every outgoing socket draws from. At base 150,
# while an evaluation ran, one replay test saw five restarts in a row never heard by the
# supervisor; at base 40 it passed.
_FIRST_ID, _END_ID = 10, 100
_SPAN = 15
# Two pytest sessions on one machine at once (two checkouts, two developers, two xdist
# workers) must not share domains: each process that needs one claims a range of _SPAN ids
# with an exclusive lock on a file under _CLAIMS, held until the process ends. Sessions that
# shared default ranges crossed their messages (a node "applied twice" numbers another
# session's publisher sent). RORY_TEST_DOMAIN_BASE and RORY_TEST_DOMAIN_SPAN, when set, give
# the ranges instead (base + slot x span per worker), unlocked.
_CLAIMS = Path(tempfile.gettempdir()) / 'rory-test-domains'
_claimed: list[tuple[int, int]] = []  # this process's (base, span), once claimed
_claim_files: list[IO[bytes]] = []  # held open: closing one would release its lock


def _range(worker_id: str) -> tuple[int, int]:
    if _claimed:
        return _claimed[0]
    if 'RORY_TEST_DOMAIN_BASE' in os.environ:
        base = int(os.environ['RORY_TEST_DOMAIN_BASE'])
        span = int(os.environ.get('RORY_TEST_DOMAIN_SPAN', '30'))
        slot = 0 if worker_id == 'master' else int(worker_id.removeprefix('gw')) + 1
        _claimed.append((base + slot * span, span))
        return _claimed[0]
    _CLAIMS.mkdir(exist_ok=True)
    for base in range(_FIRST_ID, _END_ID - _SPAN + 1, _SPAN):
        claim = (_CLAIMS / f'{base}.lock').open('ab')
        try:
            fcntl.flock(claim, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            claim.close()
            continue
        _claim_files.append(claim)
        _claimed.append((base, _SPAN))
        return _claimed[0]
    raise RuntimeError(f'every range of ROS domain ids {_FIRST_ID}-{_END_ID - 1} is held by '
                       f'another test process ({_CLAIMS}); set RORY_TEST_DOMAIN_BASE')


def _domain(worker_id: str) -> int:
    base, span = _range(worker_id)
    return base + next(_next) % span


NO_ROS_DOMAIN = 'none: a test not marked ros starts no ROS process'


@pytest.fixture(autouse=True)
def no_ros_process(request: pytest.FixtureRequest) -> Iterator[None]:
    """Unless the test is marked ros, the processes it starts inherit a ROS_DOMAIN_ID that
    rcl refuses."""
    if request.node.get_closest_marker('ros') is not None:
        yield
        return
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv('ROS_DOMAIN_ID', NO_ROS_DOMAIN)
        yield


@pytest.fixture
def ros_domain(worker_id: str) -> int:
    """A ROS domain id no other test of this session uses."""
    return _domain(worker_id)


@pytest.fixture
def more_ros_domains(worker_id: str) -> Callable[[], int]:
    """Further domain ids, one a call, for a test that runs several ROS graphs at once."""
    return lambda: _domain(worker_id)


@pytest.fixture(scope='module')
def module_ros_domains(worker_id: str) -> Callable[[], int]:
    """Domain ids, one a call, for a module-scoped fixture that runs ROS graphs shared by
    several tests."""
    return lambda: _domain(worker_id)


# Tests that run the MuJoCo simulator with a ROS stack in real time. Two of them side by side
# starve each other on a 2-core machine (three output-count checks failed that way), so under
# `make test` (--dist loadgroup) they run one after another on one worker while the other
# worker takes the rest, one test at a time.
SIMULATOR_TESTS = frozenset({
    'eval/harness/test_simrun.py',
    'integration/test_eval_quick.py',
    'integration/test_fleet.py',
    'integration/test_stack.py',
    'integration/test_target_crash.py',
    'integration/test_target_faults.py',
    'sim/test_sim_ros.py',
    'targets/test_amcl_sim.py',
    'targets/test_depth_mapper_sim.py',
    'targets/test_graph_slam_sim.py',
    'targets/test_grid_slam_sim.py',
    'targets/test_lama_local_sim.py',
    'targets/test_navigator_sim.py',
})
# Modules whose tests share results computed once per process (functools.cache: a whole
# route driven through a target's core, e.g. test_graph_slam_core's route_run; or a
# module-scoped fixture, test_depth_mapper_core's real_room_run). Handed out one test at a
# time, their tests landed on both workers and each computed the same routes (68 s of test
# time for graph_slam_core's, 38 s in one process): each runs on one worker.
SHARED_CACHE_TESTS = frozenset({
    'targets/test_amcl_core.py',
    'targets/test_depth_mapper_core.py',
    'targets/test_graph_slam_core.py',
    'targets/test_grid_slam_core.py',
    'targets/test_lama_local_core.py',
})
_TESTS = Path(__file__).parent


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        path = item.path.relative_to(_TESTS).as_posix()
        if path in SIMULATOR_TESTS:
            item.add_marker(pytest.mark.xdist_group('simulator'))
        elif path in SHARED_CACHE_TESTS:
            item.add_marker(pytest.mark.xdist_group(path))
