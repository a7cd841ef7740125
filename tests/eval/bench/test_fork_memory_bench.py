"""The fork memory bench: every layout runs as real rclpy processes, forked children share
their parent's pages, and bad options are refused by name."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rory_eval.bench.fork_memory_bench import main

pytestmark = pytest.mark.ros


def test_every_layout_runs_and_forking_shares_pages(
    ros_domain: int, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / 'runs.json'
    assert main(['--runs', '1', '--settle', '3', '--domain', str(ros_domain),
                 '--out', str(out)]) == 0
    runs = json.loads(out.read_text())
    # One process bare; node, supervisor and standby; plus the fork server; the supervisor as
    # the parent of the other two.
    assert {layout: len(sizes[0]) for layout, sizes in runs.items()} == {
        'bare': 1, 'separate': 3, 'zygote': 4, 'parent': 3}
    separate = sum(runs['separate'][0])
    # Three interpreters that import rclpy on their own hold three copies of its objects;
    # forked ones share one (measured: 151 MB against 108 and 97).
    assert sum(runs['zygote'][0]) < separate
    assert sum(runs['parent'][0]) < separate
    assert '| parent | 3 |' in capsys.readouterr().out


def test_an_unknown_target_is_refused_by_name(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(['--target', 'no_such_node'])
    assert "'no_such_node'" in capsys.readouterr().err
