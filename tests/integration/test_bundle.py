"""A node dies on one message on the robot; its bundle makes it die on that message again."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest
import yaml
from supervision import events, wait_for

from rory_eval.harness.scenario import EXAMPLE, scenario_env
from rory_runtime.bundle import bundle_main, reproduce_main

pytestmark = pytest.mark.ros

# The fault tests' node with a bug: the number 77 makes it raise.
FAULTS = Path(__file__).parent / 'faults'






def test_a_bundle_reproduces_the_crash_on_the_message_that_caused_it(
    tmp_path: Path, ros_domain: int, capsys: pytest.CaptureFixture[str]
) -> None:
    subprocess.run([sys.executable, '-m', 'rory_instrument', str(FAULTS), '--vars',
                    str(FAULTS / 'keyvars.yaml'), '-o', str(tmp_path / 'out')], check=True,
                   capture_output=True)
    config = tmp_path / 'supervise.yaml'
    config.write_text(yaml.safe_dump({
        'nodes': [{'name': 'fragile', 'command': ['python', 'out/poison.py'], 'method': 'rory',
                   'checkpoint_interval': 0.5, 'backoff': {'max_restarts': 1}}],
        'store': 'store',
    }))
    env = scenario_env(ros_domain)
    store = tmp_path / 'store'
    sup = subprocess.Popen([sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
                           env=env, cwd=tmp_path, stdout=subprocess.DEVNULL,
                           stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for(lambda: any(e.get('new') == 'RUNNING' for e in events(store)), 30, 'RUNNING')
        wait_for(lambda: any(e['kind'] == 'checkpoint' for e in events(store)), 10,
                  'a checkpoint')
        subprocess.run([sys.executable, str(EXAMPLE / 'count_publisher.py'), '80', '40', '2'],
                       env=env, cwd=tmp_path, check=True, timeout=60)
        # It dies on 77, is recovered, dies on 77 again: 77 is quarantined and, with
        # max_restarts 1, the supervisor gives up, leaving the store as the robot would.
        wait_for(lambda: any(e['kind'] == 'fatal' for e in events(store)), 60, 'FATAL')
    finally:
        os.killpg(sup.pid, signal.SIGINT)
        sup.wait(timeout=20)
    assert any(e['kind'] == 'quarantined' for e in events(store))

    crash = tmp_path / 'crash.tar'
    assert bundle_main([str(store), '--node', 'fragile', '-o', str(crash),
                        '--config', str(config)]) == 0
    with tarfile.open(crash) as tar:
        names = tar.getnames()
    assert 'report.txt' in names and 'bundle.json' in names and 'code/poison.py' in names
    assert any(n.startswith('store/fragile/checkpoints/') for n in names)
    assert any(n.startswith('quarantine/') for n in names)

    # Elsewhere (a temporary folder, another domain): it dies on 77 again, saying how far it
    # is as it goes; the log it names is still there afterwards.
    capsys.readouterr()
    code = reproduce_main([str(crash), '--timeout', '60', '--domain', str(ros_domain)])
    out = capsys.readouterr().out
    named = re.search(r'log in (\S+)', out)
    assert named is not None, out
    log = Path(named.group(1))
    assert code == 0, out + log.read_text()[-3000:]
    assert 'REPRODUCED: fragile died (exit status 1)' in out
    assert 'while applying /numbers' in out and 'seq 77)' in out  # the 77th message: 77
    assert 'rory reproduce: started the node' in out
    assert 'rory reproduce: restored the checkpoint' in out
    assert log.is_file() and 'fragile' in log.read_text()
    assert not log.with_suffix('').exists()  # the extracted bundle is gone
    log.unlink()


def test_bad_input_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert bundle_main([str(tmp_path), '--node', 'ghost', '-o', str(tmp_path / 'x.tar')]) == 2
    assert "no node 'ghost'" in capsys.readouterr().err
    (tmp_path / 'junk.tar').write_bytes(b'not a tar file')
    assert reproduce_main([str(tmp_path / 'junk.tar'), '-C', str(tmp_path / 'd')]) == 2
    assert 'junk.tar: not a readable bundle' in capsys.readouterr().err


def test_a_bundle_made_after_the_node_went_past_a_poison_message_still_reproduces_it(
    tmp_path: Path, ros_domain: int, capsys: pytest.CaptureFixture[str]
) -> None:
    subprocess.run([sys.executable, '-m', 'rory_instrument', str(FAULTS), '--vars',
                    str(FAULTS / 'keyvars.yaml'), '-o', str(tmp_path / 'out')], check=True,
                   capture_output=True)
    config = tmp_path / 'supervise.yaml'
    config.write_text(yaml.safe_dump({
        'nodes': [{'name': 'fragile', 'command': ['python', 'out/poison.py'], 'method': 'rory',
                   'checkpoint_interval': 0.5}],
        'store': 'store',
    }))
    env = scenario_env(ros_domain)
    store = tmp_path / 'store'
    sup = subprocess.Popen([sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
                           env=env, cwd=tmp_path, stdout=subprocess.DEVNULL,
                           stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for(lambda: any(e.get('new') == 'RUNNING' for e in events(store)), 30, 'RUNNING')
        subprocess.run([sys.executable, str(EXAMPLE / 'count_publisher.py'), '80', '40', '2'],
                       env=env, cwd=tmp_path, check=True, timeout=60)
        wait_for(lambda: any(e['kind'] == 'quarantined' for e in events(store)), 60,
                  'the poison message quarantined')

        def checkpoints_after_quarantine() -> int:
            seen = events(store)
            at = next(i for i, e in enumerate(seen) if e['kind'] == 'quarantined')
            return sum(e['kind'] == 'checkpoint' for e in seen[at:])

        # It goes on past 77: the two checkpoints the store keeps are both past it.
        wait_for(lambda: checkpoints_after_quarantine() >= 3, 30, 'checkpoints past 77')
    finally:
        os.killpg(sup.pid, signal.SIGINT)
        sup.wait(timeout=20)

    crash = tmp_path / 'crash.tar'
    assert bundle_main([str(store), '--node', 'fragile', '-o', str(crash),
                        '--config', str(config)]) == 0
    assert 'warning' not in capsys.readouterr().err
    code = reproduce_main([str(crash), '-C', str(tmp_path / 'desk'), '--timeout', '60',
                           '--domain', str(ros_domain)])
    out = capsys.readouterr().out
    assert code == 0, out + (tmp_path / 'desk' / 'supervisor.log').read_text()[-3000:]
    assert 'REPRODUCED: fragile died' in out and 'seq 77)' in out
