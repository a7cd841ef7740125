"""Quality of targets/lama_local: pose error over each world's route, and navigation on its pose.

The same two runs per world as ``rory_eval.quality.amcl`` (whose machinery this reuses): the
whole ``--driver internal`` route with the node localizing on ``/ground_truth/map`` (median,
p95 and max position error, yaw error, the raw odometry's error for scale, CPU% and peak RSS),
then targets/navigator driving to the world's default goal on ``/lama_local/pose`` (remapped to
the ``/amcl_pose`` the navigator listens on).

    python -m rory_eval.quality.lama_local [--worlds W ...] [--out DIR] [--no-navigation]
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from rory_eval.quality.amcl import evaluate
from rory_eval.targets import TARGETS


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m rory_eval.quality.lama_local``."""
    return evaluate(TARGETS['lama_local'], argv)


if __name__ == '__main__':
    sys.exit(main())
