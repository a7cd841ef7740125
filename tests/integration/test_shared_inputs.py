"""Two nodes that read the same topic, under one supervisor, SIGKILLed at the same moment: both
come back exact, each from a standby of the default pool. Their ring shares one reader of the
topic (rory_runtime/supervisor/ring.py, `SharedReader`), so each recovery's backlog comes from a
history the other node's activation also takes from. Real processes throughout: two
instrumented integrators, `rory supervise`, a publisher of 1..N; exactness as in
test_recovery_exact.py.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from rory_eval.harness.scenario import (
    EXAMPLE,
    EventsFile,
    EventTracker,
    _Observer,
    child_process,
    integrators_config,
    joining,
    scenario_env,
)

pytestmark = pytest.mark.ros

COUNT = 300  # 6 s at 50 Hz
NODES = ('left', 'right')
KILL_AFTER = 2.0  # s after both have applied their first number


def test_two_nodes_sharing_an_input_struck_together_both_recover_exactly(
    tmp_path: Path, ros_domain: int
) -> None:
    workdir = tmp_path.resolve()
    config = integrators_config(workdir, list(NODES))
    env = scenario_env(ros_domain)
    with joining(ros_domain):
        observers = {name: _Observer(ros_domain, f'/{name}/state') for name in NODES}
    events = EventsFile(workdir / 'store-rory' / 'events.jsonl')
    trackers = {name: EventTracker() for name in NODES}
    sup_log = workdir / 'supervisor.log'

    def poll() -> None:
        for ev in events.poll():
            if ev.get('node') in trackers:
                trackers[ev['node']].feed([ev])

    def wait_until(what: str, done: Any, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not done():
            poll()
            assert sup.poll() is None, f'supervisor exited:\n{sup_log.read_text()[-3000:]}'
            assert time.monotonic() < deadline, f'{what}:\n{sup_log.read_text()[-3000:]}'
            time.sleep(0.01)

    try:
        with child_process([sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
                           env, workdir, sup_log) as sup:
            wait_until('the nodes never ran',
                       lambda: all(t.state == 'RUNNING' for t in trackers.values()), 60.0)
            # Two nodes and one ring reader for both: the publisher waits for the three.
            publisher = [sys.executable, str(EXAMPLE / 'count_publisher.py'), str(COUNT), '50',
                         str(len(NODES) + 1)]
            with child_process(publisher, env, workdir, workdir / 'publisher.log') as pub:
                wait_until('no number was applied', lambda: all(
                    o.state.get('count', 0) > 0 for o in observers.values()), 30.0)
                # One reader of /numbers in the ring, not one per node.
                graph = observers[NODES[0]].node
                wait_until('the graph never showed 3 readers of /numbers',
                           lambda: graph.count_subscribers('/numbers') == len(NODES) + 1, 10.0)
                # The default pool holds a standby for each of the two (config.py,
                # standby_pool_size): both start warm.
                wait_until('the pool never had two standbys ready',
                           lambda: sup_log.read_text().count(' ready in ') >= len(NODES), 30.0)
                time.sleep(KILL_AFTER)
                pids = [trackers[name].pid for name in NODES]
                assert all(pid is not None for pid in pids)
                for pid in pids:
                    assert pid is not None
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGKILL)
                struck_at = time.monotonic()
                wait_until('the publisher never finished', lambda: pub.poll() is not None, 60.0)
                assert pub.returncode == 0, (workdir / 'publisher.log').read_text()
                wait_until('the nodes never ended exact', lambda: all(
                    o.state.get('count') == COUNT for o in observers.values()), 60.0)
            recovered = [e for e in events.events if e['kind'] == 'recovered']
    finally:
        for observer in observers.values():
            observer.close()
    assert sorted(e['node'] for e in recovered) == sorted(NODES), recovered
    respawns = [e for e in events.events if e['kind'] == 'spawn' and e['incarnation'] == 2]
    assert sorted(e['node'] for e in respawns if e['warm']) == sorted(NODES), respawns
    assert all(t.first_respawned_at is not None and t.first_respawned_at >= struck_at - 1.0
               for t in trackers.values())
    for name, observer in observers.items():
        history = observer.state['history']
        assert len(history) == len(set(history)), f'{name}: a number applied twice'
        assert history == list(range(1, COUNT + 1)), f'{name}: numbers lost or out of order'

