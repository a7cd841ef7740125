"""A key variable that is not state: refused where the source shows it, else at the first
checkpoint with a logged error naming the variable and its type; the node keeps running."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rory_eval.harness.scenario import Program, prepare, scenario_env

pytestmark = pytest.mark.ros

REFUSAL = Path(__file__).parent / 'refusal'


def test_a_lock_as_state_is_refused_at_the_first_checkpoint(
    tmp_path: Path, ros_domain: int
) -> None:
    program = Program(REFUSAL, REFUSAL / 'keyvars.yaml', 'guarded.py', '/state', 'guarded')
    config = prepare(tmp_path, 'rory', interval=0.5, pace='paced', program=program)
    events = tmp_path / 'store-rory' / 'events.jsonl'
    sup = subprocess.Popen(
        [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
        env=scenario_env(ros_domain), cwd=tmp_path, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 30
        errors: list[str] = []
        while not errors and time.monotonic() < deadline:
            if events.exists():
                for line in events.read_text().splitlines():
                    event = json.loads(line)
                    if event['kind'] == 'error':
                        errors.append(event['message'])
            time.sleep(0.1)
        assert errors, 'no error reported'
        assert "variable 'guard'" in errors[0]
        assert 'lock' in errors[0]
        assert 'checkpoint skipped' in errors[0]
        kinds = [json.loads(line)['kind'] for line in events.read_text().splitlines()]
        assert 'checkpoint' not in kinds  # refused, never half-written
        assert 'exit' not in kinds  # the node keeps running
    finally:
        sup.send_signal(signal.SIGINT)
        try:
            out, _ = sup.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(sup.pid, signal.SIGKILL)
            out, _ = sup.communicate()
    assert b'checkpoint skipped' in out  # logged by the supervisor too
