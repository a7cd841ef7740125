"""The demos: a crash and its recovery, shown in a few minutes.

* :mod:`.mapping_demo` - ``make demo``: grid_slam mapping office_small in the simulator,
  SIGKILLed and brought back by restart and by RORY, the maps side by side.
* :mod:`.integrator_demo` - the integrator summing numbers, SIGKILLed and brought back by each
  method (``python -m rory_eval.demos.integrator_demo``).
"""
