"""The scripted driver completes each world's route without collision (synchronous, no ROS)."""

from __future__ import annotations

import itertools
import math

import pytest

from sim.driver import RouteFollower, run_offline
from sim.worlds import WORLDS, get_world


@pytest.mark.parametrize('name', sorted(WORLDS))
def test_driver_completes_the_route_without_collision(name: str) -> None:
    summary = run_offline(name, seed=0)
    assert summary['completed'], summary
    assert summary['collisions'] == 0, summary['collision_events']
    assert 60.0 <= summary['route_time'] <= 130.0
    world = get_world(name)
    end = summary['final_pose']
    assert math.hypot(end['x'] - world.route[-1][0], end['y'] - world.route[-1][1]) < 0.1
    # The path followed the route: every recorded point is near the route's polyline.
    rows = [line.split(',') for line in summary['path_csv'].splitlines()[1:]]
    pts = [(world.start.x, world.start.y), *world.route]
    for row in rows:
        x, y = float(row[1]), float(row[2])
        assert _distance_to_polyline(x, y, pts) < 0.25, (x, y)
    # Odometry alone is visibly wrong by the end, while ground truth followed the route.
    assert summary['odometry_error']['position'] > 0.2


def test_follower_turns_in_place_then_drives_and_stops_at_the_end() -> None:
    follower = RouteFollower([(1.0, 0.0), (1.0, 1.0)])
    v, w = follower.command(0.0, 0.0, 2.0)
    assert (v, w) == (0.0, -1.2)  # on the spot, turning right at the cap
    v, w = follower.command(0.0, 0.0, 0.0)
    assert v == pytest.approx(0.3) and w == pytest.approx(0.0)
    v, w = follower.command(1.0, 0.05, math.pi / 2)
    assert follower.index == 1 and v > 0
    assert follower.command(1.0, 1.0, math.pi / 2) == (0.0, 0.0)
    assert follower.done


def _distance_to_polyline(x: float, y: float, pts: list[tuple[float, float]]) -> float:
    best = math.inf
    for (ax, ay), (bx, by) in itertools.pairwise(pts):
        dx, dy = bx - ax, by - ay
        t = max(0.0, min(1.0, ((x - ax) * dx + (y - ay) * dy) / (dx * dx + dy * dy)))
        best = min(best, math.hypot(ax + t * dx - x, ay + t * dy - y))
    return best
