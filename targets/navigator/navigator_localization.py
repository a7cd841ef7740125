"""The robot's pose in ``map`` between localization updates, as move_base gets it from TF.

A localization node (AMCL) publishes the pose of ``base_link`` in ``map`` at the stamp of the
scan it used, a little late and at ~10 Hz. Like AMCL's ``map -> odom`` transform, the tracker
keeps the correction ``map_from_odom = map_from_base(t) * inverse(odom_from_base(t))`` computed
with the odometry *at the localization's stamp* (interpolated from a short history), and
composes it with the newest odometry: between updates the pose follows the wheels, and every
update removes the drift accumulated since.
"""

from __future__ import annotations

from collections import deque

from navigator_geometry import Pose2D, compose, interpolate, inverse

HISTORY = 150  # odometry samples kept: 3 s at 50 Hz, longer than any localization delay


class PoseTracker:
    """Odometry history and the ``map -> odom`` correction (all of it key state).

    Attributes:
        odom_history: ``(stamp_ns, x, y, yaw)`` of recent odometry in ``odom``, oldest first.
        map_from_odom: the correction from the last localization pose; None before the first.
        localization_stamp_ns: stamp of that pose (0 before the first).
    """

    def __init__(self) -> None:
        self.odom_history: deque[tuple[int, float, float, float]] = deque(maxlen=HISTORY)
        self.map_from_odom: Pose2D | None = None
        self.localization_stamp_ns = 0

    @property
    def latest_odom(self) -> Pose2D | None:
        """The newest odometry pose in ``odom``."""
        if not self.odom_history:
            return None
        _, x, y, yaw = self.odom_history[-1]
        return Pose2D(x, y, yaw)

    @property
    def latest_stamp_ns(self) -> int:
        """Stamp of the newest odometry (0 before any)."""
        return self.odom_history[-1][0] if self.odom_history else 0

    def add_odometry(self, stamp_ns: int, pose: Pose2D) -> bool:
        """Record an odometry pose; False (and ignored) if older than the newest one."""
        if self.odom_history and stamp_ns < self.odom_history[-1][0]:
            return False
        self.odom_history.append((stamp_ns, pose.x, pose.y, pose.yaw))
        return True

    def odom_at(self, stamp_ns: int) -> Pose2D | None:
        """Odometry at a stamp: interpolated, or the nearest end of the history outside it."""
        history = self.odom_history
        if not history:
            return None
        if stamp_ns >= history[-1][0]:
            return self.latest_odom
        if stamp_ns <= history[0][0]:
            _, x, y, yaw = history[0]
            return Pose2D(x, y, yaw)
        # Localization is at most a few samples behind: search from the newest end.
        for k in range(len(history) - 1, 0, -1):
            t0, x0, y0, a0 = history[k - 1]
            if t0 == stamp_ns:
                # As it is: interpolated at fraction 0 the wrapped yaw would change its last
                # bits, and the result would depend on whether later odometry had arrived.
                return Pose2D(x0, y0, a0)
            if t0 <= stamp_ns:
                t1, x1, y1, a1 = history[k]
                fraction = (stamp_ns - t0) / (t1 - t0) if t1 > t0 else 1.0
                return interpolate(Pose2D(x0, y0, a0), Pose2D(x1, y1, a1), fraction)
        return None  # not reached: the bounds were checked above

    def add_localization(self, stamp_ns: int, map_from_base: Pose2D) -> bool:
        """Update the correction from a localization pose; False if it cannot be used yet
        (no odometry) or is older than the pose already used."""
        if stamp_ns < self.localization_stamp_ns:
            return False
        odom_from_base = self.odom_at(stamp_ns)
        if odom_from_base is None:
            return False
        self.map_from_odom = compose(map_from_base, inverse(odom_from_base))
        self.localization_stamp_ns = stamp_ns
        return True

    def pose(self) -> Pose2D | None:
        """The robot's pose in ``map`` now (newest odometry), or None if not localized."""
        odom = self.latest_odom
        if self.map_from_odom is None or odom is None:
            return None
        return compose(self.map_from_odom, odom)
