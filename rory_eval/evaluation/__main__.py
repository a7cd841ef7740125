"""``python -m rory_eval.evaluation``: see :mod:`rory_eval.evaluation.cli`."""

import sys

from rory_eval.evaluation.cli import main

sys.exit(main())
