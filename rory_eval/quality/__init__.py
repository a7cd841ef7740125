"""Quality of each target program in normal runs (no crash), measured in the simulator.

One module per target: ``python -m rory_eval.quality.<target>`` runs it in the worlds at full
length and prints its metrics, CPU% and RSS, and draws a figure.
"""
