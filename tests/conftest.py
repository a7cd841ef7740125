"""Shared fixtures. Tests that start ROS processes must not hear each other: each gets its own
ROS_DOMAIN_ID (disjoint ranges per pytest-xdist worker) and discovery stays on localhost."""

from __future__ import annotations

import itertools
import os

import pytest

_next = itertools.count()
# Two pytest sessions on one machine at once (two checkouts, two developers) must not share
# domains: give the second one another base and span, e.g. RORY_TEST_DOMAIN_BASE=120
# RORY_TEST_DOMAIN_SPAN=20 (ids 120..139 per worker; Fast DDS takes ids up to 232).
_BASE = int(os.environ.get('RORY_TEST_DOMAIN_BASE', '10'))
_PER_WORKER = int(os.environ.get('RORY_TEST_DOMAIN_SPAN', '30'))


@pytest.fixture
def ros_domain(worker_id: str) -> int:
    """A ROS domain id no other test of this session uses."""
    slot = 0 if worker_id == 'master' else int(worker_id.removeprefix('gw')) + 1
    return _BASE + slot * _PER_WORKER + next(_next) % _PER_WORKER
