"""``rory eval``: the paper's Tables I-IV and its figures, from real runs, in one command.

* :mod:`.plan` - the six targets (how each runs in the simulator, what it outputs, how it is
  judged), the four methods, and the list of runs a command line asks for.
* :mod:`.runner` - one run as its own process: the simulator, the target under
  ``rory supervise`` (or bare), a SIGKILL at the crash time; what it output and how RORY
  recovered it, saved as ``record.json`` plus the final map or model.
* :mod:`.judge` - a crash run against the same target's no-crash run, with the thresholds.
* :mod:`.report` - the tables (Markdown and CSV) and :mod:`.figures` - the PNGs.
* :mod:`.cli` - ``python -m rory_eval.evaluation`` / ``rory eval`` / ``make eval``.
"""
