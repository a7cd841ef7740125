"""The rest bench's pure parts: its config of distinct nodes, the standby's readiness in the log,
the fixed processes' sum, medians over runs and the table. No process is started."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

from rory_eval.bench.rest_bench import (
    fixed_of,
    other_users,
    shared_libraries,
    standby_ready,
    summarise,
    table,
    thread_ns,
    thread_shares,
    thread_wakeups,
    write_config,
)


def role(cpu: float, pss: float, processes: int = 1) -> dict[str, Any]:
    return {'processes': processes, 'cpu_percent': cpu, 'steady_cpu_percent': cpu,
            'peak_rss_mb': pss + 10, 'pss_mb': pss, 'steady_threads_percent': {}}


def run(sup_cpu: float, sup_pss: float, threads: dict[str, float]) -> dict[str, Any]:
    roles = {'supervisor': role(sup_cpu, sup_pss),
             'zygote': role(0.0, 12.0),
             'standby': role(0.05, 18.0),
             'node': role(3.0, 150.0, processes=6)}
    return {'roles': roles, 'fixed': fixed_of(roles),
            'threads_percent': {'supervisor': threads, 'standby': {'dds.ev': 0.05}},
            'threads_wakeups': {'supervisor': {kind: 10.0 * share / 0.05
                                               for kind, share in threads.items()},
                                'standby': {'dds.ev': 2.0}},
            'main_threads': {'supervisor': 'python', 'standby': 'rory-standby'}}


def test_the_fixed_processes_are_supervisor_zygote_and_standby_not_the_nodes() -> None:
    fixed = run(0.25, 38.0, {})['fixed']
    assert fixed == {'cpu_percent': pytest.approx(0.30), 'pss_mb': pytest.approx(68.0)}


def test_medians_per_role_and_thread_kind_and_of_each_runs_sum() -> None:
    runs = [run(0.20, 38.0, {'python': 0.10, 'dds.ev': 0.10}),
            run(0.40, 40.0, {'python': 0.20, 'rory-ros': 0.20}),
            run(0.30, 39.0, {'python': 0.15, 'dds.ev': 0.05, 'rory-ros': 0.10})]
    summary = summarise(runs)
    assert summary['runs'] == 3
    assert summary['fixed']['cpu_percent'] == {'median': pytest.approx(0.35),
                                               'min': pytest.approx(0.25),
                                               'max': pytest.approx(0.45)}
    assert summary['fixed']['pss_mb']['median'] == pytest.approx(69.0)
    assert summary['roles']['supervisor']['pss_mb']['median'] == 39.0
    assert summary['roles']['node']['processes'] == 6
    # A kind a run did not show counts 0 in that run; largest first.
    assert summary['threads']['supervisor'] == {'python': 0.15, 'rory-ros': 0.10,
                                                'dds.ev': 0.05}
    assert summary['threads']['standby'] == {'dds.ev': 0.05}
    assert summary['wakeups']['supervisor'] == {'python': pytest.approx(30.0),
                                                'rory-ros': pytest.approx(20.0),
                                                'dds.ev': pytest.approx(10.0)}
    assert summary['threads_all']['supervisor'] == {'median': pytest.approx(0.30),
                                                    'min': pytest.approx(0.20),
                                                    'max': pytest.approx(0.40)}
    assert summary['main_threads'] == {'supervisor': 'python', 'standby': 'rory-standby'}


def test_the_table_shows_the_fixed_sum_each_process_the_nodes_and_the_threads() -> None:
    summary = summarise([run(0.20, 38.0, {'python': 0.12, 'dds.ev': 0.08}),
                         run(0.30, 40.0, {'python': 0.18, 'dds.ev': 0.12})])
    text = table(summary)
    assert '| **fixed: supervisor + zygote + standbys + spares** | **0.30** (0.25-0.35) ' \
           '| **69.0** (68.0-70.0) |' in text
    assert '| zygote | 0.00 (0.00-0.00) | 12.0 (12.0-12.0) |' in text
    assert '| the 6 nodes (not in the figure) | 3.00 (3.00-3.00) | 150.0 (150.0-150.0) |' in text
    assert '| thread | supervisor % | runs/s | standby % | runs/s |' in text
    assert "| `python` (the supervisor's main thread) | 0.150 | 30.0 | - | - |" in text
    assert '| `dds.ev` | 0.100 | 20.0 | 0.050 | 2.0 |' in text
    assert '| **all threads** | **0.250** | 50.0 | **0.050** | 2.0 |' in text
    assert 'Not alone' not in text


def test_a_run_beside_other_users_of_its_libraries_is_flagged() -> None:
    runs = [run(0.20, 38.0, {}), {**run(0.30, 30.0, {}), 'other_users': {77: 'python talker'}}]
    summary = summarise(runs)
    assert summary['runs_not_alone'] == 1
    assert 'Not alone in 1 of 2 runs' in table(summary)


def test_no_runs_is_refused() -> None:
    with pytest.raises(ValueError, match='no runs'):
        summarise([])


def test_the_standby_is_ready_when_the_log_says_so_for_its_pid() -> None:
    log = '[rory] integrator_1: standby pid 4242 started\n[rory] standby pid 4242 ready in 310 ms\n'
    assert standby_ready(log, 4242)
    assert not standby_ready(log, 424)
    assert not standby_ready('[rory] standby pid 4242 ended before it was ready (-9)\n', 4242)


def test_each_node_has_its_own_name_and_topics(tmp_path: Path) -> None:
    (tmp_path / 'out').mkdir()  # the instrumented program: prepare does not run the tool again
    config = yaml.safe_load(write_config(tmp_path, 3).read_text())
    names = [node['name'] for node in config['nodes']]
    assert names == ['integrator_1', 'integrator_2', 'integrator_3']
    third = config['nodes'][2]
    assert third['method'] == 'rory'
    assert 'warm_standby' not in third  # the default: on for rory
    assert third['command'][-6:] == ['-r', '__node:=integrator_3', '-r', '/numbers:=/numbers_3',
                                     '-r', '/integrator/state:=/integrator_3/state']
    assert len({' '.join(node['command']) for node in config['nodes']}) == 3


def test_threads_are_read_per_kind_in_nanoseconds_from_schedstat(tmp_path: Path) -> None:
    for tid, comm, ns in ((10, 'python3.11', 5_000_000), (11, 'dds.udp.7411', 1_000),
                          (12, 'dds.udp.7412', 2_000)):
        task = tmp_path / '10' / 'task' / str(tid)
        task.mkdir(parents=True)
        (task / 'comm').write_text(comm + '\n')
        (task / 'schedstat').write_text(f'{ns} 77 {tid - 7}\n')
    assert thread_ns(10, proc=tmp_path) == {10: ('python', 5_000_000, 3),
                                            11: ('dds.udp', 1_000, 4),
                                            12: ('dds.udp', 2_000, 5)}
    assert thread_ns(99, proc=tmp_path) == {}  # gone


def test_thread_shares_count_a_new_thread_from_zero_and_leave_an_ended_one_out() -> None:
    before = {1: ('python', 100_000_000, 500), 2: ('dds.ev', 0, 0),
              3: ('rory-ring', 50_000_000, 70)}
    after = {1: ('python', 130_000_000, 800), 2: ('dds.ev', 6_000_000, 20),
             4: ('dds.ev', 3_000_000, 10)}
    # over 10 s: 30 ms is 0.3 % of a core; the two dds.ev threads 9 ms, 0.09 %
    assert thread_shares(before, after, 10.0) == {'python': pytest.approx(0.3),
                                                  'dds.ev': pytest.approx(0.09)}
    assert list(thread_shares(before, after, 10.0)) == ['python', 'dds.ev']
    assert thread_wakeups(before, after, 10.0) == {'python': 30.0, 'dds.ev': 3.0}


def test_other_users_are_the_processes_outside_ours_that_map_python_or_dds(
        tmp_path: Path) -> None:
    dds = '/venv/site-packages/ros_fastrtps.libs/libfastrtps.so.2.14'
    python = '/pyenv/lib/libpython3.11.so.1.0'
    maps = {1: f'7f00-7f10 r-xp 00000000 08:01 42 {dds}\n'
               f'7f10-7f20 r--p 00000000 08:01 42 {dds}\n'
               f'7e00-7e10 r-xp 00000000 08:01 41 {python}\n',
            2: f'7f00-7f10 r-xp 00000000 08:01 42 {dds}\n',
            3: '7f00-7f10 r-xp 00000000 08:01 43 /usr/lib/libc.so.6\n',
            4: f'7e00-7e10 r-xp 00000000 08:01 41 {python}\n'}
    for pid, text in maps.items():
        (tmp_path / str(pid)).mkdir()
        (tmp_path / str(pid) / 'maps').write_text(text)
        (tmp_path / str(pid) / 'cmdline').write_bytes(b'python\0talker.py\0')
    (tmp_path / 'self').mkdir()
    assert shared_libraries(1, proc=tmp_path) == [dds, python]
    assert shared_libraries(3, proc=tmp_path) == []
    assert shared_libraries(9, proc=tmp_path) == []  # gone
    assert other_users([dds, python], {1}, proc=tmp_path) == {2: 'python talker.py',
                                                               4: 'python talker.py'}
    assert other_users([dds], {1, 2}, proc=tmp_path) == {}
    assert other_users([], {1}, proc=tmp_path) == {}
