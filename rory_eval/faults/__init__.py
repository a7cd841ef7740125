"""``make faults``: RORY struck by every kind of fault, judged on exactness.

Each is a command, ``python -m rory_eval.faults.<name>``; docs/faults.md holds their results.

* :mod:`.fault_campaign` - part one: the fault-injectable integrator (``flaky/``) struck at a
  random moment by SIGKILL, SIGSEGV, an exception or a hang, some twice.
* :mod:`.target_faults` - part two: the real targets in the simulator, struck the same ways
  under ``python -m rory_eval.faults.flaky.inject``, their outputs against a run without a
  fault; built on :mod:`.target_crash`, a target SIGKILLed once and compared byte for byte.
* :mod:`.storm_campaign` - part three: crash storms on the integrator, strikes in a row.
* :mod:`.corpus_campaign` - part four: every node of the corpus with fast replay, SIGKILLed at
  random times, against its no-crash run.
* :mod:`.load_campaign` - parts one to four, fewer runs, with busy processes on every core
  beside them, and runs without a fault that must show no kill and no safe state.
"""
