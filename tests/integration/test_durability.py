"""The supervisor itself SIGKILLed: started again, it recovers the node from the store."""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from rory_eval.harness.scenario import (
    EXAMPLE,
    EventsFile,
    EventTracker,
    _Observer,
    child_process,
    joining,
    prepare,
    scenario_env,
)
from rory_runtime import protocol

pytestmark = pytest.mark.ros

SUPERVISE = [sys.executable, '-m', 'rory_runtime.cli', 'supervise']


def _wait(what: str, ok: Callable[[], bool], timeout: float, log: Path,
          sup: subprocess.Popen[bytes] | None = None) -> None:
    deadline = time.monotonic() + timeout
    while not ok():
        if time.monotonic() > deadline or (sup is not None and sup.poll() is not None):
            text = log.read_text(errors='replace') if log.exists() else ''
            raise AssertionError(f'{what} did not happen in {timeout} s\n{text[-3000:]}')
        time.sleep(0.02)


def _modes(store: Path) -> dict[Path, int]:
    """The permission bits of everything in a store, skipping what goes while it is read (a
    running node rotates and prunes its log)."""
    modes: dict[Path, int] = {}
    for path in [store, *store.rglob('*')]:
        try:
            modes[path.relative_to(store)] = stat.S_IMODE(path.stat().st_mode)
        except FileNotFoundError:
            continue
    return modes


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie is dead too: its parent (the killed supervisor) never reaped it
    stat = Path(f'/proc/{pid}/stat').read_text()
    return stat.rsplit(')', 1)[1].split()[0] != 'Z'


def test_supervisor_killed_then_started_again_resumes_the_node_from_the_store(
    tmp_path: Path, ros_domain: int
) -> None:
    workdir = tmp_path.resolve()
    config = prepare(workdir, 'rory', interval=1.0, pace='fast')
    store = workdir / 'store-rory'
    env = scenario_env(ros_domain)
    with joining(ros_domain):
        observer = _Observer(ros_domain)
    events = EventsFile(store / 'events.jsonl')
    tracker = EventTracker()
    publisher = [sys.executable, str(EXAMPLE / 'count_publisher.py')]

    def history() -> list[int]:
        return list(observer.state.get('history', []))

    def running() -> bool:
        tracker.feed(events.poll())
        return tracker.state == 'RUNNING'

    try:
        log1 = workdir / 'supervisor-1.log'
        with child_process([*SUPERVISE, str(config)], env, workdir, log1) as sup1:
            _wait('first start', running, 30, log1, sup1)
            node_pid = tracker.pid
            assert node_pid is not None
            # 1..100 over 2 s: checkpoints every second, the last numbers only in the log
            subprocess.run([*publisher, '100', '50', '2'], env=env, check=True, timeout=60)
            _wait('1..100 applied', lambda: history() == list(range(1, 101)), 15, log1)
            sup1.send_signal(signal.SIGKILL)  # not its session: the node must die by itself
            sup1.wait()
            _wait('the node dying with its supervisor', lambda: not _alive(node_pid), 5, log1)

        marker = json.loads((store / 'supervisor.json').read_text())
        assert marker['clean'] is False
        log2 = workdir / 'supervisor-2.log'
        with child_process([*SUPERVISE, str(config)], env, workdir, log2) as sup2:
            _wait('resumed', lambda: running() and tracker.pid != node_pid, 60, log2, sup2)
            kinds = [e['kind'] for e in events.events]
            assert 'resumed' in kinds
            resumed = next(e for e in events.events if e['kind'] == 'resumed')
            assert resumed['unrecorded_s'] is not None and resumed['unrecorded_s'] < 30
            assert (store / '.previous').exists() is False  # nothing was set aside
            _wait('state restored', lambda: history() == list(range(1, 101)), 15, log2)

            # A second supervisor on the same store is refused while this one lives.
            refused = subprocess.run([*SUPERVISE, str(config)], env=env, capture_output=True,
                                     text=True, timeout=60)
            assert refused.returncode == 1
            assert 'in use by another supervisor' in refused.stderr

            # ... and the node goes on from where it was.
            subprocess.run([*publisher, '50', '50', '2', '101'], env=env, check=True,
                           timeout=60)
            _wait('101..150 applied', lambda: history() == list(range(1, 151)), 15, log2)
            # Checkpoints and logs hold the robot's state and all it heard: the owner's only.
            # (Looked at while it runs: a clean stop checkpoints, and prunes the log before.)
            modes = _modes(store)
            wrong = {str(p): oct(m) for p, m in modes.items()
                     if m != (0o700 if (store / p).is_dir() else 0o600)}
            assert not wrong, wrong
            assert any(p.suffix == '.mcap' for p in modes) and len(modes) > 10
            sup2.send_signal(signal.SIGINT)
            assert sup2.wait(timeout=30) == 0
        assert json.loads((store / 'supervisor.json').read_text())['clean'] is True

        # After a clean stop the next run starts fresh and sets the old store aside.
        log3 = workdir / 'supervisor-3.log'
        with child_process([*SUPERVISE, str(config)], env, workdir, log3) as sup3:
            _wait('the old run set aside', (store / '.previous' / 'events.jsonl').exists, 30,
                  log3, sup3)
            fresh_events = EventsFile(store / 'events.jsonl')
            fresh = EventTracker()

            def fresh_running() -> bool:
                fresh.feed(fresh_events.poll())
                return fresh.state == 'RUNNING'

            _wait('fresh start', fresh_running, 30, log3, sup3)
            assert 'resumed' not in [e['kind'] for e in fresh_events.events]
            assert (store / '.previous' / 'integrator').exists()
    finally:
        observer.close()


def test_a_node_whose_status_is_never_heard_is_replaced_then_given_up(
    tmp_path: Path, ros_domain: int
) -> None:
    # The node runs and beats, but its HELLO never reaches the supervisor (a wrapper takes the
    # status socket's address out of its environment, so its runtime has nowhere to send):
    # after its hello_timeout (2 s here; 10 s by default) it is replaced, and after max_restarts
    # the supervisor gives up rather than wait forever in STARTING.
    import yaml

    workdir = tmp_path.resolve()
    config = prepare(workdir, 'rory', interval=1.0, pace='fast')
    (workdir / 'unheard.py').write_text(
        'import os, runpy\n'
        f'os.environ.pop({protocol.ENV_STATUS!r}, None)\n'
        "runpy.run_path('out/integrator.py', run_name='__main__')\n")
    doc = yaml.safe_load(config.read_text())
    doc['nodes'][0]['command'] = ['python', 'unheard.py']
    doc['nodes'][0]['backoff'] = {'max_restarts': 1}
    doc['nodes'][0]['hello_timeout'] = 2.0
    config.write_text(yaml.safe_dump(doc))
    env = scenario_env(ros_domain)
    log = workdir / 'supervisor.log'
    with child_process([*SUPERVISE, str(config)], env, workdir, log) as sup:
        assert sup.wait(timeout=90) == 1  # all nodes ended, FATAL
    events = [json.loads(line) for line in
              (workdir / 'store-rory' / 'events.jsonl').read_text().splitlines()]
    assert [e['kind'] for e in events].count('unheard') == 2
    reasons = [e['reason'] for e in events if e['kind'] == 'state' and e['new'] == 'CRASHED']
    assert reasons and all(r.startswith('unheard (no HELLO after 2.') for r in reasons), reasons
    states = [e['new'] for e in events if e['kind'] == 'state']
    assert states[-3:] == ['FATAL', 'STOPPING', 'STOPPED'], states
