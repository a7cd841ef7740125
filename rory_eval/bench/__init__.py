"""The benches: what RORY costs and how fast it recovers, measured on real processes.

Each is a command, ``python -m rory_eval.bench.<name>``; ``make bench`` runs most of them in
turn and docs/performance.md holds their figures. Recovery time per method
(:mod:`.recovery_bench`), at other run lengths (:mod:`.length_bench`) and across hosts
(:mod:`.multihost_bench`); the checkpoint stall (:mod:`.stall_bench`); recording under load
(:mod:`.recording_bench`); overhead on the targets (:mod:`.overhead_bench`), on one light node
(:mod:`.light_node_bench`), per message or tick (:mod:`.message_cost_bench`), in-process
(:mod:`.hot_path_bench`) and for a whole stack (:mod:`.stack_bench`); memory of forked processes
(:mod:`.fork_memory_bench`); the ring's own participant (:mod:`.ring_participant_bench`); DDS
discovery after a restart (:mod:`.discovery`) and at rest in a fleet (:mod:`.dds_fleet_bench`).
"""
