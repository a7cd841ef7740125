"""rory_runtime.supervise: the supervisor run from a program, with its config as a mapping."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from rory_eval.harness.scenario import scenario_env
from rory_runtime.errors import ConfigError
from rory_runtime.supervisor.embed import resolve_config


def test_a_mapping_is_validated_as_the_file_is(tmp_path: Path) -> None:
    config = resolve_config({'nodes': [{'name': 'a', 'command': ['python', 'a.py']}],
                             'store': 'st'}, folder=tmp_path)
    assert config.store == tmp_path / 'st' and config.nodes[0].command[0] == sys.executable
    with pytest.raises(ConfigError) as caught:
        resolve_config({'nodes': [{'name': 'a', 'command': ['x'], 'method': 'respawn'}]},
                       folder=tmp_path)
    assert str(caught.value).startswith(f'{tmp_path / "<mapping>"}: nodes[0].method: ')


@pytest.mark.ros
def test_a_program_supervises_and_gets_the_exit_code(tmp_path: Path, ros_domain: int) -> None:
    program = textwrap.dedent('''
        import sys
        import rory_runtime

        config = {'nodes': [{'name': 'once', 'command': ['python', '-c', 'print(42)'],
                             'method': 'restart'}]}
        sys.exit(rory_runtime.supervise(config, folder=sys.argv[1]))
    ''')
    done = subprocess.run([sys.executable, '-c', program, str(tmp_path)],
                          env=scenario_env(ros_domain), capture_output=True, text=True,
                          timeout=60, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout == '42\n'  # the node's; the supervisor logs through `logging`, unset here
    events = [json.loads(line) for line in
              (tmp_path / '.rory' / 'events.jsonl').read_text().splitlines()]
    assert [e['code'] for e in events if e['kind'] == 'exit'] == [0]
