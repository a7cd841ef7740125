"""`rory supervise` as a process: clean stop on signals, crash loops, clean exits, bad config."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from rosbags.interfaces import QosDurability, QosReliability
from rosbags.rosbag2 import Reader
from supervision import events as read_events
from supervision import wait_for

from rory_eval.harness.scenario import EXAMPLE, Kill, Program, prepare, run, scenario_env
from rory_runtime import protocol
from rory_runtime.codec import decode_vars
from rory_runtime.store import CheckpointStore

pytestmark = pytest.mark.ros






def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie is dead for our purpose
    stat = Path(f'/proc/{pid}/stat')
    return stat.exists() and stat.read_text().split(')')[-1].split()[0] != 'Z'


def _supervise(config: Path, env: dict[str, str]) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
        env=env,
        cwd=config.parent,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


@pytest.fixture
def reap() -> Any:
    """Kill whatever a test started, even when it fails."""
    procs: list[subprocess.Popen[bytes]] = []
    yield procs
    for proc in procs:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_signal_stops_supervisor_and_its_node(
    sig: signal.Signals, tmp_path: Path, ros_domain: int, reap: list[Any]
) -> None:
    config = prepare(tmp_path, 'rory', interval=0.5, pace='paced')
    store = tmp_path / 'store-rory'
    sup = _supervise(config, scenario_env(ros_domain))
    reap.append(sup)
    wait_for(
        lambda: any(e.get('new') == 'RUNNING' for e in read_events(store)), 30, 'node RUNNING'
    )
    node_pid = next(e['pid'] for e in read_events(store) if e['kind'] == 'spawn')
    wait_for(
        lambda: any(e['kind'] == 'checkpoint' for e in read_events(store)), 10, 'a checkpoint'
    )
    wait_for(lambda: any(e['kind'] == 'standby' for e in read_events(store)), 10, 'a standby')
    standby_pid = next(e['pid'] for e in read_events(store) if e['kind'] == 'standby')
    sup.send_signal(sig)
    out, _ = sup.communicate(timeout=20)
    assert sup.returncode == 0, out.decode()
    assert not _alive(node_pid), 'the node outlived its supervisor'
    assert not _alive(standby_pid), 'the warm standby outlived its supervisor'
    text = out.decode()
    assert f'stopping ({sig.name})' in text
    assert 'integrator: STOPPING -> STOPPED' in text
    assert 'terminate called' not in text


def test_a_crash_is_recovered_by_the_warm_standby(tmp_path: Path, ros_domain: int) -> None:
    # No checkpoint before the one a clean stop takes: nothing is pruned, so the recovery log
    # R is still on disk at the end, beside the node's own segments.
    result = run('rory', (Kill(after=4.0),), tmp_path, domain_id=ros_domain, pace='fast',
                 interval=30.0)
    assert result.correct, result
    events = read_events(tmp_path / 'store-rory')
    standby = next(e for e in events if e['kind'] == 'standby')
    spawns = [e for e in events if e['kind'] == 'spawn']
    assert [s['warm'] for s in spawns[:2]] == [False, True]
    assert spawns[1]['pid'] == standby['pid'] and standby['incarnation'] == 1
    assert len(result.recoveries) == 1
    # Every closed segment, the node's and the supervisor's recovery log alike, says what QoS
    # the publisher offered (count_publisher: reliable, volatile).
    closed = [p.parent for p in (tmp_path / 'store-rory').glob('integrator/log/*/metadata.yaml')]
    assert len(closed) >= 2
    for segment in closed:
        with Reader(segment) as bag:
            for connection in bag.connections:
                if not protocol.is_input_topic(connection.topic):
                    continue  # a tick or clock record: no DDS topic, nothing offered
                (qos,) = connection.ext.offered_qos_profiles  # type: ignore[union-attr]
                # (Discovery does not carry a writer's history or depth: 0, as ros2 bag record has.)
                assert (qos.reliability, qos.durability) == (
                    QosReliability.RELIABLE, QosDurability.VOLATILE), segment


def test_crash_loop_backs_off_then_gives_up(
    tmp_path: Path, ros_domain: int, reap: list[Any]
) -> None:
    config = tmp_path / 'crashy.yaml'
    config.write_text(
        yaml.safe_dump(
            {
                'nodes': [
                    {
                        'name': 'crashy',
                        'command': ['python', '-c', 'import sys; sys.exit(3)'],
                        'method': 'restart',
                        'backoff': {'step': 0.1, 'max_restarts': 2},
                    }
                ]
            }
        )
    )
    sup = _supervise(config, scenario_env(ros_domain))
    reap.append(sup)
    out, _ = sup.communicate(timeout=60)
    text = out.decode()
    assert sup.returncode == 1, text
    events = read_events(tmp_path / '.rory')
    assert [e['code'] for e in events if e['kind'] == 'exit'] == [3, 3, 3]
    states = [e['new'] for e in events if e['kind'] == 'state']
    assert 'BACKOFF' in states and states[-3:] == ['FATAL', 'STOPPING', 'STOPPED']
    assert 'giving up' in text


def test_clean_exit_is_not_a_crash(tmp_path: Path, ros_domain: int, reap: list[Any]) -> None:
    config = tmp_path / 'done.yaml'
    config.write_text(
        yaml.safe_dump(
            {'nodes': [{'name': 'done', 'command': ['python', '-c', 'pass'], 'method': 'rory'}]}
        )
    )
    sup = _supervise(config, scenario_env(ros_domain))
    reap.append(sup)
    out, _ = sup.communicate(timeout=30)
    assert sup.returncode == 0, out.decode()
    events = read_events(tmp_path / '.rory')
    assert [e['kind'] for e in events].count('spawn') == 1
    assert 'EXITED' in [e['new'] for e in events if e['kind'] == 'state']


@pytest.mark.parametrize(
    ('node', 'field'),
    [
        ({'name': 'n', 'command': ['x'], 'method': 'respawn'}, 'nodes[0].method'),
        ({'name': 'n', 'command': ['x'], 'replay': 'slow'}, 'nodes[0].replay'),
        ({'name': 'n', 'command': ['x'], 'checkpoint_interval': 0}, 'nodes[0].checkpoint_interval'),
        ({'name': '/bad', 'command': ['x']}, 'nodes[0].name'),
        ({'name': 'n'}, 'nodes[0].command'),
    ],
)
def test_bad_config_exits_2_naming_file_and_field(
    node: dict[str, Any], field: str, tmp_path: Path
) -> None:
    config = tmp_path / 'bad.yaml'
    config.write_text(yaml.safe_dump({'nodes': [node]}))
    proc = subprocess.run(
        [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert proc.returncode == 2
    assert f'{config}: {field}:' in proc.stderr
    assert not (tmp_path / '.rory').exists(), 'a bad config must not touch the store'


def _threads(pid: int) -> list[str]:
    return [(task / 'comm').read_text().strip() for task in Path(f'/proc/{pid}/task').iterdir()]


def test_under_localhost_rory_runs_no_shared_memory_and_still_hears_plain_peers(
    tmp_path: Path, ros_domain: int, reap: list[Any]
) -> None:
    # A process SIGKILLed while holding a shared-memory port's mutex blocks every writer to
    # that port (a supervisor froze for 3 s; its ring lost messages). Under LOCALHOST the
    # supervisor and its nodes use UDPv4 on 127.0.0.1 only, and still talk to processes left
    # at the LOCALHOST defaults (shared memory and UDPv4).
    plain = {k: v for k, v in os.environ.items() if not k.startswith('FAST')}
    plain.update(ROS_DOMAIN_ID=str(ros_domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    config = prepare(tmp_path, 'rory', interval=0.5, pace='fast')
    store = tmp_path / 'store-rory'
    sup = _supervise(config, plain)
    reap.append(sup)
    wait_for(
        lambda: any(e.get('new') == 'RUNNING' for e in read_events(store)), 30, 'node RUNNING'
    )
    node_pid = next(e['pid'] for e in read_events(store) if e['kind'] == 'spawn')
    # The plain publisher waits for two readers (the node's and RORY's ring), sends 50
    # numbers and exits 0 once both acknowledged every one.
    publisher = subprocess.Popen(
        [sys.executable, str(EXAMPLE / 'count_publisher.py'), '50', '50', '2'], env=plain,
        cwd=tmp_path, start_new_session=True,
    )
    reap.append(publisher)
    assert publisher.wait(timeout=30) == 0
    for pid, who in ((sup.pid, 'supervisor'), (node_pid, 'node')):
        shm = [t for t in _threads(pid) if t.startswith('dds.shm')]
        assert not shm, f'{who} runs Fast DDS shared memory: {shm}'
        assert any(t.startswith('dds.udp') for t in _threads(pid)), who
    # The node runs RORY's profile, whose short lease lets the graph forget a killed node
    # within 1 s (its HELLO says what its participant was made with: a fork's
    # /proc/PID/environ is the supervisor's at its start); so does the standby that will
    # replace it, a fork made with the same environment, on UDPv4 alone.
    hello = next(e for e in read_events(store) if e['kind'] == 'hello')
    assert Path(hello['dds_profile']).name == 'fast_rediscovery_localhost_node.xml'
    wait_for(lambda: any(e['kind'] == 'standby' for e in read_events(store)), 20, 'a standby')
    standby_pid = next(e['pid'] for e in read_events(store) if e['kind'] == 'standby')
    wait_for(lambda: any(t.startswith('dds.udp') for t in _threads(standby_pid)), 20,
             'the standby participant')
    assert not [t for t in _threads(standby_pid) if t.startswith('dds.shm')]


def test_a_clean_stop_leaves_a_checkpoint_of_the_state_at_the_stop(
    tmp_path: Path, ros_domain: int, reap: list[Any]
) -> None:
    # Checkpoints every 60 s: none would be taken in this run but the one at the stop.
    config = prepare(tmp_path, 'rory', interval=60.0, pace=None)
    env = scenario_env(ros_domain)
    sup = _supervise(config, env)
    reap.append(sup)
    store = tmp_path / 'store-rory'
    wait_for(lambda: any(e.get('new') == 'RUNNING' for e in read_events(store)), 60,
             'the node running')
    publisher = subprocess.run(
        [sys.executable, str(EXAMPLE / 'count_publisher.py'), '40', '50', '2'], env=env,
        cwd=tmp_path, capture_output=True, timeout=60, check=False)
    assert publisher.returncode == 0, publisher.stdout
    time.sleep(0.5)  # acknowledged is received; let the callbacks run
    sup.send_signal(signal.SIGINT)
    assert sup.wait(timeout=30) == 0
    latest = CheckpointStore(store, 'integrator').latest_valid()
    assert latest is not None
    values = decode_vars(latest.vars_blob)
    assert (values['count'], values['total']) == (40, 40 * 41 // 2)


def test_a_node_installed_as_a_console_script_is_recovered_by_the_warm_standby(
    tmp_path: Path, ros_domain: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The instrumented integrator installed as pip installs a package's entry point:
    # `integrator_node = integrator:main`, the script on PATH, the module on PYTHONPATH.
    prepare(tmp_path, 'rory', interval=2.0, pace=None)
    site, bin_dir = tmp_path / 'site', tmp_path / 'bin'
    info = site / 'integrator_node-1.0.dist-info'
    info.mkdir(parents=True)
    (info / 'METADATA').write_text('Metadata-Version: 2.1\nName: integrator-node\nVersion: 1.0\n')
    (info / 'entry_points.txt').write_text(
        '[console_scripts]\nintegrator_node = integrator:main\n')
    bin_dir.mkdir()
    script = bin_dir / 'integrator_node'
    script.write_text(f'#!{sys.executable}\nimport sys\nfrom integrator import main\n'
                      'sys.exit(main())\n')
    script.chmod(0o755)
    monkeypatch.setenv('PYTHONPATH', os.pathsep.join(
        [str(tmp_path / 'out'), str(site), *filter(None, [os.environ.get('PYTHONPATH')])]))
    monkeypatch.setenv('PATH', f'{bin_dir}{os.pathsep}{os.environ["PATH"]}')
    program = Program(EXAMPLE, EXAMPLE / 'keyvars.yaml', 'integrator.py', '/integrator/state',
                      'integrator', settings=(('command', ['integrator_node']),))
    result = run('rory', (Kill(after=3.0),), tmp_path, domain_id=ros_domain, count=300,
                 interval=2.0, pace='fast', program=program)
    assert result.correct, result
    spawns = [e for e in read_events(tmp_path / 'store-rory') if e['kind'] == 'spawn']
    assert [s['warm'] for s in spawns[:2]] == [False, True], spawns  # the recovery: warm
