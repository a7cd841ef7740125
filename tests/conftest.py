"""Shared fixtures. Tests that start ROS processes must not hear each other: each gets its own
ROS_DOMAIN_ID (disjoint ranges per pytest-xdist worker) and discovery stays on localhost."""

from __future__ import annotations

import itertools

import pytest

_next = itertools.count()
_PER_WORKER = 30


@pytest.fixture
def ros_domain(worker_id: str) -> int:
    """A ROS domain id no other test of this session uses."""
    slot = 0 if worker_id == 'master' else int(worker_id.removeprefix('gw')) + 1
    return 10 + slot * _PER_WORKER + next(_next) % _PER_WORKER
