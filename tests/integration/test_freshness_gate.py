"""Freshness rules and the release gate with real processes (issue 27): the integrator's
`history` has a max_age far shorter than any recovery takes, so it is always stale when
restored; `total` and `count` have no rule.

* a crash: history reset, total and count restored; the node waits at its release gate, live
  with its outputs muted and /e_stop held, until /rory/integrator/release is called; then every
  number is counted once;
* the same after the supervisor itself was killed and started again on the store it left;
* on_stale: refuse: the node is not started, the supervisor gives up with the safe state held;
* a gate's timeout: released, or given up with the safe state held.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from supervision import events, wait_for

from rory_eval.harness.scenario import EXAMPLE, scenario_env

pytestmark = pytest.mark.ros

NUMBERS = 150
RATE = 30.0  # Hz: 5 s of numbers
MAX_AGE = 0.05  # s: shorter than any restore after a crash can be

CALL_RELEASE = '''
import sys, rclpy
from std_srvs.srv import Trigger
rclpy.init()
node = rclpy.create_node('operator')
client = node.create_client(Trigger, sys.argv[1])
assert client.wait_for_service(timeout_sec=10.0), 'no release service'
future = client.call_async(Trigger.Request())
rclpy.spin_until_future_complete(node, future, timeout_sec=10.0)
print(f'{future.result().success} {future.result().message}')
'''


def _setup(tmp_path: Path, on_stale: str, gate: bool | dict[str, Any],
           method: str = 'rory') -> Path:
    """The integrator instrumented with a rule on history; its supervisor config's path."""
    keyvars = tmp_path / 'keyvars.yaml'
    keyvars.write_text(yaml.safe_dump({'nodes': [{
        'file': 'integrator.py', 'class': 'Integrator',
        'vars': ['total', 'count', {'name': 'history', 'max_age': MAX_AGE,
                                    'on_stale': on_stale}]}]}))
    subprocess.run([sys.executable, '-m', 'rory_instrument', str(EXAMPLE), '--vars',
                    str(keyvars), '-o', str(tmp_path / 'out')], check=True, capture_output=True)
    node: dict[str, Any] = {'name': 'integrator', 'command': ['python', 'out/integrator.py'],
                            'checkpoint_interval': 1.0, 'method': method}
    if gate:
        node['release_gate'] = gate if isinstance(gate, dict) else {'timeout': None}
    config = tmp_path / 'supervise.yaml'
    config.write_text(yaml.safe_dump({
        'nodes': [node], 'store': 'store',
        'safe_state': [{'topic': '/e_stop', 'type': 'std_msgs/msg/Bool',
                        'hold': {'data': True}, 'release': {'data': False}}]}))
    shutil.copy(EXAMPLE / 'count_publisher.py', tmp_path / 'count_publisher.py')
    shutil.copy(EXAMPLE / 'tally.py', tmp_path / 'tally.py')
    return config


class _Run:
    """A supervisor, a count publisher and whatever else a test starts; all reaped."""

    def __init__(self, tmp_path: Path, domain: int) -> None:
        self.dir = tmp_path
        self.env = scenario_env(domain)
        self.store = tmp_path / 'store'
        self.procs: list[subprocess.Popen[bytes]] = []
        self.logs = 0

    def start(self, *argv: str) -> subprocess.Popen[bytes]:
        self.logs += 1
        log = open(self.dir / f'proc{self.logs}.log', 'wb')  # noqa: SIM115 (closed at exit)
        proc = subprocess.Popen([sys.executable, *argv], cwd=self.dir, env=self.env,
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        log.close()
        self.procs.append(proc)
        return proc

    def supervise(self) -> subprocess.Popen[bytes]:
        return self.start('-m', 'rory_runtime.cli', 'supervise', 'supervise.yaml')

    def log(self, proc: subprocess.Popen[bytes]) -> str:
        return (self.dir / f'proc{self.procs.index(proc) + 1}.log').read_text(errors='replace')

    def output(self, *argv: str) -> str:
        done = subprocess.run([sys.executable, *argv], cwd=self.dir, env=self.env,
                              capture_output=True, text=True, timeout=60)
        return done.stdout.strip()

    def events(self, kind: str) -> list[dict[str, Any]]:
        return [e for e in events(self.store) if e['kind'] == kind]

    def state_is(self, new: str) -> bool:
        states = self.events('state')
        return bool(states) and states[-1]['new'] == new

    def kill_node_after_a_checkpoint(self) -> None:
        wait_for(lambda: len(self.events('checkpoint')) >= 2, 30, 'two checkpoints')
        time.sleep(0.3)  # well past MAX_AGE since the checkpoint
        out = self.output('-m', 'rory_runtime.cli', 'kill', 'store', 'integrator')
        assert 'sent SIGKILL' in out, out

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


@pytest.fixture
def run(tmp_path: Path, ros_domain: int) -> Any:
    r = _Run(tmp_path, ros_domain)
    try:
        yield r
    finally:
        r.close()


def _e_stop(run: _Run) -> list[str]:
    return [e['what'] for e in run.events('safe_state')]


def _gated_then_released(run: _Run) -> dict[str, Any]:
    """Wait at the gate (live, muted, /e_stop held), call the service; the recovered event."""
    wait_for(lambda: run.state_is('GATED'), 30, 'the node at its release gate')
    time.sleep(1.0)
    assert run.state_is('GATED') and _e_stop(run)[-1] == 'held'
    assert not run.events('recovered')
    answer = run.output('-c', CALL_RELEASE, '/rory/integrator/release')
    assert answer == 'True integrator: released', answer
    wait_for(lambda: bool(run.events('recovered')), 10, 'the recovery to end')
    assert run.state_is('RUNNING') and _e_stop(run)[-1] == 'released'
    (recovered,) = run.events('recovered')
    assert recovered['gate_ms'] >= 1000.0 and 'release called' in recovered['gate']
    # Live while it waited, its outputs muted: its state, published once a second and after
    # every number, went nowhere for that second and more.
    (opened,) = run.events('gate_opened')
    assert opened['muted'] > recovered['muted'], (opened, recovered)
    # Again, with nothing waiting: refused, and said why.
    answer = run.output('-c', CALL_RELEASE, '/rory/integrator/release')
    assert answer.startswith('False integrator: RUNNING'), answer
    return recovered


def _assert_reset_history_only(run: _Run, recovered: dict[str, Any]) -> None:
    verdict = recovered['freshness']
    assert verdict['restored'] == ['total', 'count'] and verdict['reset'] == ['history']
    assert verdict['age_s'] > MAX_AGE and verdict['max_age'] == {'history': MAX_AGE}


def test_a_crash_resets_the_stale_variable_and_waits_at_the_gate(run: _Run) -> None:
    _setup(run.dir, 'reset', gate=True)
    supervisor = run.supervise()
    publisher = run.start('count_publisher.py', str(NUMBERS), str(RATE), '@integrator')
    run.kill_node_after_a_checkpoint()
    recovered = _gated_then_released(run)
    _assert_reset_history_only(run, recovered)
    assert publisher.wait(timeout=30) == 0
    # total and count were restored and, live while gated, kept counting: every number once.
    # history was reset at the restore: it holds what came after the checkpoint only.
    state = json.loads(run.output('-c', STATE, '/integrator/state'))
    assert (state['count'], state['total']) == (NUMBERS, NUMBERS * (NUMBERS + 1) // 2)
    assert state['history'][0] > 1 and state['history'][-1] == NUMBERS
    assert state['history'] == list(range(state['history'][0], NUMBERS + 1))
    supervisor.send_signal(signal.SIGINT)
    supervisor.wait(timeout=20)
    text = run.log(supervisor)
    assert 'integrator: REPLAYING -> GATED (caught up; outputs muted' in text, text
    assert f'stale, reset: history (max_age {MAX_AGE:g} s)' in text, text


STATE = '''
import sys, rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node('reader')
got = []
node.create_subscription(String, sys.argv[1], lambda m: got.append(m.data),
                         QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
while not got:
    rclpy.spin_once(node, timeout_sec=0.1)
rclpy.spin_once(node, timeout_sec=1.5)  # the last number's state, if it is on its way
print(got[-1])
'''


def test_after_a_supervisor_restart_on_an_old_store_the_same_holds(run: _Run) -> None:
    _setup(run.dir, 'reset', gate=True)
    first = run.supervise()
    wait_for(lambda: len(run.events('checkpoint')) >= 2, 30, 'two checkpoints')
    first.send_signal(signal.SIGKILL)  # a power cut: the node dies with it
    first.wait(timeout=10)
    time.sleep(1.0)
    second = run.supervise()
    wait_for(lambda: bool(run.events('resumed')), 30, 'the resume from the store')
    recovered = _gated_then_released(run)
    _assert_reset_history_only(run, recovered)
    assert recovered['freshness']['age_s'] > 1.0
    second.send_signal(signal.SIGINT)
    assert second.wait(timeout=20) == 0


def test_a_stale_variable_under_refuse_stops_the_start(run: _Run) -> None:
    _setup(run.dir, 'refuse', gate=False)
    supervisor = run.supervise()
    run.start('count_publisher.py', str(NUMBERS), str(RATE), '@integrator')
    run.kill_node_after_a_checkpoint()
    assert supervisor.wait(timeout=30) == 1  # its only node given up
    (fatal,) = run.events('fatal')
    assert fatal['freshness']['refused'] == ['history']
    assert 'checkpoint too old for history' in fatal['reason']
    assert not run.events('recovered')
    assert _e_stop(run)[-1] == 'held'
    spawns = run.events('spawn')
    assert len(spawns) == 2  # the refused process was not started again
    refused_pid = spawns[-1]['pid']
    assert not Path(f'/proc/{refused_pid}').exists() or 'Z' in Path(
        f'/proc/{refused_pid}/stat').read_text().split(')')[-1].split()[0]
    text = run.log(supervisor)
    assert 'RESTORING -> FATAL (checkpoint too old for history' in text, text


@pytest.mark.parametrize('on_timeout', ['release', 'give_up'])
def test_a_gate_nobody_calls_does_what_its_timeout_says(run: _Run, on_timeout: str) -> None:
    # release under checkpoint: no replay, so no SYNC has proved the path OPEN takes
    _setup(run.dir, 'keep', gate={'timeout': 1.0, 'on_timeout': on_timeout},
           method='checkpoint' if on_timeout == 'release' else 'rory')
    supervisor = run.supervise()
    run.start('count_publisher.py', str(NUMBERS), str(RATE), '@integrator')
    run.kill_node_after_a_checkpoint()
    wait_for(lambda: run.state_is('GATED'), 30, 'the node at its release gate')
    gated_at = run.events('state')[-1]['t']
    if on_timeout == 'release':
        wait_for(lambda: bool(run.events('recovered')), 10, 'the release at the timeout')
        (recovered,) = run.events('recovered')
        assert 'on_timeout: release' in recovered['gate'] and recovered['gate_ms'] >= 1000.0
        assert recovered['freshness']['kept_stale'] == ['history']
        assert run.state_is('RUNNING') and _e_stop(run)[-1] == 'released'
        supervisor.send_signal(signal.SIGINT)
        assert supervisor.wait(timeout=20) == 0
        return
    assert supervisor.wait(timeout=30) == 1  # its only node given up
    (fatal,) = run.events('fatal')
    assert 'within 1 s; on_timeout: give_up' in fatal['reason'] and fatal['t'] - gated_at >= 1.0
    assert not run.events('recovered') and _e_stop(run)[-1] == 'held'
