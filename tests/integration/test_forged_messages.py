"""Another participant on the domain, or another process on the computer, without the run's key,
cannot steer a node or its supervisor: forged envelopes on the shadow topic and forged status
messages on the supervisor's status socket are refused."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import UInt8MultiArray
from supervision import events, wait_for

from rory_eval.harness.scenario import prepare, scenario_env
from rory_runtime import protocol

pytestmark = pytest.mark.ros


def _status_socket(pid: int) -> str:
    """The supervisor's status socket (abstract: ``@rory-status-<pid>-...`` in /proc/net/unix),
    as any process on the computer can find it."""
    for line in Path('/proc/net/unix').read_text().splitlines():
        name = line.split()[-1]
        if name.startswith(f'@rory-status-{pid}-'):
            return '\0' + name[1:]
    raise AssertionError(f'no status socket of {pid}')


def test_forged_envelopes_and_statuses_are_refused(tmp_path: Path, ros_domain: int) -> None:
    # A released node destroys its shadow subscription at its first checkpoint tick (nothing
    # comes on it after the handover); a long interval keeps it up while the rogue publishes.
    config = prepare(tmp_path, 'rory', interval=60.0, pace='fast')
    store = tmp_path / 'store-rory'
    log = tmp_path / 'supervisor.log'
    refusal = "ignoring malformed status: status signature does not match this run's key"
    # The supervisor's output goes to a file, so that the test can wait for its refusal: the
    # rogue's writer having matched the supervisor's reader does not mean the reader has matched
    # the writer yet, and a writer destroyed before that takes its message with it.
    with log.open('wb') as out:
        sup = subprocess.Popen(
            [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
            env=scenario_env(ros_domain), cwd=tmp_path, stdout=out,
            stderr=subprocess.STDOUT, start_new_session=True)
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain,
               signal_handler_options=SignalHandlerOptions.NO)
    rogue = Node('rogue', context=context)
    try:
        wait_for(lambda: any(e.get('new') == 'RUNNING' for e in events(store)), 30, 'RUNNING')
        incarnation = next(e['incarnation'] for e in events(store) if e['kind'] == 'spawn')
        shadow = rogue.create_publisher(
            UInt8MultiArray, protocol.replay_topic('integrator', incarnation),
            protocol.REPLAY_QOS)
        wait_for(lambda: shadow.get_subscription_count() >= 1, 20, 'the rogue publisher matched')
        # A message that was never published, pushed into the node as if replayed; and a
        # status that would end a recovery that is not happening.
        forged = protocol.pack_msg(incarnation, topic='/numbers', recv_ns=1, source_ns=1, seq=1,
                                   data=b'\x00\x01\x00\x00' + (41).to_bytes(8, 'little'))
        shadow.publish(forged)
        released = protocol.ReleasedStatus(
            applied=0, replayed=0, duplicates=0, muted=0, quarantined=0, passed_by_relay=0,
            ticks=0, ticks_replayed=0, clock_fallbacks=0, parameter_changes=0,
            parameter_changes_replayed=0, requests=0, requests_replayed=0)
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as status:
            status.sendto(protocol.encode_status(released, 'integrator', incarnation,
                                                 key=bytes(32)).encode(),
                          _status_socket(sup.pid))
        wait_for(lambda: any(e['kind'] == 'error' and 'not signed' in e.get('message', '')
                              for e in events(store)), 20, "the node's refusal")
        wait_for(lambda: refusal in log.read_text(errors='replace'), 20,
                 "the supervisor's refusal")
        kinds = [e['kind'] for e in events(store)]
        assert 'exit' not in kinds  # the node goes on
    finally:
        rogue.destroy_node()
        context.try_shutdown()
        sup.send_signal(signal.SIGINT)
        try:
            sup.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(sup.pid, signal.SIGKILL)
            sup.wait()
    assert refusal in log.read_text(errors='replace')
