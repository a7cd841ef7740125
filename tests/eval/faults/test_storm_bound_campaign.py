"""The storm-bound campaign's checks (rory_eval/faults/storm_bound_campaign.py): its verdict on
made-up readings, and its reading of /proc on this test's own child processes. No ROS."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rory_eval.faults.storm_bound_campaign import (
    Campaign,
    Reading,
    fd_kind,
    judge,
    kinds_change,
    least,
    memory_by_mapping,
    read_once,
    still_there,
    table,
)


def _reading(storm: int, **changes: object) -> Reading:
    """Three nodes, a pool of three, the zygote; figures as a quiet run shows them."""
    base = Reading(storm=storm, pss_mb=80.0, rss_mb=120.0, fds=60, threads=30, nodes=3,
                   standbys=3, zygotes=1, others=0, zombies=0, zygote_rss_mb=70.0,
                   zygote_fds=8, recovered_ms=150.0, warm=3,
                   fd_kinds={'pipe': 20, 'socket': 30, 'anon_inode:[eventpoll]': 10})
    return dataclasses.replace(base, **changes)  # type: ignore[arg-type]


def _storms(n: int = 20, **changes_at: dict[str, object]) -> list[Reading]:
    """A reading before the storms and one after each; ``changes_at['7']``: storm 7's."""
    return [_reading(k, **changes_at.get(str(k), {})) for k in range(n + 1)]


def test_constant_figures_with_a_little_memory_noise_are_bounded() -> None:
    readings = _storms(**{str(k): {'pss_mb': 80.0 + 0.1 * (k % 3)} for k in range(21)})
    verdict = judge(readings, nodes=3, pool=3)
    assert verdict.bounded, verdict.failures
    assert 'PSS: 80.0 MB at storm 3, 80.2 at storm 20 (+0.2), highest 80.2 at storm 5' \
        in verdict.notes


def test_growth_during_the_warm_up_is_not_held_against_it() -> None:
    readings = _storms(**{'0': {'fds': 50, 'pss_mb': 70.0}, '1': {'fds': 55, 'pss_mb': 76.0},
                          '2': {'fds': 58, 'threads': 29}})
    assert judge(readings, nodes=3, pool=3).bounded


def test_a_descriptor_more_after_the_warm_up_is_a_leak_and_its_kind_is_named() -> None:
    readings = _storms(**{str(k): {'fds': 60 + 2 * (k - 10),
                                   'fd_kinds': {'pipe': 20 + 2 * (k - 10), 'socket': 30,
                                                'anon_inode:[eventpoll]': 10}}
                          for k in range(11, 21)})
    verdict = judge(readings, nodes=3, pool=3)
    assert not verdict.bounded
    assert verdict.failures[0].startswith('descriptors grew: 60 at storm 3, 62 at storm 11, ')
    assert verdict.failures[0].endswith('80 at storm 20')
    assert 'descriptors, storm 3 -> 20: pipe +20' in verdict.notes


def test_memory_is_allowed_its_tolerance_and_no_more() -> None:
    within = _storms(**{'20': {'pss_mb': 82.0, 'rss_mb': 121.9, 'zygote_rss_mb': 71.5}})
    assert judge(within, nodes=3, pool=3).bounded
    beyond = _storms(**{'20': {'pss_mb': 82.1}})
    verdict = judge(beyond, nodes=3, pool=3)
    assert verdict.failures == ['PSS grew +2.1 MB: 80.0 MB at storm 3, 82.1 at storm 20 '
                                '(tolerance +2 MB)']
    assert not judge(_storms(**{'9': {'zygote_rss_mb': 75.0}}), nodes=3, pool=3).bounded


def test_a_thread_or_process_more_is_not_tolerated() -> None:
    assert not judge(_storms(**{'12': {'threads': 31}}), nodes=3, pool=3).bounded
    assert not judge(_storms(**{'12': {'zygote_fds': 9}}), nodes=3, pool=3).bounded


def test_the_tree_must_be_the_nodes_the_pool_and_the_zygote_at_every_reading() -> None:
    leaked_standby = judge(_storms(**{'15': {'standbys': 4}}), nodes=3, pool=3)
    assert 'storm 15: 3 nodes, 4 standbys, 1 zygotes, 0 others (expected 3 nodes, 3 standbys, ' \
        '1 zygote, nothing else)' in leaked_standby.failures
    assert any(f.startswith('processes grew: 7 at storm 3, 8 at storm 15')
               for f in leaked_standby.failures)
    # Before the storms and in the warm-up too: the tree is checked, not only its growth.
    assert not judge(_storms(**{'0': {'standbys': 2}}), nodes=3, pool=3).bounded
    assert not judge(_storms(**{'1': {'others': 1}}), nodes=3, pool=3).bounded
    zombie = judge(_storms(**{'2': {'zombies': 1}}), nodes=3, pool=3)
    assert zombie.failures == ['storm 2: 1 zombies in the tree']
    assert judge(_storms(), nodes=2, pool=2).failures[0].startswith('storm 0: 3 nodes')


def test_a_campaign_cut_short_is_not_bounded() -> None:
    verdict = judge(_storms(2), nodes=3, pool=3)
    assert verdict.failures == ['2 storms: none after the warm-up of 2']


def test_least_keeps_what_lasts() -> None:
    passing = _reading(4, fds=62, threads=31, pss_mb=80.5, fd_kinds={'pipe': 22})
    assert least([passing, _reading(4), passing]) == _reading(4)
    assert least([passing, _reading(4)]).fd_kinds == _reading(4).fd_kinds


def test_descriptor_kinds_lose_their_inode() -> None:
    assert fd_kind('pipe:[123456]') == 'pipe'
    assert fd_kind('socket:[99]') == 'socket'
    assert fd_kind('anon_inode:[eventfd]') == 'anon_inode:[eventfd]'
    assert fd_kind('/dev/shm/fastrtps_port7411') == '/dev/shm/fastrtps_port7411'
    assert kinds_change({'pipe': 4, 'socket': 2}, {'pipe': 6, 'socket': 1, '/x': 1}) == \
        '/x +1, pipe +2, socket -1'
    assert kinds_change({'pipe': 4}, {'pipe': 4}) == 'none'


def test_the_table_has_a_row_per_reading() -> None:
    rows = table(_storms(3)).splitlines()
    assert len(rows) == 2 + 4
    assert rows[2].startswith('| before | - | - | 80.0 | 120.0 | 60 | 30 | 7 (3 + 3 + 1 + 0) | 0 |')
    assert rows[3].startswith('| 1 | 150 | 3/3 | ')
    idle = table([_reading(5, publishing=False)]).splitlines()[2]
    assert idle.startswith('| 5 (idle) |')


def _stat(pid: int) -> list[str]:
    """/proc/PID/stat's fields after the command name (state first)."""
    return Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()


def test_a_real_tree_read_from_proc() -> None:
    sleeper = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(30)'])
    done = subprocess.Popen([sys.executable, '-c', 'pass'])
    try:
        deadline = time.monotonic() + 10
        while _stat(done.pid)[0] != 'Z':
            assert time.monotonic() < deadline
            time.sleep(0.01)
        as_node = read_once(os.getpid(), 1, node_pids={sleeper.pid})
        # This process's descriptors, give or take the one each listing opens.
        assert abs(as_node.fds - len(os.listdir('/proc/self/fd'))) <= 1
        assert as_node.pss_mb > 0 and as_node.rss_mb >= as_node.pss_mb
        assert as_node.threads >= 1
        roles = {m.pid: m.role for m in as_node.members}
        assert roles[sleeper.pid] == 'node' and roles[done.pid] == 'zombie'
        assert as_node.zombies >= 1
        unknown = read_once(os.getpid(), 1, node_pids=set())
        assert {m.pid: m.role for m in unknown.members}[sleeper.pid] == 'other'
        started = {sleeper.pid: int(_stat(sleeper.pid)[19])}
        while _stat(sleeper.pid)[0] != 'S':  # under load it may still be starting ('R')
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert still_there(started) == {sleeper.pid: 'S'}
        sleeper.kill()
        sleeper.wait()
        assert still_there(started) == {}
    finally:
        for proc in (sleeper, done):
            proc.kill()
            proc.wait()


def test_a_zombie_when_the_supervisor_exits_is_noted_a_live_process_fails() -> None:
    ended = Campaign(nodes=3, pool=3, count=10, exact={'n0': True, 'n1': True, 'n2': True},
                     stop_code=0, left_at_exit={41: 'Z'})
    assert ended.end_failures() == []
    ended.left_at_exit = {41: 'Z', 42: 'S'}
    ended.left_later = {42: 'S'}
    assert ended.end_failures() == [
        "processes alive when the supervisor had exited: {42: 'S'}",
        "processes left 2 s after the supervisor exited: {42: 'S'}"]
    inexact = Campaign(nodes=2, pool=2, count=10, exact={'n0': True, 'n1': False})
    assert inexact.end_failures() == ['n1 did not apply 1..10 exactly once, in order']


def test_memory_by_mapping_adds_up_to_the_process() -> None:
    mappings = memory_by_mapping(os.getpid())
    assert mappings['[anon]']['maps'] >= 1
    assert any('libpython' in name or 'python' in Path(name).name for name in mappings)
    total = sum(m['rss'] for m in mappings.values())
    assert total == pytest.approx(read_once(os.getpid(), 0).rss_mb, rel=0.1)
