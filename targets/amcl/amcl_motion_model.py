"""The odometry motion model, sampled (Probabilistic Robotics, Table 5.6).

The odometry's motion between two updates is split into a rotation, a translation and a
second rotation; each particle moves by a noisy copy of the three, the noise growing with the
motion through ``alpha1..alpha4``. As in amcl, a translation under 1 cm has no first rotation,
and reversing counts as a small rotation for the noise (so driving backwards is not mistaken
for a half turn).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from planar_geometry import Pose, wrap_angle

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class MotionNoise:
    """amcl's differential-drive noise parameters.

    Attributes:
        alpha1: rotation noise from rotation.
        alpha2: rotation noise from translation.
        alpha3: translation noise from translation.
        alpha4: translation noise from rotation.
    """

    alpha1: float = 0.2
    alpha2: float = 0.2
    alpha3: float = 0.2
    alpha4: float = 0.2


def _small_angle(a: float) -> float:
    # |a| or |a - pi|, whichever is smaller: a reverse motion is not a half turn.
    return min(abs(wrap_angle(a)), abs(wrap_angle(a - math.pi)))


def sample_motion_model_odometry(particles: FloatArray, odom_before: Pose, odom_after: Pose,
                                 noise: MotionNoise, rng: np.random.Generator) -> FloatArray:
    """Move every particle row ``(x, y, yaw)`` by a noisy copy of the odometry's motion.

    Returns:
        A new (N, 3) array; yaw wrapped to [-pi, pi).
    """
    dx = odom_after[0] - odom_before[0]
    dy = odom_after[1] - odom_before[1]
    trans = math.hypot(dx, dy)
    rot1 = 0.0 if trans < 0.01 else wrap_angle(math.atan2(dy, dx) - odom_before[2])
    rot2 = wrap_angle(odom_after[2] - odom_before[2] - rot1)
    rot1_n, rot2_n = _small_angle(rot1), _small_angle(rot2)
    n = particles.shape[0]
    sd_rot1 = math.sqrt(noise.alpha1 * rot1_n ** 2 + noise.alpha2 * trans ** 2)
    sd_trans = math.sqrt(noise.alpha3 * trans ** 2 + noise.alpha4 * (rot1_n ** 2 + rot2_n ** 2))
    sd_rot2 = math.sqrt(noise.alpha1 * rot2_n ** 2 + noise.alpha2 * trans ** 2)
    e = rng.standard_normal((3, n))
    rot1_hat = rot1 - sd_rot1 * e[0]
    trans_hat = trans - sd_trans * e[1]
    rot2_hat = rot2 - sd_rot2 * e[2]
    out = np.empty_like(particles)
    heading = particles[:, 2] + rot1_hat
    out[:, 0] = particles[:, 0] + trans_hat * np.cos(heading)
    out[:, 1] = particles[:, 1] + trans_hat * np.sin(heading)
    out[:, 2] = (heading + rot2_hat + np.pi) % (2.0 * np.pi) - np.pi
    return out
