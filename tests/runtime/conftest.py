"""Fixtures of the runtime's tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import rclpy
from rclpy.context import Context


@pytest.fixture
def context(ros_domain: int) -> Iterator[Context]:
    """An rclpy context of its own, in the test's domain, shut down afterwards."""
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    yield ctx
    ctx.try_shutdown()
