"""The navigator without ROS: map, goal, pose, scan in; velocity commands and a plan out.

What move_base does, in one message-driven state machine::

    IDLE --goal--> PLANNING --A* ok--> FOLLOWING --at goal, turned to its yaw--> REACHED
                      ^  |                |   |
                      |  +--no path--+    |   +--plan blocked by the scan--> PLANNING
                      |              v    v
                      +--done--- RECOVERING (turn in place, back up) --too many--> FAILED

Every state change happens in one of the ``on_*`` methods, from the messages' contents and
stamps only: fed the same messages in the same order, two cores end in the same state. Control
runs on odometry, decimated by stamp to ``control_period``.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from navigator_controller import (
    Command,
    ControllerParams,
    arc_collides,
    follow,
    limit_acceleration,
    progress_index,
    remaining_length,
    turn_to_yaw,
)
from navigator_costmap import Costmap, GridMap, InflationParams, build_costmap
from navigator_geometry import FloatArray, Pose2D, path_length, transform_points, wrap
from navigator_localization import PoseTracker
from navigator_planner import astar, cells_to_points, nearest_free_cell, smooth_path

NS = 1_000_000_000
STOP = Command(0.0, 0.0)


class Status(enum.Enum):
    """What the navigator is doing (published on ``/navigator/status``)."""

    IDLE = 'IDLE'
    PLANNING = 'PLANNING'
    FOLLOWING = 'FOLLOWING'
    RECOVERING = 'RECOVERING'
    REACHED = 'REACHED'
    FAILED = 'FAILED'


class RecoveryKind(enum.Enum):
    """Recovery behaviours, tried in turn as move_base does."""

    ROTATE = 'rotate'
    BACK_UP = 'back_up'


@dataclass
class Recovery:
    """A recovery behaviour under way.

    Attributes:
        kind: which behaviour.
        start: odometry pose when it began (``odom``).
        start_ns: stamp when it began.
        turned: how far it has turned so far (rad; ROTATE).
        last_yaw: odometry yaw at the previous step (ROTATE).
    """

    kind: RecoveryKind
    start: Pose2D
    start_ns: int
    turned: float = 0.0
    last_yaw: float = 0.0


@dataclass(frozen=True)
class NavigatorParams:
    """Tuning of the whole navigator (ROS parameters of the node).

    Attributes:
        inflation: costmap inflation.
        controller: local controller and robot limits.
        xy_goal_tolerance: distance at which the goal position counts as reached (m).
        yaw_goal_tolerance: heading error at which the goal counts as reached (rad).
        control_period: seconds between control steps (odometry is decimated to it).
        progress_timeout: seconds without ``progress_distance`` of progress before recovering.
        progress_distance: progress that resets the timeout (m).
        blocked_timeout: seconds the controller may stay blocked before a replan.
        max_recoveries: recoveries in a row (without progress) before giving up.
        obstacle_range: scan points farther than this are not put into the costmap (m).
        unexpected_distance: a scan point farther than this from every known obstacle is an
            obstacle the map does not have (m).
        start_snap: how far the plan's start may be moved off a lethal cell (m).
        goal_snap: the same for the goal (m).
        backup_distance: how far BACK_UP reverses (m).
        backup_speed: how fast (m/s).
        rotate_speed: turn rate of ROTATE (rad/s).
        stop_duration: how long zero commands follow REACHED or FAILED (s).
        scan_offset_x: the lidar's x in ``base_link`` (m); there is no TF.
        scan_offset_y: its y (m).
    """

    inflation: InflationParams = field(default_factory=InflationParams)
    controller: ControllerParams = field(default_factory=ControllerParams)
    xy_goal_tolerance: float = 0.08
    yaw_goal_tolerance: float = 0.08
    control_period: float = 0.05
    progress_timeout: float = 12.0
    progress_distance: float = 0.2
    blocked_timeout: float = 0.6
    max_recoveries: int = 4
    obstacle_range: float = 2.5
    unexpected_distance: float = 0.15
    start_snap: float = 0.4
    goal_snap: float = 0.3
    backup_distance: float = 0.25
    backup_speed: float = 0.1
    rotate_speed: float = 1.0
    stop_duration: float = 1.0
    scan_offset_x: float = -0.064
    scan_offset_y: float = 0.0


def _empty_points() -> FloatArray:
    return np.zeros((0, 2))


class NavigatorCore:
    """move_base as plain Python. Attributes below ``# key state`` are what a restart loses.

    Args:
        params: tuning.
    """

    def __init__(self, params: NavigatorParams) -> None:
        self.params = params
        # key state ------------------------------------------------------------------------
        self.grid: GridMap | None = None
        self.goal: Pose2D | None = None
        self.goal_stamp_ns = 0
        self.status = Status.IDLE
        self.status_stamp_ns = 0
        self.tracker = PoseTracker()
        self.scan_points: FloatArray = _empty_points()  # latest scan, in odom
        self.scan_stamp_ns = 0
        self.scan_checked = True  # the latest scan has been checked against the plan
        self.seen_cells: npt.NDArray[np.int64] = np.zeros(0, dtype=np.int64)
        self.plan: FloatArray = _empty_points()
        self.plan_index = 0
        self.plans_made = 0
        self.first_plan_length = 0.0  # the A* length of the first plan to this goal (m)
        self.goal_xy_reached = False
        self.last_command: tuple[float, float] = (0.0, 0.0)
        self.next_control_ns = 0
        self.best_remaining = math.inf
        self.progress_stamp_ns = 0
        self.blocked_since_ns = 0
        self.replans_without_progress = 0
        self.recovery: Recovery | None = None
        self.recoveries = 0  # in a row, since the last progress
        self.total_recoveries = 0
        self.failure = ''
        # cache (derived from grid and seen_cells) and output buffer, not state ------------
        self._costmap: Costmap | None = None
        self._costmap_key: tuple[object, object] = (None, None)
        self.notes: list[tuple[str, str]] = []  # (level, text) for the node to log, drained

    # -- inputs ------------------------------------------------------------------------------

    def on_map(self, grid: GridMap) -> bool:
        """A map arrived; False if it is the map already held (a latched map again)."""
        if self.grid is not None and self.grid.same_as(grid):
            return False
        self.grid = grid
        self.seen_cells = np.zeros(0, dtype=np.int64)  # cell indices of the old grid
        if self.status in (Status.FOLLOWING, Status.RECOVERING):
            self._set_status(Status.PLANNING, self.tracker.latest_stamp_ns)
        return True

    def on_goal(self, stamp_ns: int, goal: Pose2D) -> bool:
        """A goal arrived; False if it is the goal already held (delivered again)."""
        if self.goal == goal and self.goal_stamp_ns == stamp_ns:
            return False
        self.goal = goal
        self.goal_stamp_ns = stamp_ns
        self.seen_cells = np.zeros(0, dtype=np.int64)
        self.plan = _empty_points()
        self.plan_index = 0
        self.first_plan_length = 0.0
        self.goal_xy_reached = False
        self.recovery = None
        self.recoveries = 0
        self.replans_without_progress = 0
        self.failure = ''
        self._set_status(Status.PLANNING, max(stamp_ns, self.tracker.latest_stamp_ns))
        return True

    def on_localization(self, stamp_ns: int, pose: Pose2D) -> bool:
        """A localization pose of base_link in ``map``; False if it could not be used."""
        return self.tracker.add_localization(stamp_ns, pose)

    def on_scan(self, stamp_ns: int, ranges: npt.NDArray[np.float32], angle_min: float,
                angle_increment: float, range_min: float, range_max: float) -> int:
        """Keep the scan's returns as points in ``odom``; how many there were.

        NaN, inf and out-of-range beams carry no obstacle and are dropped.
        """
        r = np.asarray(ranges, dtype=np.float64)
        angles = angle_min + angle_increment * np.arange(len(r))
        valid = np.isfinite(r) & (r >= range_min) & (r <= range_max)
        r, angles = r[valid], angles[valid]
        base = np.column_stack([self.params.scan_offset_x + r * np.cos(angles),
                                self.params.scan_offset_y + r * np.sin(angles)])
        odom = self.tracker.odom_at(stamp_ns)
        if odom is None:
            return 0  # no odometry yet: nothing to place the scan with
        self.scan_points = transform_points(odom, base)
        self.scan_stamp_ns = stamp_ns
        self.scan_checked = False
        return len(base)

    def on_odometry(self, stamp_ns: int, pose: Pose2D) -> Command | None:
        """Record odometry; when a control step is due, the command to send (None: none)."""
        if not self.tracker.add_odometry(stamp_ns, pose):
            return None
        if stamp_ns < self.next_control_ns:
            return None
        # Odometry comes every 20 ms: a period of 50 ms runs control on every third (60 ms),
        # the 5 ms slack absorbs stamp rounding.
        period_ns = int(self.params.control_period * NS)
        self.next_control_ns = stamp_ns + period_ns - 5_000_000
        command = self._control(stamp_ns)
        if command is not None:
            self.last_command = (command.linear, command.angular)
        return command

    # -- outputs -----------------------------------------------------------------------------

    def pose(self) -> Pose2D | None:
        """The robot in ``map`` (None before localization)."""
        return self.tracker.pose()

    def costmap(self) -> Costmap | None:
        """The costmap of the current map and seen obstacles (built when they changed)."""
        if self.grid is None:
            return None
        if self._costmap is None or self._costmap_key[0] is not self.grid \
                or self._costmap_key[1] is not self.seen_cells:
            extra = None
            if len(self.seen_cells):
                width = self.grid.data.shape[1]
                rows, cols = np.divmod(self.seen_cells, width)
                res = self.grid.resolution
                extra = np.column_stack([self.grid.origin_x + (cols + 0.5) * res,
                                         self.grid.origin_y + (rows + 0.5) * res])
            self._costmap = build_costmap(self.grid, self.params.inflation, extra)
            self._costmap_key = (self.grid, self.seen_cells)
        return self._costmap

    # -- control -----------------------------------------------------------------------------

    def _set_status(self, status: Status, stamp_ns: int) -> None:
        if status != self.status:
            self.status = status
            self.status_stamp_ns = stamp_ns

    def _note(self, level: str, text: str) -> None:
        self.notes.append((level, text))

    def _scan_in_robot_frame(self) -> FloatArray:
        odom = self.tracker.latest_odom
        if odom is None or len(self.scan_points) == 0:
            return _empty_points()
        c, s = math.cos(odom.yaw), math.sin(odom.yaw)
        d = self.scan_points - np.array([odom.x, odom.y])
        return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])

    def _control(self, stamp_ns: int) -> Command | None:
        status = self.status
        if status == Status.IDLE:
            return None
        if status in (Status.REACHED, Status.FAILED):
            within = stamp_ns - self.status_stamp_ns <= self.params.stop_duration * NS
            return STOP if within else None
        pose = self.tracker.pose()
        if pose is None or self.grid is None or self.goal is None:
            return None  # waiting for localization or the map (the node says which)
        if status == Status.PLANNING:
            if not self._make_plan(pose, stamp_ns):
                return self._start_recovery(stamp_ns, 'no path to the goal')
            status = self.status
        if status == Status.RECOVERING:
            return self._recover(stamp_ns)
        return self._follow(pose, stamp_ns)

    def _unexpected_points(self, pose: Pose2D) -> FloatArray:
        """Scan points near the robot that no known obstacle explains, in ``map``."""
        costmap = self.costmap()
        correction = self.tracker.map_from_odom
        if costmap is None or correction is None or len(self.scan_points) == 0:
            return _empty_points()
        points = transform_points(correction, self.scan_points)
        near = np.hypot(points[:, 0] - pose.x, points[:, 1] - pose.y) < self.params.obstacle_range
        points = points[near]
        return points[costmap.distance_at(points) > self.params.unexpected_distance]

    def _remember_obstacles(self, points: FloatArray) -> None:
        if self.grid is None or len(points) == 0:
            return
        res = self.grid.resolution
        h, w = self.grid.data.shape
        cols = np.floor((points[:, 0] - self.grid.origin_x) / res).astype(np.int64)
        rows = np.floor((points[:, 1] - self.grid.origin_y) / res).astype(np.int64)
        inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        cells = np.union1d(self.seen_cells, rows[inside] * w + cols[inside])
        if len(cells) != len(self.seen_cells):
            self.seen_cells = cells.astype(np.int64)

    def _make_plan(self, pose: Pose2D, stamp_ns: int) -> bool:
        assert self.goal is not None
        self._remember_obstacles(self._unexpected_points(pose))
        costmap = self.costmap()
        assert costmap is not None
        start = nearest_free_cell(costmap, costmap.cell_of(pose.x, pose.y),
                                  self.params.start_snap)
        goal = nearest_free_cell(costmap, costmap.cell_of(self.goal.x, self.goal.y),
                                 self.params.goal_snap)
        if start is None or goal is None:
            which = 'the robot' if start is None else 'the goal'
            self._note('warn', f'no free cell near {which}: cannot plan')
            return False
        cells = astar(costmap, start, goal)
        if cells is None:
            self._note('warn', 'A* found no path to the goal')
            return False
        points = cells_to_points(costmap, cells)
        points[0] = (pose.x, pose.y)
        if goal == costmap.cell_of(self.goal.x, self.goal.y):
            points[-1] = (self.goal.x, self.goal.y)
        self.plan = smooth_path(points, costmap)
        self.plan_index = 0
        self.plans_made += 1
        length = path_length(self.plan)
        if self.first_plan_length == 0.0:
            self.first_plan_length = length
        self.best_remaining = length
        self.progress_stamp_ns = stamp_ns
        self.blocked_since_ns = 0
        self.scan_checked = True
        self._set_status(Status.FOLLOWING, stamp_ns)
        self._note('info', f'plan {self.plans_made}: {len(self.plan)} points, {length:.2f} m')
        return True

    def _plan_blocked(self, pose: Pose2D) -> bool:
        """Whether the plan ahead runs into something the newest scan sees and the map lacks."""
        self.scan_checked = True
        unexpected = self._unexpected_points(pose)
        if len(unexpected) == 0:
            return False
        ahead = self.plan[self.plan_index:]
        steps = np.hypot(*np.diff(ahead, axis=0).T) if len(ahead) > 1 else np.zeros(0)
        within = np.concatenate([[0.0], np.cumsum(steps)]) <= self.params.obstacle_range
        ahead = ahead[within]
        limit = self.params.controller.robot_radius + self.params.controller.collision_margin
        d = np.hypot(ahead[:, None, 0] - unexpected[None, :, 0],
                     ahead[:, None, 1] - unexpected[None, :, 1])
        hit = d.min(axis=0) < limit
        if not hit.any():
            return False
        self._remember_obstacles(unexpected)
        return True

    def _follow(self, pose: Pose2D, stamp_ns: int) -> Command:
        assert self.goal is not None
        params = self.params
        dt = params.control_period
        goal_distance = math.hypot(self.goal.x - pose.x, self.goal.y - pose.y)
        if goal_distance <= params.xy_goal_tolerance:
            self.goal_xy_reached = True  # latched: turning in place may drift a little
        if self.goal_xy_reached:
            command, error = turn_to_yaw(pose, self.goal.yaw, self.last_command, dt,
                                         params.controller)
            if abs(error) <= params.yaw_goal_tolerance:
                self._set_status(Status.REACHED, stamp_ns)
                self._note('info', f'goal reached: {goal_distance:.3f} m, '
                                   f'{math.degrees(error):.1f} deg off')
                return STOP
            return command
        if not self.scan_checked and self._plan_blocked(pose):
            self._note('info', 'the scan sees an obstacle on the plan: replanning')
            return self._replan(pose, stamp_ns, 'plan blocked')
        self.plan_index = progress_index(pose, self.plan, self.plan_index)
        remaining = remaining_length(self.plan, self.plan_index) + math.hypot(
            self.plan[self.plan_index, 0] - pose.x, self.plan[self.plan_index, 1] - pose.y)
        if remaining < self.best_remaining - params.progress_distance:
            self.best_remaining = remaining
            self.progress_stamp_ns = stamp_ns
            self.recoveries = 0
            self.replans_without_progress = 0
        elif stamp_ns - self.progress_stamp_ns > params.progress_timeout * NS:
            return self._start_recovery(stamp_ns, 'no progress')
        command = follow(pose, self.plan, self.plan_index, self._scan_in_robot_frame(),
                         self.last_command, dt, params.controller)
        if not command.blocked:
            self.blocked_since_ns = 0
            return command
        if self.blocked_since_ns == 0:
            self.blocked_since_ns = stamp_ns
        elif stamp_ns - self.blocked_since_ns > params.blocked_timeout * NS:
            self._remember_obstacles(self._unexpected_points(pose))
            return self._replan(pose, stamp_ns, 'blocked')
        return command

    def _replan(self, pose: Pose2D, stamp_ns: int, why: str) -> Command:
        self.replans_without_progress += 1
        if self.replans_without_progress > 2:
            return self._start_recovery(stamp_ns, f'{why}, replanning did not help')
        if self._make_plan(pose, stamp_ns):
            return Command(0.0, 0.0, blocked=True)  # start the new plan from standstill
        return self._start_recovery(stamp_ns, f'{why}, and no other path')

    def _start_recovery(self, stamp_ns: int, why: str) -> Command:
        self.recoveries += 1
        self.total_recoveries += 1
        self.replans_without_progress = 0
        if self.recoveries > self.params.max_recoveries:
            self.failure = why
            self._set_status(Status.FAILED, stamp_ns)
            self._note('error', f'giving up on the goal after {self.params.max_recoveries} '
                                f'recoveries: {why}')
            return STOP
        kind = RecoveryKind.ROTATE if self.recoveries % 2 == 1 else RecoveryKind.BACK_UP
        odom = self.tracker.latest_odom
        assert odom is not None
        self.recovery = Recovery(kind, odom, stamp_ns, 0.0, odom.yaw)
        # As move_base's costmap reset: forget what the scan put in the costmap; the replan
        # after the behaviour marks again what is still there.
        self.seen_cells = np.zeros(0, dtype=np.int64)
        self._set_status(Status.RECOVERING, stamp_ns)
        self._note('warn', f'recovery {self.recoveries} ({kind.value}): {why}')
        return STOP

    def _recover(self, stamp_ns: int) -> Command:
        recovery = self.recovery
        odom = self.tracker.latest_odom
        assert recovery is not None and odom is not None
        params = self.params
        dt = params.control_period
        elapsed = (stamp_ns - recovery.start_ns) / NS
        done = False
        if recovery.kind == RecoveryKind.ROTATE:
            recovery.turned += abs(wrap(odom.yaw - recovery.last_yaw))
            recovery.last_yaw = odom.yaw
            done = recovery.turned >= 2.0 * math.pi or elapsed > 4.0 * math.pi / params.rotate_speed
            linear, angular = 0.0, params.rotate_speed
        else:
            moved = math.hypot(odom.x - recovery.start.x, odom.y - recovery.start.y)
            linear, angular = -params.backup_speed, 0.0
            done = (moved >= params.backup_distance
                    or elapsed > params.backup_distance / params.backup_speed + 3.0
                    or arc_collides(linear, angular, self._scan_in_robot_frame(),
                                    params.controller))
        if done:
            self.recovery = None
            self._set_status(Status.PLANNING, stamp_ns)
            return STOP
        return Command(*self._limited(linear, angular, dt))

    def _limited(self, linear: float, angular: float, dt: float) -> tuple[float, float]:
        return limit_acceleration(linear, angular, self.last_command, dt,
                                  self.params.controller)
