"""A real target killed under RORY in the simulator: is its output exactly the no-crash one?

The simulator's internal driver makes every sensor message identical from run to run for a
seed, and the targets are deterministic functions of their input. So a recovery that loses
nothing and applies nothing twice leaves the target publishing, for every scan after its
release, *byte for byte* the message it publishes in a run without a crash. This runs the
target under ``rory supervise`` twice - without a crash, then SIGKILLed at ``--kill-at`` sim
seconds - records its pose output, and compares the serialized messages stamp by stamp.

    python -m rory_eval.faults.target_crash --target grid_slam --world office_small --kill-at 20
"""

from __future__ import annotations

import argparse
import itertools
import json
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import yaml

from rory_eval.harness.killer import Killer
from rory_eval.harness.simrun import SimRun, exit_on_sigterm, store_events
from rory_eval.targets import EXACT_TARGETS, POSE_STAMPED, Target


def sensor_readers(target: Target) -> dict[str, int]:
    """What the simulator's clock waits for: the node and RORY's ring on each input.

    Waiting for a topic the target does not read (depth_mapper has no /scan) only times out:
    30 s per run, and the start then races the subscriptions.
    """
    return {topic: 2 for topic in target.inputs}


@dataclass
class Comparison:
    """Stamp-by-stamp comparison of the two runs' outputs."""

    reference: int  # messages in the run without a crash
    crashed: int  # messages in the run with the crash
    common: int  # stamps in both
    identical: int  # of those, byte-identical
    missing_after_release: int  # reference stamps after the release absent from the crash run
    recovered_ms: float | None
    first_difference: str = ''

    @property
    def exact(self) -> bool:
        """Every common output identical, none missing after the release."""
        return (self.common > 0 and self.identical == self.common
                and self.missing_after_release == 0)


class Fault(Protocol):
    """What strikes the node during a run (a Killer, target_faults' striker): a thread."""

    def start(self) -> None:
        """Begin watching the run (it waits for the simulator's clock itself)."""

    def stop(self) -> None:
        """Stop striking; called when the run is over, however it ended."""


def instrument(target: Target, inst: Path) -> Path:
    """``rory instrument`` the target's folder into ``inst`` unless it is there already."""
    if not (inst / target.node_file).exists():
        subprocess.run([sys.executable, '-m', 'rory_instrument', str(target.folder), '--vars',
                        str(target.keyvars), '-o', str(inst)], check=True,
                       capture_output=True)
    return inst


def run_supervised(target: Target, world: str, out: Path, *, domain_id: int, duration: float,
                   command: Sequence[str], settings: dict[str, Any] | None = None,
                   fault: Fault | None = None) -> tuple[dict[int, bytes], list[dict[str, Any]]]:
    """One run of the target under ``rory supervise`` (method rory, checkpoints every 2 s,
    fast replay) in the simulator, with ``fault`` striking it meanwhile.

    Args:
        target: The target.
        world: The simulator's world.
        out: The run's folder: ``supervise.yaml``, ``store/``, ``run/`` (the simulator's).
        domain_id: ROS domain of the run.
        duration: Sim seconds.
        command: The node's command line, as the supervisor starts it.
        settings: More of the node's supervisor settings.
        fault: Started before the run, stopped after it.

    Returns:
        The serialized pose messages by stamp (ns), and the supervisor's events.
    """
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from rclpy.serialization import serialize_message

    store = out / 'store'
    config = out / 'supervise.yaml'
    # No safe state: /e_stop would stop the simulator's driver and change every later input.
    config.write_text(yaml.safe_dump({
        'nodes': [{'name': target.name, 'command': list(command), 'method': 'rory',
                   'checkpoint_interval': 2.0, 'replay': 'fast', **(settings or {})}],
        'store': str(store),
    }))
    # The clock waits for the node and RORY's ring to subscribe its inputs, then one more
    # second so the latched map reaches the node before the first scan in every run: otherwise
    # the interleaving of map and scans at start-up differs between runs, and so do the outputs.
    run = SimRun(world, out / 'run', domain_id=domain_id, duration=duration, depth=target.depth,
                 wait_for=sensor_readers(target), sim_args=['--start-delay', '1.0'])
    run.add_node('supervisor', [sys.executable, '-m', 'rory_runtime.cli', 'supervise',
                                str(config)])
    msg_type = PoseStamped if target.pose_type == POSE_STAMPED else PoseWithCovarianceStamped
    run.record(target.pose_topic, msg_type, qos=1000)
    if fault is not None:
        fault.start()
    try:
        result = run.run()
    finally:
        if fault is not None:
            fault.stop()
    by_stamp: dict[int, bytes] = {}
    for msg in result.messages[target.pose_topic]:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        by_stamp[stamp] = bytes(serialize_message(msg))
    return by_stamp, store_events(store)


def run_under_rory(target: Target, world: str, out: Path, *, domain_id: int, duration: float,
                   kill_at: float | None) -> tuple[dict[int, bytes], list[dict[str, Any]]]:
    """One run, SIGKILLed at ``kill_at`` sim seconds unless None; as :func:`run_supervised`."""
    out.mkdir(parents=True, exist_ok=True)
    inst = instrument(target, out / 'inst')
    command = ['python', str(inst / target.node_file), *target.argv(world)[2:]]
    killer = None
    if kill_at is not None:
        killer = Killer(out / 'run' / 'sim.log', world, out / 'store', kill_at)
    return run_supervised(target, world, out, domain_id=domain_id, duration=duration,
                          command=command, fault=killer)


def compare(reference: dict[int, bytes], crashed: dict[int, bytes],
            events: Sequence[dict[str, Any]]) -> Comparison:
    """Outputs stamp by stamp; after the release every reference stamp must be there."""
    common = sorted(set(reference) & set(crashed))
    identical = [s for s in common if reference[s] == crashed[s]]
    first = next((s for s in common if reference[s] != crashed[s]), None)
    recovered = [e for e in events if e['kind'] == 'recovered']
    missing = 0
    if recovered and crashed:
        # From the first output after the first release to the crash run's last one, every
        # output of the reference must be there (the stop may cut the two runs' ends
        # differently) - except inside a later outage: a strike after a release gets a
        # recovery of its own, and a node is silent while it recovers.
        outages = _outages(sorted(crashed), len(recovered))
        start, end = outages[0][1], max(crashed)
        missing = sum(1 for s in reference
                      if start <= s <= end and s not in crashed
                      and not any(a < s < b for a, b in outages[1:]))
    return Comparison(len(reference), len(crashed), len(common), len(identical), missing,
                      recovered[0]['total_ms'] if recovered else None,
                      '' if first is None else f'first difference at stamp {first / 1e9:.2f} s')


def _outages(stamps: list[int], recoveries: int) -> list[tuple[int, int]]:
    """The ``recoveries`` largest gaps between outputs (the outages), in time order.

    Each is (last output before, first output after); a run without a gap gives its first
    stamp as both.
    """
    if len(stamps) < 2:
        first = stamps[0] if stamps else 0
        return [(first, first)]
    gaps = sorted(itertools.pairwise(stamps), key=lambda ab: ab[1] - ab[0], reverse=True)
    return sorted(gaps[:max(1, recoveries)])


def main(argv: Sequence[str] | None = None) -> int:
    """Run both, print the comparison; exit 0 when exact."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.faults.target_crash',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--target', choices=sorted(EXACT_TARGETS), required=True)
    parser.add_argument('--world', default='office_small')
    parser.add_argument('--duration', type=float, default=40.0, help='sim seconds')
    parser.add_argument('--kill-at', type=float, default=15.0, help='sim seconds')
    parser.add_argument('--domain', type=int, default=200)
    parser.add_argument('--out', default='target-crash-out')
    args = parser.parse_args(argv)
    target = EXACT_TARGETS[args.target]
    out = Path(args.out) / f'{args.target}-{args.world}'
    reference, _ = run_under_rory(target, args.world, out / 'reference', domain_id=args.domain,
                                  duration=args.duration, kill_at=None)
    crashed, events = run_under_rory(target, args.world, out / 'crash', domain_id=args.domain,
                                     duration=args.duration, kill_at=args.kill_at)
    result = compare(reference, crashed, events)
    print(json.dumps({'target': args.target, 'world': args.world, 'kill_at': args.kill_at,
                      'exact': result.exact, **result.__dict__}))
    return 0 if result.exact else 1


if __name__ == '__main__':
    sys.exit(main())
