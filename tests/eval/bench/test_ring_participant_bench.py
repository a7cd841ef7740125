"""The ring participant bench: both configurations run as real processes, and bad options are
refused by name."""

from __future__ import annotations

import pytest

from rory_eval.bench.ring_participant_bench import main

pytestmark = pytest.mark.ros


def test_both_configurations_run_and_the_shared_one_has_fewer_threads(
    ros_domain: int, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(['--runs', '1', '--seconds', '1', '--peers', '1', '--topics', '2',
                 '--domain', str(ros_domain)]) == 0
    rows = [line.split('|') for line in capsys.readouterr().out.splitlines()
            if line.startswith('| a ') or line.startswith('| the ')]
    threads = {row[1].strip(): int(row[4]) for row in rows}
    # A participant of its own brings its own Fast DDS threads (receive, events, ...).
    assert threads['the supervisor\'s participant'] < threads['a participant of their own']


def test_a_run_count_below_one_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(['--runs', '0'])
    assert '--runs' in capsys.readouterr().err
