"""One simulator run of a target, as the evaluation and the benches both make it.

* :mod:`.plan` - the four methods, the worlds, how long each kind of target runs, and the list
  of runs a command line asks for (the six targets are :mod:`rory_eval.targets`).
* :mod:`.runner` - one run as its own process (``python -m rory_eval.runs.runner``): the
  simulator, the target under ``rory supervise`` (or bare), a SIGKILL at the crash time; what
  it output and how RORY recovered it, saved as ``record.json`` plus the final map or model.

``rory eval`` (:mod:`rory_eval.evaluation`) and the Table II and overhead benches
(:mod:`rory_eval.bench`) stand on it; it stands on the harness and the quality runs' relay.
"""
