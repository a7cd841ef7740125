"""A real supervisor's /diagnostics and /rory/events, heard by an ordinary ROS subscriber."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import Log
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import String
from supervision import stop, wait_for

from rory_eval.harness.scenario import prepare, scenario_env
from rory_runtime.supervisor.diagnostics import EVENTS_QOS

pytestmark = pytest.mark.ros


class _Listener:
    """Subscribes to /diagnostics and /rory/events in its own context."""

    def __init__(self, domain: int) -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node('diagnostics_listener', context=self.context)
        self.status: dict[str, str] = {}
        self.level: bytes | None = None
        self.message = ''
        self.events: list[dict[str, Any]] = []
        self.rosout: list[tuple[str, str]] = []
        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 10)
        # /rosout's writers keep their last 10 s (transient local): a reader that asks for it
        # gets a line logged before it matched the supervisor, as rqt_console does.
        self.node.create_subscription(
            Log, '/rosout', lambda m: self.rosout.append((m.name, m.msg)),
            QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.node.create_subscription(String, '/rory/events', self._on_event, EVENTS_QOS)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while self.context.ok():
            with contextlib.suppress(Exception):
                self.executor.spin_once(timeout_sec=0.05)

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name == 'rory: integrator':
                self.status = {kv.key: kv.value for kv in status.values}
                self.level = status.level
                self.message = status.message

    def _on_event(self, msg: String) -> None:
        self.events.append(json.loads(msg.data))

    def close(self) -> None:
        self.context.try_shutdown()
        self.thread.join(timeout=2.0)
        # The participant ends with the context's last node, not with its shutdown
        # (tests/sim/conftest.py, Probe.close).
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()




@pytest.fixture
def listener(ros_domain: int) -> Iterator[_Listener]:
    made = _Listener(ros_domain)
    yield made
    made.close()


def test_diagnostics_and_events_follow_a_crash_and_its_recovery(
    tmp_path: Path, ros_domain: int, listener: _Listener
) -> None:
    config = prepare(tmp_path, 'rory', interval=0.5, pace='fast')
    sup = subprocess.Popen(
        [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
        env=scenario_env(ros_domain), cwd=tmp_path, stdout=subprocess.DEVNULL,
        stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for(lambda: listener.status.get('state') == 'RUNNING'
                  and listener.status.get('last checkpoint age (s)', '') != '', 30,
                  'a RUNNING node with a checkpoint on /diagnostics')
        assert listener.level == DiagnosticStatus.OK
        assert listener.status['crashes'] == '0' and listener.status['method'] == 'rory'
        pid = int(listener.status['pid'])
        wait_for(lambda: listener.status.get('warm standby') == 'ready', 20, 'a ready standby')
        os.kill(pid, signal.SIGKILL)
        wait_for(lambda: listener.status.get('crashes') == '1'
                  and listener.status.get('state') == 'RUNNING', 30,
                  'the recovered node on /diagnostics')
        assert float(listener.status['last recovery (ms)']) > 0
        assert int(listener.status['pid']) != pid
        kinds = [e['kind'] for e in listener.events]
        assert {'spawn', 'state', 'checkpoint', 'exit', 'recovered'} <= set(kinds)
        states = [e['new'] for e in listener.events if e['kind'] == 'state']
        assert states[:3] == ['STARTING', 'ARMING', 'RUNNING']
        assert {'CRASHED', 'RESTORING', 'REPLAYING'} <= set(states)
    finally:
        stop(sup)


def test_ros_args_reach_the_supervisor_and_every_node_and_its_log_reaches_rosout(
    tmp_path: Path, ros_domain: int, listener: _Listener
) -> None:
    config = prepare(tmp_path, 'rory', interval=0.5, pace='fast')
    sup = subprocess.Popen(
        [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config),
         '--ros-args', '-r', '__ns:=/robot1'],
        env=scenario_env(ros_domain), cwd=tmp_path, stdout=subprocess.DEVNULL,
        stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wanted = {('integrator', '/robot1'), ('rory_supervisor', '/robot1')}
        wait_for(lambda: wanted <= set(listener.node.get_node_names_and_namespaces()), 30,
                  'the supervisor and the node in the namespace given by --ros-args')
        wait_for(lambda: any(name == 'robot1.rory_supervisor'
                              and '[rory] integrator: ARMING -> RUNNING' in text
                              for name, text in listener.rosout), 20,
                  "the supervisor's log on /rosout")
    finally:
        stop(sup)


def test_a_node_on_sim_time_without_a_clock_is_warned_about_overdue_checkpoints(
    tmp_path: Path, ros_domain: int, listener: _Listener
) -> None:
    # use_sim_time with no /clock: the node's ROS time stands still, so does its checkpoint
    # timer. Nothing fails; the operator must still hear that a crash would lose the run.
    config = prepare(tmp_path, 'rory', interval=0.5, pace='fast')
    sup = subprocess.Popen(
        [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config),
         '--ros-args', '-p', 'use_sim_time:=true'],
        env=scenario_env(ros_domain), cwd=tmp_path, stdout=subprocess.DEVNULL,
        stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for(lambda: listener.status.get('state') == 'RUNNING'
                  and listener.level == bytes(DiagnosticStatus.WARN), 30,
                  'a WARN on /diagnostics for the running node')
        assert listener.message.startswith('running; checkpoints overdue (none yet')
        wait_for(lambda: any(e['kind'] == 'checkpoints_overdue' for e in listener.events), 10,
                  'the checkpoints_overdue event')
        assert not any(e['kind'] == 'checkpoint' for e in listener.events)
    finally:
        stop(sup)
