"""What every measurement, campaign and demo here runs on: real processes, started and watched.

* :mod:`.scenario` - the integrator scenario: ``examples/integrator`` under ``rory supervise``,
  a publisher of 1..N, SIGKILLs at chosen moments, the node's history watched.
* :mod:`.simrun` - one simulator run (``python -m sim``), its nodes, a recorder, ground truth.
* :mod:`.process_usage` - CPU and memory of a process tree, per role, sampled during a run.
* :mod:`.killer` - the SIGKILL of a crash run, a set time after the simulator's clock starts.
* :mod:`.hosts` - several "hosts" on one machine as network namespaces.
* :mod:`.stack` - AMCL and the navigator under one supervisor in the simulator, struck by
  name (``python -m rory_eval.harness.stack``).
* :mod:`.fleet` - two simulated robots on one DDS network, one supervisor each
  (``python -m rory_eval.harness.fleet``).
"""
