"""docs/launch.md's supervisor configuration is one RORY's parser takes as written."""

from __future__ import annotations

import re
from pathlib import Path

from rory_runtime.supervisor.config import load_config

DOC = Path(__file__).resolve().parents[2] / 'docs' / 'launch.md'


def test_the_configuration_in_the_launch_page_parses(tmp_path: Path) -> None:
    blocks = re.findall(r'```yaml\n(.*?)```', DOC.read_text(), re.S)
    supervise = next(b for b in blocks if b.startswith('nodes:'))
    path = tmp_path / 'robot' / 'supervise.yaml'
    path.parent.mkdir()
    path.write_text(supervise)
    config = load_config(path)
    assert [n.name for n in config.nodes] == ['amcl', 'mapper']
    assert config.nodes[1].checkpoint_interval == 1.0
    assert config.store == Path('/var/lib/rory/robot1')
    assert config.safe_state[0].topic == '/e_stop'
