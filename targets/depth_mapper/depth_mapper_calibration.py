"""Online calibration of the wheel odometry's heading error, learnt while the ICP tracks.

Wheel odometry errs systematically: a wheel separation that is not the nominal one over- or
under-counts every turn, and unequal wheel radii make a straight run curve (Borenstein & Feng
1996, UMBmark). Both are linear in the odometry's own increments, so between two frames the
heading the geometry measured relates to the odometry's as

    dyaw_true - dyaw_odom = a * dyaw_odom + b * ds_odom

and ``(a, b)`` is a linear least-squares fit over the frames the geometry pins down well (a
ridge keeps it near zero until there is evidence; cf. Censi et al. 2013 for calibrating
odometry from a sensor's motion estimates). Corrected odometry keeps the heading where the
camera sees nothing but the floor, which in a large hall is a third of the time.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


class HeadingCalibration:
    """Accumulates the normal equations of the heading-error fit.

    Args:
        ridge: prior weight pulling ``(a, b)`` to zero (rad² and m² of increments).
        limit: largest correction allowed for either coefficient.

    Attributes:
        normal_matrix: sum of ``f f^T`` over the samples, ``f = (dyaw_odom, ds_odom)``.
        normal_vector: sum of ``f * (dyaw_true - dyaw_odom)``.
        samples: how many frame pairs went in.
    """

    def __init__(self, ridge: float = 0.05, limit: float = 0.1) -> None:
        self.ridge = ridge
        self.limit = limit
        self.normal_matrix: FloatArray = np.zeros((2, 2))
        self.normal_vector: FloatArray = np.zeros(2)
        self.samples = 0

    def observe(self, odom_yaw: float, odom_distance: float, true_yaw: float) -> None:
        """One frame-to-frame increment: the odometry's turn and travel, the measured turn."""
        f = np.array([odom_yaw, odom_distance])
        self.normal_matrix += np.outer(f, f)
        self.normal_vector += f * (true_yaw - odom_yaw)
        self.samples += 1

    def coefficients(self) -> FloatArray:
        """The current ``(a, b)``: turn scale error and heading drift per metre."""
        a = self.normal_matrix + self.ridge * np.eye(2)
        solution = np.linalg.solve(a, self.normal_vector)
        return np.asarray(np.clip(solution, -self.limit, self.limit), dtype=np.float64)

    def corrected_yaw(self, odom_yaw: float, odom_distance: float) -> float:
        """The odometry's turn with the learnt error removed."""
        a, b = self.coefficients()
        return float(odom_yaw * (1.0 + a) + b * odom_distance)
