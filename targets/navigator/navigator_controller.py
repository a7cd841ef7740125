"""Local controller: regulated pure pursuit with a scan-based collision check.

Pure pursuit (Coulter 1992) steers along the arc through a lookahead point on the plan; the
*regulated* variant (Macenski et al. 2023, Nav2's RPP) slows down on tight curvature, near
obstacles and when approaching the goal, and turns in place when the path is far off the
heading. Every command is limited by the robot's velocity and acceleration limits and then
checked against the latest scan: the arc it would drive over the next ``collision_horizon``
seconds must keep the footprint circle clear of every scan point, else the robot stops and
reports the plan blocked (the caller replans or recovers). All plain numpy, no ROS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from navigator_geometry import FloatArray, Pose2D, wrap


@dataclass(frozen=True)
class ControllerParams:
    """Controller tuning and the robot's limits.

    Attributes:
        max_linear: m/s (the robot's limit is 0.5).
        max_angular: rad/s (limit 1.8).
        linear_accel: m/s^2 (limit 1.0).
        angular_accel: rad/s^2 (limit 3.0).
        lookahead: pure pursuit lookahead distance (m).
        rotate_threshold: heading error to the lookahead point above which it turns in place.
        rotate_gain: proportional gain of in-place turns (1/s).
        min_rotate_speed: smallest in-place turn rate, so small errors still close (rad/s).
        min_turn_radius: curvature regulation: below this radius the speed scales down (m).
        approach_decel: deceleration used to slow down towards the goal (m/s^2).
        min_approach_speed: the slowest forward speed near the goal (m/s).
        robot_radius: footprint circle for the collision check (m).
        collision_margin: clearance kept beyond the footprint circle (m).
        collision_horizon: how far ahead the commanded arc is checked (s).
        slowdown_distance: obstacle distance (beyond the footprint) below which to slow (m).
    """

    max_linear: float = 0.45
    max_angular: float = 1.5
    linear_accel: float = 0.9
    angular_accel: float = 2.5
    lookahead: float = 0.5
    rotate_threshold: float = 0.75
    rotate_gain: float = 2.0
    min_rotate_speed: float = 0.25
    min_turn_radius: float = 0.8
    approach_decel: float = 0.35
    min_approach_speed: float = 0.06
    robot_radius: float = 0.205
    collision_margin: float = 0.03
    collision_horizon: float = 1.2
    slowdown_distance: float = 0.4


@dataclass(frozen=True)
class Command:
    """A velocity command and what the controller found.

    Attributes:
        linear: forward speed (m/s).
        angular: turn rate (rad/s).
        blocked: the wanted motion would hit something the scan sees; the command stops.
    """

    linear: float
    angular: float
    blocked: bool = False


def progress_index(pose: Pose2D, path: FloatArray, index: int, window: int = 60) -> int:
    """The plan index nearest the robot, searched forward from ``index`` (never backwards)."""
    end = min(len(path), index + window)
    if end <= index:
        return max(0, len(path) - 1)
    d = np.hypot(path[index:end, 0] - pose.x, path[index:end, 1] - pose.y)
    return index + int(np.argmin(d))


def lookahead_point(pose: Pose2D, path: FloatArray, index: int,
                    distance: float) -> tuple[float, float]:
    """The first plan point from ``index`` at least ``distance`` from the robot (else the end)."""
    tail = path[index:]
    d = np.hypot(tail[:, 0] - pose.x, tail[:, 1] - pose.y)
    far = np.nonzero(d >= distance)[0]
    k = int(far[0]) if len(far) else len(tail) - 1
    return float(tail[k, 0]), float(tail[k, 1])


def remaining_length(path: FloatArray, index: int) -> float:
    """Length of the plan from ``index`` to its end (m)."""
    tail = path[index:]
    if len(tail) < 2:
        return 0.0
    return float(np.hypot(*np.diff(tail, axis=0).T).sum())


def arc_poses(linear: float, angular: float, horizon: float, step: float = 0.1) -> FloatArray:
    """Poses ``(K, 3)`` (x, y, yaw in the robot's frame) along a constant-velocity arc, from
    ``step`` to ``horizon`` seconds."""
    t = np.arange(1, max(1, math.ceil(horizon / step)) + 1) * step
    yaw = angular * t
    if abs(angular) < 1e-6:
        x = linear * t
        y = np.zeros_like(t)
    else:
        r = linear / angular
        x = r * np.sin(yaw)
        y = r * (1.0 - np.cos(yaw))
    return np.column_stack([x, y, yaw])


def arc_collides(linear: float, angular: float, points: FloatArray,
                 params: ControllerParams) -> bool:
    """Whether driving (linear, angular) for the horizon brings a scan point (robot frame,
    ``(N, 2)``) within the footprint circle plus margin.

    Points already that close at the start count only if the motion brings them closer, so a
    robot brushing past an obstacle can still move away from it.
    """
    if len(points) == 0 or (linear == 0.0 and angular == 0.0):
        return False
    reach = abs(linear) * params.collision_horizon + params.robot_radius + 0.1
    near = points[np.hypot(points[:, 0], points[:, 1]) < reach]
    if len(near) == 0:
        return False
    poses = arc_poses(linear, angular, params.collision_horizon)
    limit = params.robot_radius + params.collision_margin
    dist = np.hypot(near[None, :, 0] - poses[:, 0:1], near[None, :, 1] - poses[:, 1:2])
    closest_now = float(np.hypot(near[:, 0], near[:, 1]).min())
    closest_then = float(dist.min())
    if closest_then >= limit:
        return False
    return closest_then < closest_now - 1e-3


def clearance(points: FloatArray, robot_radius: float) -> float:
    """Distance from the footprint circle to the nearest scan point ahead (x > -radius)."""
    if len(points) == 0:
        return math.inf
    ahead = points[points[:, 0] > -robot_radius]
    if len(ahead) == 0:
        return math.inf
    return float(np.hypot(ahead[:, 0], ahead[:, 1]).min()) - robot_radius


def limit_acceleration(linear: float, angular: float, previous: tuple[float, float],
                       dt: float, params: ControllerParams) -> tuple[float, float]:
    """Clamp a command to the speed limits and to what the accelerations allow from the
    previous command over ``dt`` seconds."""
    v0, w0 = previous
    dv = params.linear_accel * dt
    dw = params.angular_accel * dt
    linear = min(max(linear, v0 - dv), v0 + dv)
    angular = min(max(angular, w0 - dw), w0 + dw)
    linear = min(max(linear, -params.max_linear), params.max_linear)
    angular = min(max(angular, -params.max_angular), params.max_angular)
    return linear, angular


def rotate_towards(error: float, params: ControllerParams) -> float:
    """In-place turn rate that closes a heading error."""
    w = params.rotate_gain * error
    if abs(w) < params.min_rotate_speed:
        w = math.copysign(params.min_rotate_speed, error)
    return min(max(w, -params.max_angular), params.max_angular)


def follow(pose: Pose2D, path: FloatArray, index: int, scan_points: FloatArray,
           previous: tuple[float, float], dt: float, params: ControllerParams) -> Command:
    """One pure pursuit step along ``path`` from ``index`` (see ``progress_index``).

    Args:
        pose: the robot in ``map``.
        path: the plan ``(N, 2)`` in ``map``.
        index: progress along it.
        scan_points: obstacles the scan sees, in the robot's frame ``(M, 2)``.
        previous: the last command (linear, angular), for the acceleration limits.
        dt: time since it (s).
        params: tuning and limits.
    """
    lx, ly = lookahead_point(pose, path, index, params.lookahead)
    dx, dy = lx - pose.x, ly - pose.y
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    bx, by = c * dx + s * dy, -s * dx + c * dy  # the lookahead point in the robot's frame
    heading_error = math.atan2(by, bx)
    if abs(heading_error) > params.rotate_threshold:
        linear, angular = 0.0, rotate_towards(heading_error, params)
    else:
        dist2 = max(bx * bx + by * by, 1e-6)
        curvature = 2.0 * by / dist2
        linear = params.max_linear
        if abs(curvature) * params.min_turn_radius > 1.0:
            linear /= abs(curvature) * params.min_turn_radius
        remaining = remaining_length(path, index) + math.hypot(path[index, 0] - pose.x,
                                                               path[index, 1] - pose.y)
        linear = min(linear, max(params.min_approach_speed,
                                 math.sqrt(2.0 * params.approach_decel * remaining)))
        free = clearance(scan_points, params.robot_radius)
        if free < params.slowdown_distance:
            linear *= max(0.35, free / params.slowdown_distance)
        angular = linear * curvature
        if abs(angular) > params.max_angular:
            angular = math.copysign(params.max_angular, angular)
            linear = abs(angular / curvature)
    wanted = (linear, angular)
    linear, angular = limit_acceleration(linear, angular, previous, dt, params)
    if arc_collides(linear, angular, scan_points, params):
        # Stop driving; keep turning in place only if that alone was wanted (turning in place
        # sweeps nothing: the footprint circle stays where it is).
        turn = angular if wanted[0] == 0.0 else 0.0
        return Command(0.0, turn, blocked=True)
    return Command(linear, angular)


def turn_to_yaw(pose: Pose2D, yaw: float, previous: tuple[float, float], dt: float,
                params: ControllerParams) -> tuple[Command, float]:
    """Stop and turn in place to ``yaw``; the command and the remaining heading error."""
    error = wrap(yaw - pose.yaw)
    linear, angular = limit_acceleration(0.0, rotate_towards(error, params), previous, dt,
                                         params)
    return Command(linear, angular), error
