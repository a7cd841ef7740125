"""One evaluation run, as its own process: the simulator, the target, maybe a crash.

    python -m rory_eval.runs.runner RUN.json --out DIR --domain N --instrumented DIR

``RUN.json`` is a :class:`~rory_eval.runs.plan.RunSpec`. The target runs bare (the original
script) or under ``rory supervise`` with the spec's method, checkpoint interval and replay pace;
with a crash time, the node process is SIGKILLed that many seconds after the clock starts (the
simulator runs at real-time factor 1). The run leaves, in DIR:

* ``record.json`` - a :class:`RunRecord`: the pose outputs, the navigator's statuses, the
  collisions, ground truth, the supervisor's recovery events, CPU and RSS of the target's
  process tree (supervisor and node together under RORY);
* ``final_map.npz`` (mapping targets) or ``final_model.npy`` (the 3D model);
* ``run/`` - every process's log and the simulator's files; ``store/`` - RORY's store.

A run that fails (a process died, the clock never started) still writes ``record.json``, with
``error`` set, so the evaluation reports it instead of stopping.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
import traceback
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from rory_eval.harness.killer import Killer
from rory_eval.harness.simrun import LATCHED, SimRun, SimRunResult, store_events
from rory_eval.runs.plan import BARE, RunSpec
from rory_eval.targets import TARGETS, Kind, Target

RECORD = 'record.json'


@dataclass
class RunRecord:
    """What one run gave; plain data, saved as ``record.json``."""

    run: dict[str, Any]  # the RunSpec
    error: str = ''  # the run itself failed (not the target's result)
    wall_seconds: float = 0.0
    poses: list[tuple[float, float, float]] = field(default_factory=list)  # (t, x, y) in map
    statuses: list[str] = field(default_factory=list)  # navigator status changes
    collisions: int = 0
    ground_truth: list[tuple[float, float, float, float]] = field(default_factory=list)
    killed_at: float | None = None  # s after the clock started, when the SIGKILL was sent
    events: list[dict[str, Any]] = field(default_factory=list)  # recovered / exit / fatal
    cpu_percent: float = math.nan  # the target's process tree, % of one core
    peak_rss_mb: float = math.nan
    steady_cpu_percent: float = math.nan  # the tree over the run's second half
    pss_mb: float = math.nan  # the tree's proportional set size at the end
    usage_by_role: dict[str, dict[str, Any]] = field(default_factory=dict)  # node, supervisor...

    @property
    def spec(self) -> RunSpec:
        """The run this recorded."""
        return RunSpec.from_json(self.run)

    @property
    def recoveries(self) -> list[dict[str, Any]]:
        """The supervisor's 'recovered' events (crash detected -> released, and its steps)."""
        return [e for e in self.events if e.get('kind') == 'recovered']

    @property
    def gave_up(self) -> bool:
        """The supervisor went FATAL."""
        return any(e.get('kind') == 'fatal' for e in self.events)

    def save(self, folder: Path) -> None:
        """Write ``record.json`` in folder."""
        (folder / RECORD).write_text(json.dumps(asdict(self)) + '\n')

    @classmethod
    def load(cls, folder: Path) -> RunRecord:
        """Read ``record.json`` from folder."""
        data = json.loads((folder / RECORD).read_text())
        data['poses'] = [tuple(p) for p in data['poses']]
        data['ground_truth'] = [tuple(r) for r in data['ground_truth']]
        return cls(**data)


def readers(spec: RunSpec) -> int:
    """Readers each input topic gets from the target: the node, and RORY's ring if it logs."""
    return 2 if spec.method in ('rory', 'replay') else 1


def node_argv(target: Target, world: str) -> list[str]:
    """The original node's command line for a world (sim time, start pose, map remaps)."""
    if target.kind == Kind.LOCALIZATION and target.pose_topic != '/amcl_pose':
        # The navigator drives on /amcl_pose: another localizer's pose is remapped onto it.
        return target.argv(world, '-r', f'{target.pose_topic}:=/amcl_pose')
    return target.argv(world)


def instrument(target: Target, into: Path) -> Path:
    """The target instrumented by ``rory_instrument`` into ``into`` (once; reused after)."""
    if not (into / target.node_file).exists():
        into.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, '-m', 'rory_instrument', str(target.folder), '--vars',
                        str(target.keyvars), '-o', str(into)], check=True,
                       capture_output=True)
    return into


def supervisor_config(spec: RunSpec, argv: Sequence[str], instrumented: Path,
                      store: Path) -> dict[str, Any]:
    """``rory supervise``'s config for the run: the instrumented node with the spec's method."""
    target = spec.spec
    node: dict[str, Any] = {
        'name': target.name,
        'command': ['python', str(instrumented / target.node_file), *argv[2:]],
        'method': spec.method,
    }
    if spec.method in ('rory', 'checkpoint'):
        node['checkpoint_interval'] = spec.interval
    if spec.method in ('rory', 'replay'):
        node['replay'] = spec.replay
    # No safe state: /e_stop would stop the simulator's driver and change every later input,
    # and the reference run has none.
    return {'nodes': [node], 'store': str(store)}


def execute(spec: RunSpec, out: Path, *, domain_id: int, instrumented: Path) -> RunRecord:
    """Make the run; its record (also when it failed: ``error`` says how)."""
    out.mkdir(parents=True, exist_ok=True)
    record = RunRecord(run=spec.to_json())
    started = time.monotonic()
    try:
        _execute(spec, out, domain_id, instrumented, record)
    except Exception as exc:  # any failure becomes the record's error
        record.error = f'{type(exc).__name__}: {exc}'
        (out / 'error.txt').write_text(traceback.format_exc())
    record.wall_seconds = time.monotonic() - started
    record.events = [e for e in store_events(out / 'store')
                     if e.get('kind') in ('recovered', 'exit', 'fatal', 'spawn')]
    record.save(out)
    return record


def _execute(spec: RunSpec, out: Path, domain_id: int, instrumented: Path,
             record: RunRecord) -> None:
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String

    from rory_eval.harness.goals import goal_message
    from rory_eval.quality.navigator import relay_argv
    from sim.worlds import get_world

    target = spec.spec
    argv = node_argv(target, spec.world)
    n = readers(spec)
    closed_loop = target.kind in (Kind.NAVIGATION, Kind.LOCALIZATION)
    wait_for = {topic: n for topic in target.inputs}
    if target.kind == Kind.LOCALIZATION:
        # The navigator (bare) reads the scan and odometry too; the map is the localizer's.
        wait_for = {topic: n + 1 for topic in target.inputs}
        wait_for['/ground_truth/map'] = n + 1
    # The start delay lets latched data (the map) reach every node before the first scan, so
    # that start-up does not depend on DDS interleaving.
    run = SimRun(spec.world, out / 'run', domain_id=domain_id, duration=spec.duration,
                 driver='none' if closed_loop else 'internal', seed=spec.seed,
                 depth=target.depth, wait_for=wait_for, sim_args=['--start-delay', '1.0'])
    store = out / 'store'
    if spec.method == BARE:
        run.add_node(target.name, argv)
        usage_name = target.name
    else:
        config = out / 'supervise.yaml'
        config.write_text(yaml.safe_dump(supervisor_config(spec, argv, instrumented, store)))
        run.add_node('supervisor', [sys.executable, '-m', 'rory_runtime.cli', 'supervise',
                                    str(config)])
        usage_name = 'supervisor'
    world = get_world(spec.world)
    if target.kind == Kind.NAVIGATION:
        run.add_node('localizer', relay_argv(spec.seed + 1))
        run.publish_once('/goal_pose', goal_message(spec.world, world.default_goal),
                         subscribers=n)
    elif target.kind == Kind.LOCALIZATION:
        # The navigator drives on the localizer's pose, its goal latched (not the target).
        navigator = TARGETS['navigator'].node
        run.add_node('navigator', [sys.executable, str(navigator), '--ros-args',
                                   '-p', 'use_sim_time:=true', '-r', '/map:=/ground_truth/map'])
        run.publish_latched('/goal_pose', goal_message(spec.world, world.default_goal))
    if target.kind == Kind.MAP:
        run.record(target.result_topic, OccupancyGrid, qos=LATCHED, keep_last=True)
    elif target.kind == Kind.MODEL:
        run.record(target.result_topic, PointCloud2, qos=LATCHED, keep_last=True)
    if closed_loop:
        run.record('/navigator/status', String, qos=LATCHED)
    pose_topic = '/amcl_pose' if target.kind == Kind.LOCALIZATION else target.pose_topic
    if target.kind != Kind.NAVIGATION:
        pose_type = (PoseWithCovarianceStamped if target.kind == Kind.LOCALIZATION
                     else PoseStamped)
        run.record(pose_topic, pose_type, qos=1000)
    killer = None
    if spec.crash_at is not None:
        killer = Killer(out / 'run' / 'sim.log', spec.world, store, spec.crash_at)
        killer.start()
    try:
        result = run.run()
    finally:
        if killer is not None:
            killer.stop()
    if killer is not None:
        record.killed_at = killer.killed_at
        if killer.error:
            msg = f'the crash was not made: {killer.error}'
            raise RuntimeError(msg)
    _keep(result, record, target, pose_topic, out)
    usage = result.usage.get(usage_name)
    if usage is not None:
        record.cpu_percent, record.peak_rss_mb = usage.cpu_percent, usage.peak_rss_mb
        if usage.tree is not None:
            record.steady_cpu_percent = usage.tree.steady_cpu_percent
            record.pss_mb = usage.tree.pss_mb
            record.usage_by_role = usage.tree.to_json()


def _keep(result: SimRunResult, record: RunRecord, target: Target, pose_topic: str,
          out: Path) -> None:
    """What the judge and the figures need, from the run's messages."""
    record.ground_truth = [(round(t, 4), round(x, 4), round(y, 4), round(yaw, 4))
                           for t, x, y, yaw in result.ground_truth]
    record.collisions = int(result.summary.get('collisions', 0))
    for msg in result.messages.get('/navigator/status', []):
        if not record.statuses or record.statuses[-1] != msg.data:
            record.statuses.append(msg.data)
    poses = [] if target.kind == Kind.NAVIGATION else result.messages.get(pose_topic, [])
    for msg in poses:
        pose = msg.pose.pose if hasattr(msg.pose, 'pose') else msg.pose
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        record.poses.append((round(t, 4), round(pose.position.x, 4), round(pose.position.y, 4)))
    if target.kind == Kind.MAP and result.messages.get(target.result_topic):
        grid = result.last(target.result_topic)
        np.savez_compressed(
            out / 'final_map.npz',
            data=np.asarray(grid.data, dtype=np.int8).reshape(grid.info.height, grid.info.width),
            resolution=grid.info.resolution, origin_x=grid.info.origin.position.x,
            origin_y=grid.info.origin.position.y)
    if target.kind == Kind.MODEL and result.messages.get(target.result_topic):
        cloud = result.last(target.result_topic)
        points = np.frombuffer(bytes(cloud.data), dtype=np.float32).reshape(-1, 3)
        np.save(out / 'final_model.npy', points)


def main(argv: Sequence[str] | None = None) -> int:
    """Run one spec; exit 0 when the run completed (whatever the target's result)."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.runs.runner')
    parser.add_argument('spec', type=Path, help='RunSpec as JSON')
    parser.add_argument('--out', type=Path, required=True)
    parser.add_argument('--domain', type=int, required=True)
    parser.add_argument('--instrumented', type=Path, required=True)
    args = parser.parse_args(argv)
    spec = RunSpec.from_json(json.loads(args.spec.read_text()))
    if spec.target not in TARGETS:
        print(f'{args.spec}: unknown target {spec.target!r}', file=sys.stderr)
        return 2
    record = execute(spec, args.out.resolve(), domain_id=args.domain,
                     instrumented=args.instrumented.resolve())
    return 1 if record.error else 0


if __name__ == '__main__':
    sys.exit(main())
