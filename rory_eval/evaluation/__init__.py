"""``rory eval``: the paper's Tables I-IV and its figures, from real runs, in one command.

* :mod:`rory_eval.runs` - the runs themselves: :mod:`~rory_eval.runs.plan` (which runs a
  command line asks for) and :mod:`~rory_eval.runs.runner` (one run as its own process),
  which the benches use too.
* :mod:`.judge` - a crash run against the same target's no-crash run, with the thresholds.
* :mod:`.report` - the tables (Markdown and CSV) and :mod:`.figures` - the PNGs.
* :mod:`.cli` - ``python -m rory_eval.evaluation`` / ``rory eval`` / ``make eval``.
"""
