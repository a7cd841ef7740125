"""The instrumented program run alone (no supervisor) behaves exactly like the original."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rory_eval.harness.scenario import EXAMPLE, _Observer, joining, scenario_env

pytestmark = pytest.mark.ros

COUNT = 100


def _run_alone(program: Path, domain: int, tmp_path: Path) -> dict[str, object]:
    env = scenario_env(domain)
    env.pop('RORY_NODE', None)
    with joining(domain):
        observer = _Observer(domain)
    node = subprocess.Popen([sys.executable, str(program)], env=env, cwd=tmp_path)
    try:
        subprocess.run(
            [sys.executable, str(EXAMPLE / 'count_publisher.py'), str(COUNT), '100'],
            env=env,
            check=True,
            timeout=60,
        )
        deadline = time.monotonic() + 20
        while observer.state.get('count') != COUNT and time.monotonic() < deadline:
            time.sleep(0.05)
        return dict(observer.state)
    finally:
        node.terminate()
        node.wait(timeout=10)
        observer.close()


def test_instrumented_node_alone_matches_the_original(tmp_path: Path, ros_domain: int) -> None:
    out = tmp_path / 'out'
    subprocess.run(
        [
            sys.executable, '-m', 'rory_instrument', str(EXAMPLE),
            '--vars', str(EXAMPLE / 'keyvars.yaml'), '-o', str(out),
        ],
        check=True,
    )
    assert 'rory_runtime.checkpointed' in (out / 'integrator.py').read_text()
    original = _run_alone(EXAMPLE / 'integrator.py', ros_domain, tmp_path)
    instrumented = _run_alone(out / 'integrator.py', ros_domain, tmp_path)
    expected = list(range(1, COUNT + 1))
    assert original['history'] == expected
    assert instrumented == original


def test_unsupervised_decorator_returns_the_class_without_loading_the_runtime() -> None:
    code = (
        'import sys, rory_runtime\n'
        'class C: pass\n'
        'D = rory_runtime.checkpointed(vars=("x",), module_vars=("y",), checkpoint_interval=1.0,'
        ' replay="fast", manifest="sha256:0")(C)\n'
        'assert D is C\n'
        'rory_runtime.checkpoint_module(__name__, vars=("y",), checkpoint_interval=1.0,'
        ' replay="fast", manifest="sha256:0")\n'
        'assert "rory_runtime.node.attach" not in sys.modules, "runtime loaded unsupervised"\n'
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith('RORY_')}
    subprocess.run([sys.executable, '-c', code], env=env, check=True)
