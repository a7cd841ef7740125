"""``rory eval``: the paper's Tables I-IV and its figures, from real runs, in one command.

* :mod:`.plan` - the four methods, the worlds, how long each kind of target runs, and the list
  of runs a command line asks for (the six targets are :mod:`rory_eval.targets`).
* :mod:`.runner` - one run as its own process: the simulator, the target under
  ``rory supervise`` (or bare), a SIGKILL at the crash time; what it output and how RORY
  recovered it, saved as ``record.json`` plus the final map or model.
* :mod:`.judge` - a crash run against the same target's no-crash run, with the thresholds.
* :mod:`.report` - the tables (Markdown and CSV) and :mod:`.figures` - the PNGs.
* :mod:`.cli` - ``python -m rory_eval.evaluation`` / ``rory eval`` / ``make eval``.
"""
