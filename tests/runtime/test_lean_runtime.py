"""What a robot installs (pyproject.toml: no extras) is enough for the runtime and the
instrumenter: neither imports the simulator's or the evaluation's packages, and `rory sim` /
`rory eval` without them say so in one line, exit 2. (`python -m rory_eval.lean_install` does
it for real in a clean venv.)"""

from __future__ import annotations

import subprocess
import sys

# Importing a module mapped to None in sys.modules fails, as if it were not installed.
WITHOUT_EXTRAS = '''
import sys
for name in ('mujoco', 'matplotlib', 'sim', 'rory_eval'):
    sys.modules[name] = None
'''


def _python(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-c', WITHOUT_EXTRAS + code], capture_output=True,
                          text=True, timeout=120)


def test_the_runtime_and_the_instrumenter_import_nothing_of_the_extras() -> None:
    done = _python('''
import rory_instrument.cli, rory_runtime.cli, rory_runtime.node.attach, rory_runtime.inspection
import rory_runtime.bundle, rory_runtime.kill, rory_runtime.supervisor.supervisor
import rory_runtime.supervisor.embed
print('ok')
''')
    assert done.returncode == 0 and done.stdout.strip() == 'ok', done.stderr


def test_sim_and_eval_without_their_extra_say_what_to_install() -> None:
    for command, missing in (('sim', 'mujoco'), ('eval', 'mujoco, matplotlib')):
        done = _python(f'''
from rory_runtime.cli import main
sys.exit(main(['{command}', '--help']))
''')
        assert done.returncode == 2, done.stderr
        assert done.stderr == (f'rory: error: rory {command} needs {missing}, not installed with '
                               f"the runtime: pip install 'rory-ros2[{command}]'\n")
