"""The message cost bench's split by thread, and which process it measures
(rory_eval/bench/message_cost_bench.py)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from rory_eval.bench.message_cost_bench import PROGRAMS, _node_pid, thread_table, thread_us


def test_the_main_thread_is_named_main_and_threads_of_a_kind_add_up() -> None:
    before = {7: ('/work/main/.ven', 1_000_000, 1), 8: ('dds.udp', 0, 1), 9: ('dds.udp', 0, 1)}
    after = {7: ('/work/main/.ven', 3_000_000, 9), 8: ('dds.udp', 400_000, 3),
             9: ('dds.udp', 600_000, 3), 10: ('rory-io', 100_000, 1)}
    # 1000 messages: 2 ms on the main thread is 2 us a message.
    assert thread_us(before, after, 7, 1000) == {'dds.udp': 1.0, 'main': 2.0, 'rory-io': 0.1}


def test_the_table_gives_medians_per_configuration_and_leaves_out_idle_kinds() -> None:
    runs = [
        {'config': 'bare', 'threads_us': {'main': 200.0, 'dds.udp': 25.0, 'dds.ev': 0.1}},
        {'config': 'bare', 'threads_us': {'main': 220.0, 'dds.udp': 27.0, 'dds.ev': 0.2}},
        {'config': 'bare', 'threads_us': {'main': 210.0, 'dds.udp': 26.0, 'dds.ev': 0.1}},
        {'config': 'rory', 'threads_us': {'main': 240.0, 'dds.udp': 30.0, 'rory-io': 2.0}},
    ]
    text = thread_table(runs, 'message')
    assert '| thread | bare | rory |' in text
    assert '| main | 210.0 | 240.0 |' in text
    assert '| dds.udp | 26.0 | 30.0 |' in text
    assert '| rory-io | 0.0 | 2.0 |' in text
    assert 'dds.ev' not in text
    assert text.index('| main') < text.index('| dds.udp') < text.index('| rory-io')


def test_the_node_is_the_one_in_the_supervisors_tree_not_anothers_with_its_command(
        tmp_path: Path) -> None:
    # pid: (parent, command line); 40 is another bench's node, started earlier (a lower pid).
    processes = {1: (0, 'init'), 40: (1, 'python out/scan_sink.py'),
                 100: (1, 'python -m rory_runtime.cli supervise supervise.yaml'),
                 101: (100, 'rory-zygote'), 102: (101, 'python out/scan_sink.py')}
    for pid, (parent, command) in processes.items():
        (tmp_path / str(pid)).mkdir()
        (tmp_path / str(pid) / 'stat').write_text(f'{pid} (python) S {parent} 1 1 0\n')
        (tmp_path / str(pid) / 'cmdline').write_bytes(command.replace(' ', '\0').encode())
    program = PROGRAMS['scan']
    deadline = time.monotonic() + 5
    assert _node_pid(100, 'rory', deadline, program, proc=tmp_path) == 102
    assert _node_pid(100, 'bare', deadline, program, proc=tmp_path) == 100
    (tmp_path / '102' / 'stat').unlink()  # not started yet: the other bench's is not taken
    with pytest.raises(RuntimeError, match='restart: the node never started'):
        _node_pid(100, 'restart', time.monotonic() + 0.3, program, proc=tmp_path)
