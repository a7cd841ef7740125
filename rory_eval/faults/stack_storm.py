"""``make faults``, the six-target storm: every node of the stack SIGKILLed in the same millisecond.

One bug in a library every node loads, one OOM kill of a cgroup: the whole stack dies at once
(issue 38). Each run here is a pair, as ``rory eval`` makes them (the same world and seed):

* the **storm**: the six targets (grid_slam, graph_slam, depth_mapper, amcl, lama_local,
  navigator; the navigator driving to the world's goal on AMCL's pose) under one ``rory
  supervise`` (method rory, fast replay, the default standby pool, ``/e_stop`` held while any
  recovers, as the stack bench's rory configuration), struck once the stack has settled - every
  node RUNNING, each with a checkpoint taken, the standby pool full and ready, and not before
  :data:`STRIKE_AT` sim s - by one strike naming them all (``all``, rory_eval/harness/stack.py):
  six SIGKILLs in one loop, microseconds apart;
* then the **reference**: the same stack, the same seed, no crash, the robot stopped over the
  same sim seconds as in the storm (``/e_stop`` held by this harness from the simulator's own
  record of the storm's stops, :func:`stops_of`), so that the crashes are all that differs:
  by default the six under the same ``rory supervise``, not struck (``--reference bare``: the
  six bare, as ``rory eval``'s references are). The robot's path follows from the nodes'
  outputs, so what changes its timing changes what the camera sees: against a bare run without
  a stop, the six bare with a 1 s stop at 12 s gave depth_mapper a precision of 0.950; against
  the bare run with the stop, the six under RORY with it and no crash gave 0.948 (seed 0,
  2026-11-28; the judge's bar is 0.95). In ``rory eval`` the mapping targets follow the
  simulator's fixed route, and a bare reference differs from a crash run only by the crash.

The two mapping targets both publish ``/map``; here each is remapped onto its own
(:data:`MAP_TOPICS`, in both runs) so that each map is judged on its own.

A storm run passes when:

* every node is back: one ``recovered`` event each after the kill, nothing given up;
* every target is correct as ``rory eval`` judges it (rory_eval/evaluation/judge.py, run as
  ``python -m rory_eval.evaluation.judge``: this layer may not import it), its storm run
  against its reference;
* the safe state was held from the first crash until the last node was released, and released
  only then: one ``held`` and one ``released`` event, the hold before any node was back, the
  release in the last node's S4 (just before its ``recovered`` event), and on ``/e_stop`` itself
  exactly ``True`` then ``False``, the ``False`` heard after every other node was back;
* the last node is back (its ``recovered`` event) within :data:`BOUND` s of the first kill.

Per run it prints one line: each node's recovery time (the ``recovered`` event's total_ms, crash
detected to released) with whether it started warm (``w``) or cold (``c``) and when it was back
after the kill; the last one's time; the safe state; the judges. Everything, each recovery's
steps among it, is written to ``OUT/storm.json``. Exit 0 only if every run passed; 2 on bad
arguments.

    python -m rory_eval.faults.stack_storm --runs 3 [--world real_room] [--out DIR]
        [--standbys N]   # the pool's size; default the supervisor's (3 for six nodes)
        [--no-spare-forks]   # spare_forks: false (default: a spare for each node beyond it)
        [--reference rory|bare]   # the reference run (default: rory supervise, not struck)
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NoReturn

import yaml

from rory_eval.harness.simrun import (
    LATCHED,
    REPO,
    SimRun,
    SimRunError,
    SimRunResult,
    exit_on_sigterm,
    store_events,
)
from rory_eval.harness.stack import ALL, Strike, Striker, instrument
from rory_eval.runs.plan import BARE, WORLDS, RunSpec
from rory_eval.runs.runner import RunRecord, _keep
from rory_eval.targets import TARGETS, Kind

STACK = ('grid_slam', 'graph_slam', 'depth_mapper', 'amcl', 'lama_local', 'navigator')
MAP_TOPICS = {'grid_slam': '/grid_slam/map', 'graph_slam': '/graph_slam/map'}
"""Each mapping target's /map, remapped: both publish /map."""
SAFE_TOPIC = '/e_stop'
DURATION = 40.0  # sim s: the navigator's ~30 s to real_room's goal, a stop, and then some
STRIKE_AT = 12.0  # sim s: the stack bench's settle time; the strike also waits for settled()
SETTLE_TIMEOUT = 20.0  # s the strike waits past STRIKE_AT for the stack to settle
BOUND = 1.0  # s from the kill to the last node back (issue 38)
METHOD = 'rory'
STANDBY_READY = re.compile(r'standby pid (\d+) ready in')
STOP_LINE = re.compile(r'e-stop (ENGAGED|released) at t=([0-9.]+)')


def node_argv(name: str, world: str) -> list[str]:
    """The target's command line in a world (as the evaluation's), its map remapped."""
    target = TARGETS[name]
    remap = ['-r', f'/map:={MAP_TOPICS[name]}'] if name in MAP_TOPICS else []
    return target.argv(world, *remap)


def storm_config(world: str, out: Path, instrumented: Path, standbys: int | None = None,
                 spare_forks: bool = True) -> Path:
    """One supervisor config for the six, each its instrumented copy, /e_stop held;
    ``standbys``: the pool's size (None: the supervisor's default); ``spare_forks``: the
    config's."""
    nodes = []
    for name in STACK:
        argv = node_argv(name, world)
        copy = instrument(name, instrumented / name)
        nodes.append({'name': name,
                      'command': ['python', str(copy / TARGETS[name].node_file), *argv[2:]],
                      'method': METHOD, 'replay': 'fast'})
    config = {
        'nodes': nodes,
        'safe_state': [{'topic': SAFE_TOPIC, 'type': 'std_msgs/msg/Bool',
                        'hold': {'data': True}, 'release': {'data': False}}],
        'store': str(out / 'store'),
        'prefix_output': True,
        **({} if standbys is None else {'standbys': standbys}),
        **({} if spare_forks else {'spare_forks': False}),
    }
    out.mkdir(parents=True, exist_ok=True)
    path = out / 'stack.yaml'
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def input_readers(ring: bool) -> dict[str, int]:
    """Readers each input has once the stack is up (the simulator's clock waits for them): one
    per node that reads it, and under RORY the ring's one reader shared by them (ring.py)."""
    counts: dict[str, int] = {}
    for name in STACK:
        for topic in TARGETS[name].inputs:
            counts[topic] = counts.get(topic, 0) + 1
    return {topic: n + (1 if ring else 0) for topic, n in counts.items()}


def settled(store: Path, supervisor_log: Path, pool: int) -> str | None:
    """None once every node is RUNNING with a checkpoint taken and ``pool`` standbys are
    ready; else what is missing."""
    events = store_events(store)
    state: dict[str, str] = {}
    for event in events:
        if event.get('kind') == 'state':
            state[event['node']] = event.get('new', '')
    missing = [f'{n} not running' for n in STACK if state.get(n) != 'RUNNING']
    checkpointed = {e['node'] for e in events if e.get('kind') == 'checkpoint'}
    missing += [f'{n} has no checkpoint' for n in STACK if n not in checkpointed]
    started = {int(e['pid']) for e in events if e.get('kind') == 'standby'}
    text = supervisor_log.read_text(errors='replace') if supervisor_log.exists() else ''
    ready = {int(pid) for pid in STANDBY_READY.findall(text)} & started
    if len(ready) < pool:
        missing.append(f'{len(ready)} of {pool} standbys ready')
    return '; '.join(missing) or None


def stops_of(sim_log: Path) -> list[tuple[float, float | None]]:
    """The robot's stops in a run as the simulator logged them: (sim s engaged, sim s released;
    None: still stopped at the end)."""
    text = sim_log.read_text(errors='replace') if sim_log.exists() else ''
    stops: list[tuple[float, float | None]] = []
    for what, at in STOP_LINE.findall(text):
        if what == 'ENGAGED' and (not stops or stops[-1][1] is not None):
            stops.append((float(at), None))
        elif what == 'released' and stops and stops[-1][1] is None:
            stops[-1] = (stops[-1][0], float(at))
    return stops


class StopReplay(threading.Thread):
    """Holds ``/e_stop`` over given sim seconds of a run (its clock runs at wall pace, timed
    from the simulator's log saying it runs), as a supervisor's safe state would. The
    publisher is made at construction, before the run starts, so it has matched by then."""

    def __init__(self, sim_log: Path, world: str, domain_id: int,
                 stops: Sequence[tuple[float, float | None]]) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.node import Node
        from rclpy.signals import SignalHandlerOptions
        from std_msgs.msg import Bool

        from rory_eval.harness.scenario import joining

        super().__init__(daemon=True, name='stop-replay')
        self.sim_log, self.world, self.stops = sim_log, world, list(stops)
        self.context = Context()
        with joining(domain_id):
            rclpy.init(context=self.context, domain_id=domain_id,
                       signal_handler_options=SignalHandlerOptions.NO)
            self.node = Node('stack_storm_stop_replay', context=self.context)
        self.publisher = self.node.create_publisher(Bool, SAFE_TOPIC, LATCHED)
        self._message = Bool
        self._finish = threading.Event()
        self.errors: list[str] = []

    def run(self) -> None:
        from rory_eval.harness.simrun import wait_for_clock

        if not wait_for_clock(self.sim_log, self.world, self._finish, 120.0):
            self.errors.append('the clock never started (no stop replayed)')
            return
        start = time.monotonic()
        for on, off in self.stops:
            for at, data in ((on, True), (off, False)):
                if at is None or self._finish.wait(max(0.0, start + at - time.monotonic())):
                    return
                self.publisher.publish(self._message(data=data))

    def stop(self) -> None:
        self._finish.set()
        self.join(timeout=2.0)
        self.node.destroy_node()
        self.context.try_shutdown()


# -- what a storm showed ----------------------------------------------------------------------

@dataclass
class Recovery:
    """One node's recovery from the storm."""

    node: str
    total_ms: float  # the supervisor's: crash detected -> released
    warm: bool | None  # started from a standby; None: no spawn event for it
    back_ms: float  # first kill -> its recovered event
    steps: dict[str, float]  # s1_ms, s2_ms, restart_ms, restore_ms, sync_ms, replay_ms, s4_ms
    exit_ms: float | None = None  # first kill -> its exit event (the supervisor took the crash)


@dataclass
class Storm:
    """What one storm run showed, and what is wrong with it (nothing: it passed)."""

    recoveries: list[Recovery]  # in the order they ended
    last_back_ms: float | None  # first kill -> the last node's recovered event
    hold_after_ms: float | None  # first kill -> the hold heard on the safe-state topic
    release_after_ms: float | None  # the last node's recovered event -> the release heard
    safe_state: list[str]  # what is wrong with it
    verdicts: dict[str, dict[str, Any]]  # per target: correct, measures, reason
    problems: list[str] = field(default_factory=list)
    kill_spread_ms: float | None = None  # the first kill to the last
    # The depth_mapper's model, storm and reference: its points on the world's surfaces
    # (model_on_geometry); shown, not judged.
    model_on_geometry: dict[str, float | None] = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        """Every node back and correct, the safe state right, the last back in time."""
        return not self.problems


STEP_KEYS = ('s1_ms', 's2_ms', 'restart_ms', 'restore_ms', 'sync_ms', 'replay_ms', 's4_ms')


def analyse(kills: Sequence[tuple[float, str, int]], events: Sequence[dict[str, Any]],
            safe: Sequence[tuple[float, bool]], verdicts: dict[str, dict[str, Any]],
            *, nodes: Sequence[str] = STACK, bound: float = BOUND) -> Storm:
    """Judge a storm: ``kills`` (wall time, node, pid), the supervisor's events (wall ``t``),
    the safe-state topic as heard (wall time, data) and each target's judge verdict."""
    problems: list[str] = []
    killed = [node for _, node, _ in kills]
    if sorted(killed) != sorted(nodes):
        problems.append(f'struck {killed}, not each of {list(nodes)} once')
    if not kills:
        return Storm([], None, None, None, ['no strike'], dict(verdicts), problems)
    first_kill = min(t for t, _, _ in kills)
    spread = (max(t for t, _, _ in kills) - first_kill) * 1000.0
    if spread >= 1.0:
        problems.append(f'struck over {spread:.1f} ms, not within one millisecond')
    after = [e for e in events if float(e.get('t', 0.0)) >= first_kill]
    warm = {(e['node'], e.get('incarnation')): e.get('warm') for e in events
            if e.get('kind') == 'spawn'}
    recovered = [e for e in after if e.get('kind') == 'recovered']
    exits: dict[str, float] = {}
    for e in after:
        if e.get('kind') == 'exit':
            exits.setdefault(e['node'], round((float(e['t']) - first_kill) * 1000.0, 1))
    recoveries = [Recovery(e['node'], float(e['total_ms']),
                           warm.get((e['node'], e.get('incarnation'))),
                           round((float(e['t']) - first_kill) * 1000.0, 1),
                           {k: float(e[k]) for k in STEP_KEYS if k in e}, exits.get(e['node']))
                  for e in recovered]
    for node in nodes:
        mine = [r for r in recoveries if r.node == node]
        if len(mine) != 1:
            problems.append(f'{node}: {len(mine)} recoveries after the kill, not 1')
    fatal = sorted({e['node'] for e in after if e.get('kind') == 'fatal'})
    if fatal:
        problems.append(f'gave up: {", ".join(fatal)}')
    last_back = recoveries[-1].back_ms if recoveries else None
    if last_back is None or last_back > bound * 1000.0:
        problems.append(f'the last node back {last_back} ms after the kill (bound '
                        f'{bound * 1000:.0f} ms)')
    safe_problems, hold_after, release_after = _safe_state(first_kill, after, safe, recovered)
    problems += [f'safe state: {p}' for p in safe_problems]
    for node in nodes:
        verdict = verdicts.get(node)
        if verdict is None:
            problems.append(f'{node}: not judged')
        elif verdict.get('correct') is not True:
            how = 'not judged' if verdict.get('correct') is None else 'wrong'
            problems.append(f'{node}: {how} ({verdict.get("reason", "")})')
    return Storm(recoveries, last_back, hold_after, release_after, safe_problems,
                 dict(verdicts), problems, round(spread, 3))


def _safe_state(first_kill: float, after: Sequence[dict[str, Any]],
                safe: Sequence[tuple[float, bool]], recovered: Sequence[dict[str, Any]],
                ) -> tuple[list[str], float | None, float | None]:
    """What is wrong with the safe state; the hold's delay after the kill and the release's
    after the last node's recovered event, as heard on the topic (ms)."""
    problems = []
    order = [(e['kind'], e['node'], e.get('what')) for e in after
             if e.get('kind') in ('recovered', 'safe_state')]
    marks = [(kind, node, what) for kind, node, what in order if kind == 'safe_state']
    if [what for _, _, what in marks] != ['held', 'released']:
        problems.append(f'events {[what for _, _, what in marks]}, not one held and one '
                        'released')
    elif order[0][0] != 'safe_state':
        problems.append(f'{order[0][1]} was back before the safe state was held')
    elif order[-2:] != [('safe_state', order[-1][1], 'released'),
                        ('recovered', order[-1][1], None)]:
        problems.append(f'released in the S4 of {marks[1][1]}, not of the last node back '
                        f'({order[-1][1]})')
    heard = [(t, data) for t, data in safe if t >= first_kill]
    before = [data for t, data in safe if t < first_kill]
    if before:
        problems.append(f'{SAFE_TOPIC} carried {before} before the kill')
    if [data for _, data in heard] != [True, False]:
        problems.append(f'{SAFE_TOPIC} heard {[data for _, data in heard]}, not [True, False]')
        return problems, None, None
    (held_at, _), (released_at, _) = heard
    others_back = [float(e['t']) for e in recovered[:-1]]
    if others_back and released_at < max(others_back):
        problems.append(f'{SAFE_TOPIC} released before every other node was back')
    hold_after = round((held_at - first_kill) * 1000.0, 1)
    release_after = (round((released_at - float(recovered[-1]['t'])) * 1000.0, 1)
                     if recovered else None)
    return problems, hold_after, release_after


def describe(storm: Storm) -> str:
    """One line: the verdict, each node's time, the last one's, the safe state, the judges."""
    nodes = ', '.join(
        f'{r.node} {r.total_ms:.0f}{"w" if r.warm else "c" if r.warm is False else "?"}'
        f'/{r.back_ms:.0f}' for r in storm.recoveries)
    correct = sum(1 for v in storm.verdicts.values() if v.get('correct') is True)
    safe = ('held until the last release' if not storm.safe_state
            else 'WRONG (' + '; '.join(storm.safe_state) + ')')
    timing = (f'hold heard {storm.hold_after_ms:.0f} ms after the kill, release '
              f'{storm.release_after_ms:+.0f} ms from the last recovery'
              if storm.hold_after_ms is not None and storm.release_after_ms is not None else '')
    last = 'none' if storm.last_back_ms is None else f'{storm.last_back_ms:.0f} ms'
    head = 'PASS' if storm.passed else 'FAIL: ' + '; '.join(storm.problems)
    spread = ('' if storm.kill_spread_ms is None
              else f' (six kills over {storm.kill_spread_ms:.2f} ms)')
    geometry = storm.model_on_geometry
    on_surfaces = ('' if geometry.get('storm') is None or geometry.get('reference') is None
                   else f' ({MODEL_TARGET} model {geometry["storm"]:.2%} of points within '
                        f'{ON_GEOMETRY * 100:.0f} cm of the geometry, reference '
                        f'{geometry["reference"]:.2%})')
    return (f'{head} | last back {last} after the kill{spread} (bound {BOUND * 1000:.0f}) | ms '
            f'recovered (w warm, c cold)/back after the kill: {nodes} | {SAFE_TOPIC} {safe}'
            f'{"; " + timing if timing else ""} | judges {correct}/{len(STACK)} correct'
            f'{on_surfaces}')


# -- the runs ---------------------------------------------------------------------------------

def run_pair(world: str, out: Path, *, domain_id: int, seed: int, repetition: int,
             standbys: int | None = None, spare_forks: bool = True,
             reference_method: str = METHOD) -> tuple[Storm, dict[str, Any]]:
    """The storm, then its reference (the robot stopped as in the storm), both in ``out``;
    judged. Every process is reaped."""
    spec = _base_spec(world, seed, repetition)
    storm_dir = out / 'storm'
    details = _stack_run(METHOD, world, storm_dir, domain_id=domain_id, seed=seed, spec=spec,
                         instrumented=out.parent / 'instrumented', standbys=standbys,
                         spare_forks=spare_forks)
    details['stops'] = stops_of(storm_dir / 'run' / 'sim.log')
    reference = out / 'reference'
    replayed = _stack_run(reference_method, world, reference, domain_id=domain_id, seed=seed,
                          spec=spec, instrumented=out.parent / 'instrumented',
                          standbys=standbys, spare_forks=spare_forks, stops=details['stops'],
                          strike=False)
    details['reference_stops'] = stops_of(reference / 'run' / 'sim.log')
    details['errors'] += [f'reference: {e}' for e in replayed['errors']]
    verdicts = judge_targets([(storm_dir / n, reference / n) for n in STACK])
    storm = analyse(details['kills'], details['events'], details['safe'],
                    dict(zip(STACK, verdicts, strict=True)))
    storm.problems[:0] = details['errors']
    storm.model_on_geometry = {
        'storm': model_on_geometry(storm_dir / MODEL_TARGET / 'final_model.npy', world),
        'reference': model_on_geometry(reference / MODEL_TARGET / 'final_model.npy', world)}
    return storm, details


MODEL_TARGET = 'depth_mapper'
ON_GEOMETRY = 0.05  # m, as rory_eval/quality/depth_mapper.py counts a point on a surface


def model_on_geometry(model: Path, world: str) -> float | None:
    """The fraction of a point model's points within :data:`ON_GEOMETRY` of the world's
    surfaces (None: no model). Printed beside the judge, not judged: the judge compares the
    model with the reference's, and the closed-loop robot of a storm sees a slightly different
    scene from its reference's (docs/faults.md, "The six-target storm")."""
    import numpy as np

    from rory_eval.metrics import distance_to_geometry
    from sim.worlds import get_world

    if not model.is_file():
        return None
    points = np.load(model)
    if len(points) == 0:
        return None
    distance = distance_to_geometry(get_world(world), np.asarray(points)[:, :3])
    return float(np.mean(distance <= ON_GEOMETRY))


def _base_spec(world: str, seed: int, repetition: int) -> dict[str, Any]:
    return {'world': world, 'repetition': repetition, 'duration': DURATION, 'seed': seed,
            'replay': 'fast'}


def _stack_run(method: str, world: str, out: Path, *, domain_id: int, seed: int,
               spec: dict[str, Any], instrumented: Path | None = None,
               standbys: int | None = None, spare_forks: bool = True,
               stops: Sequence[tuple[float, float | None]] = (),
               strike: bool = True) -> dict[str, Any]:
    """One run of the six, bare or under one supervisor (struck unless ``strike`` is
    False), the robot stopped over ``stops``; each target's record folder (``out/NAME``:
    record.json, its map or model) in the runner's layout."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Bool, String

    from rory_eval.harness.goals import goal_message
    from rory_runtime.supervisor.config import load_config
    from sim.worlds import get_world

    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    rory = method != BARE
    run = SimRun(world, out / 'run', domain_id=domain_id, duration=DURATION, driver='none',
                 seed=seed, wait_for=input_readers(ring=rory), sim_args=['--start-delay', '1.0'])
    store = out / 'store'
    striker = None
    if rory:
        assert instrumented is not None
        config = storm_config(world, out, instrumented, standbys, spare_forks)
        pool = load_config(config).standby_pool_size
        run.add_node('supervisor', [sys.executable, '-m', 'rory_runtime.cli', 'supervise',
                                    str(config)])
        striker = Striker(out / 'run' / 'sim.log', world, store,
                          [Strike.parse(f'{STRIKE_AT}:{ALL}', STACK)],
                          ready=lambda: settled(store, out / 'run' / 'supervisor.log', pool),
                          ready_timeout=SETTLE_TIMEOUT) if strike else None
        run.record(SAFE_TOPIC, Bool, qos=LATCHED)
    else:
        pool = 0
        for name in STACK:
            run.add_node(name, node_argv(name, world))
    replay = (StopReplay(out / 'run' / 'sim.log', world, domain_id, stops) if stops
              else None)
    world_spec = get_world(world)
    run.publish_once('/goal_pose', goal_message(world, world_spec.default_goal),
                     subscribers=2 if rory else 1)
    run.record('/navigator/status', String, qos=LATCHED)
    for topic in MAP_TOPICS.values():
        run.record(topic, OccupancyGrid, qos=LATCHED, keep_last=True)
    run.record(TARGETS['depth_mapper'].result_topic, PointCloud2, qos=LATCHED, keep_last=True)
    for name in ('amcl', 'lama_local'):
        run.record(TARGETS[name].pose_topic, PoseWithCovarianceStamped, qos=1000)
    wall_minus_mono = time.time() - time.monotonic()
    error = ''
    result: SimRunResult | None = None
    for thread in (striker, replay):
        if thread is not None:
            thread.start()
    try:
        result = run.run()
    except SimRunError as err:
        error = f'{type(err).__name__}: {str(err).splitlines()[0]}'
    finally:
        for thread in (striker, replay):
            if thread is not None:
                thread.stop()
    events = store_events(store)
    kills = list(striker.done) if striker is not None else []
    struck_at = striker.struck_at[0] if striker is not None and striker.struck_at else None
    for name in STACK:
        folder = out / name
        folder.mkdir()
        run_spec = RunSpec(target=name, method=method,
                           crash_at=None if struck_at is None else round(struck_at, 3), **spec)
        record = RunRecord(run=run_spec.to_json(), error=error, killed_at=struck_at,
                           events=[e for e in events if e.get('node') == name and e.get('kind')
                                   in ('recovered', 'exit', 'fatal', 'spawn')])
        if result is not None:
            _keep(_view(result, name), record, TARGETS[name], _pose_topic(name), folder)
        record.save(folder)
    safe = ([(t + wall_minus_mono, bool(m.data)) for m, t in
             zip(result.messages.get(SAFE_TOPIC, []), result.received_at.get(SAFE_TOPIC, []),
                 strict=True)] if result is not None else [])
    errors = (([error] if error else []) + (striker.errors if striker is not None else [])
              + (replay.errors if replay is not None else []))
    if rory and strike and struck_at is None and not errors:
        errors.append('the stack was never struck')
    return {'kills': kills, 'events': events, 'safe': safe, 'errors': errors, 'pool': pool,
            'struck_at': struck_at}


def _pose_topic(name: str) -> str:
    return TARGETS[name].pose_topic


def _view(result: SimRunResult, name: str) -> SimRunResult:
    """The run as the runner's ``_keep`` expects one target's: its result on its own topic."""
    target = TARGETS[name]
    messages: dict[str, list[Any]] = {'/navigator/status':
                                      result.messages.get('/navigator/status', [])}
    if target.kind == Kind.MAP:
        messages[target.result_topic] = result.messages.get(MAP_TOPICS[name], [])
    elif target.kind == Kind.MODEL:
        messages[target.result_topic] = result.messages.get(target.result_topic, [])
    elif target.kind == Kind.LOCALIZATION:
        messages[target.pose_topic] = result.messages.get(target.pose_topic, [])
    return SimRunResult(out=result.out, messages=messages, received_at={},
                        summary=result.summary, ground_truth=result.ground_truth, usage={},
                        exit_codes={})


def judge_targets(pairs: Sequence[tuple[Path, Path]]) -> list[dict[str, Any]]:
    """Each (storm folder, reference folder) judged by ``rory eval``'s judge, in a child
    process (rory_eval.evaluation sits above this layer): its verdict as plain data."""
    argv = [sys.executable, '-m', 'rory_eval.evaluation.judge',
            *(str(p) for pair in pairs for p in pair)]
    done = subprocess.run(argv, capture_output=True, text=True, cwd=REPO, check=False)
    lines = done.stdout.splitlines()
    if done.returncode != 0 or len(lines) != len(pairs):
        why = (done.stderr.strip().splitlines() or ['no output'])[-1]
        return [{'correct': None, 'measures': {}, 'reason': f'the judge failed: {why}'}
                for _ in pairs]
    return [json.loads(line) for line in lines]


# -- the command ------------------------------------------------------------------------------

class _Parser(argparse.ArgumentParser):
    """Bad arguments: one line on stderr, exit 2."""

    def error(self, message: str) -> NoReturn:
        print(f'{self.prog}: {message}', file=sys.stderr)
        sys.exit(2)


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line; exits 2 with one line when it is wrong."""
    parser = _Parser(prog='python -m rory_eval.faults.stack_storm', description=__doc__,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--runs', type=int, default=3, help='storms, each with its reference')
    parser.add_argument('--world', default='real_room', choices=WORLDS)
    parser.add_argument('--seed', type=int, default=0, help='simulator seed (+ run)')
    parser.add_argument('--reference', choices=(METHOD, BARE), default=METHOD,
                        help='the reference run: the same supervisor not struck (default), or '
                             'the six bare')
    parser.add_argument('--standbys', type=int, default=None,
                        help="the standby pool's size (default: the supervisor's, 3 for six)")
    parser.add_argument('--no-spare-forks', dest='spare_forks', action='store_false',
                        help='the config says spare_forks: false')
    parser.add_argument('--domain', type=int, default=95, help='ROS domain id to use')
    parser.add_argument('--out', type=Path,
                        help='keep the runs here (default: a temporary folder, kept on failure)')
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error('--runs must be at least 1')
    if args.standbys is not None and args.standbys < 1:
        parser.error('--standbys must be at least 1')
    if not 0 <= args.domain <= 101:
        parser.error('--domain must be 0-101 (higher ids have ports in the ephemeral range)')
    return args


def summary(storms: Sequence[Storm]) -> list[str]:
    """The runs together: passes, warm and cold recovery times, the last node's times."""
    def spread(values: Sequence[float]) -> str:
        if not values:
            return 'none'
        return (f'median {statistics.median(values):.0f}, {min(values):.0f}-{max(values):.0f} '
                f'ms (n={len(values)})')

    rows = [r for s in storms for r in s.recoveries]
    lasts = [s.last_back_ms for s in storms if s.last_back_ms is not None]
    return [
        f'{sum(s.passed for s in storms)} of {len(storms)} storms passed',
        f'recovered (total_ms), warm: {spread([r.total_ms for r in rows if r.warm])}; '
        f'cold: {spread([r.total_ms for r in rows if r.warm is False])}',
        f'back after the kill, warm: {spread([r.back_ms for r in rows if r.warm])}; '
        f'cold: {spread([r.back_ms for r in rows if r.warm is False])}',
        f'the last node back after the kill: {spread(lasts)} (bound {BOUND * 1000:.0f} ms)',
    ]


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``--runs`` pairs; one line per storm and a summary; 0 only if every storm passed."""
    exit_on_sigterm()
    args = parse_args(argv)
    root = (args.out or Path(tempfile.mkdtemp(prefix='rory-stack-storm-'))).resolve()
    storms: list[Storm] = []
    record: list[dict[str, Any]] = []
    for i in range(args.runs):
        folder = root / f'run{i:03d}'
        began = time.monotonic()
        storm, details = run_pair(args.world, folder, domain_id=args.domain,
                                  seed=args.seed + i, repetition=i, standbys=args.standbys,
                                  spare_forks=args.spare_forks,
                                  reference_method=args.reference)
        storms.append(storm)
        record.append({'run': i, 'seed': args.seed + i, 'pool': details['pool'],
                       'spare_forks': args.spare_forks,
                       'reference': args.reference,
                       'struck_at': details['struck_at'], 'kills': details['kills'],
                       'safe_heard': details['safe'], 'stops': details['stops'],
                       'reference_stops': details['reference_stops'],
                       **asdict(storm), 'passed': storm.passed})
        (root / 'storm.json').write_text(json.dumps(record, indent=1))
        print(f'[{i + 1}] {describe(storm)} ({time.monotonic() - began:.0f} s'
              f'{"" if storm.passed else f"; {folder}"})', flush=True)
    for line in summary(storms):
        print(line)
    passed = all(s.passed for s in storms)
    if passed and args.out is None:
        shutil.rmtree(root, ignore_errors=True)
    elif args.out is None:
        print(f'kept in {root}')
    return 0 if passed else 1


if __name__ == '__main__':
    sys.exit(main())
