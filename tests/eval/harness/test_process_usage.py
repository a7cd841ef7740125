"""Per-role CPU and memory of a process tree (rory_eval/harness/process_usage.py)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from typing import Any

from rory_eval.harness.process_usage import (
    ProcessReading,
    TreeSampler,
    peak_rss_mb,
    read_process,
    role_of,
    thread_kind,
    tree_cpu_ticks,
    tree_pids,
)


def test_thread_kinds_drop_instance_numbers_and_ports() -> None:
    assert [thread_kind(c) for c in ('dds.udp.7411', 'dds.ev.0', 'dds.asyn.0.0',
                                     'dds.shm.wdog', 'python')] == [
        'dds.udp', 'dds.ev', 'dds.asyn', 'dds.shm.wdog', 'python']


def test_roles_come_from_the_command_line() -> None:
    python = sys.executable
    assert role_of([python, '-m', 'rory_runtime.cli', 'supervise', 'x.yaml']) == 'supervisor'
    assert role_of([f'{python} -m rory_runtime.cli supervise x.yaml']) == 'supervisor'
    assert role_of(['rory-standby']) == 'standby'
    assert role_of(['rory-zygote']) == 'zygote'
    assert role_of(['rory-spare']) == 'spare'
    assert role_of([python, 'targets/amcl/amcl_node.py', '--ros-args']) == 'node'
    # A node merely named like a command is still the node.
    assert role_of([python, 'supervise.py']) == 'node'


class _FakeTree:
    """A supervisor (pid 1) with a node (2) from the start and a standby (3) born later."""

    def __init__(self) -> None:
        self.now = 0.0
        self.ticks = {1: 0, 2: 0, 3: 0}
        self.alive = {1, 2}
        self.pss_reads = 0

    def clock(self) -> float:
        return self.now

    def pids(self, root: int) -> list[int]:
        assert root == 1
        return sorted(self.alive)

    def read(self, pid: int, *, with_pss: bool = False) -> ProcessReading | None:
        role = {1: 'supervisor', 2: 'node', 3: 'standby'}[pid]
        self.pss_reads += with_pss
        # The node's DDS thread does a quarter of its work, the rest is Python.
        ticks = self.ticks[pid]
        threads = ((('dds.udp', ticks // 4), ('python', ticks - ticks // 4)) if pid == 2
                   else (('python', ticks),))
        return ProcessReading(pid, role, ticks, 0, 80.0 + pid,
                              40.0 + pid if with_pss else math.nan, threads)

    def advance(self, seconds: float, **ticks: Any) -> None:
        self.now += seconds
        for name, n in ticks.items():
            self.ticks[{'supervisor': 1, 'node': 2, 'standby': 3}[name]] += n


def test_the_sampler_splits_cpu_by_role_and_by_half() -> None:
    tree = _FakeTree()
    tree.ticks = {1: 500, 2: 900, 3: 0}  # start-up before the window does not count
    sampler = TreeSampler(1, clock=tree.clock, read=tree.read, pids=tree.pids)
    sampler.start()
    tree.alive.add(3)
    tree.advance(5.0, supervisor=50, node=100, standby=150)  # the standby's imports
    sampler.sample()
    tree.advance(5.0, supervisor=10, node=100, standby=5)
    sampler.sample()
    tree.advance(10.0, supervisor=20, node=200, standby=10)
    usage = sampler.finish()
    assert usage.wall_seconds == 20.0 and usage.steady_wall_seconds == 10.0
    roles = usage.roles
    assert set(roles) == {'node', 'supervisor', 'standby'}
    assert roles['node'].cpu_seconds == 4.0 and roles['node'].steady_cpu_seconds == 2.0
    assert roles['standby'].cpu_seconds == 1.65 and roles['standby'].steady_cpu_seconds == 0.1
    assert roles['supervisor'].cpu_seconds == 0.8
    assert math.isclose(usage.steady_cpu_percent, 100.0 * (2.0 + 0.2 + 0.1) / 10.0)
    # PSS is read once, at the end, for each process.
    assert tree.pss_reads == 3 and usage.pss_mb == 41.0 + 42.0 + 43.0
    assert roles['node'].steady_threads == {'python': 1.5, 'dds.udp': 0.5}
    assert usage.to_json()['standby'] == {'processes': 1, 'cpu_percent': 8.25,
                                          'steady_cpu_percent': 1.0, 'peak_rss_mb': 83.0,
                                          'pss_mb': 43.0,
                                          'steady_threads_percent': {'python': 1.0}}


def test_a_real_process_tree_is_read() -> None:
    # A parent that waits for its child, and a child named like a standby that burns CPU for 0.6 s.
    busy = ('import time,sys,setproctitle\nsetproctitle.setproctitle("rory-standby")\n'
            'end=time.process_time()+0.6\n'
            'while time.process_time()<end: pass\ntime.sleep(30)')
    parent = subprocess.Popen([sys.executable, '-c',
                               'import subprocess,sys,time\n'
                               f'subprocess.Popen([sys.executable, "-c", {busy!r}]).wait()'])
    try:
        sampler = TreeSampler(parent.pid)
        sampler.start()
        deadline = time.monotonic() + 20.0
        while True:
            time.sleep(0.3)
            sampler.sample()
            child = [p for p in tree_pids(parent.pid) if p != parent.pid]
            reading = read_process(child[0]) if child else None
            if reading is not None and reading.own_ticks >= 0.6 * os.sysconf('SC_CLK_TCK'):
                break
            assert time.monotonic() < deadline, 'the child never burnt its 0.6 s'
        # The whole tree's ticks hold the child's; a gone process has no peak.
        assert tree_cpu_ticks(parent.pid) >= reading.own_ticks
        assert peak_rss_mb(child[0]) > 1.0 and peak_rss_mb(2**22 + 1) == 0.0
        usage = sampler.finish()
        assert set(usage.roles) == {'node', 'standby'}
        assert usage.roles['standby'].cpu_seconds >= 0.55
        assert usage.roles['node'].cpu_seconds < 0.3
        for role in usage.roles.values():
            assert role.processes == 1 and role.peak_rss_mb > 1.0 and role.pss_mb > 0.5
        this = read_process(os.getpid(), with_pss=True)
        assert this is not None and this.pss_mb > 1.0
        assert dict(this.threads).get('python', -1) >= 0
    finally:
        # Killing the child ends the parent, which reaps it.
        for pid in tree_pids(parent.pid)[1:]:
            os.kill(pid, 9)
        try:
            parent.wait(timeout=10)
        finally:
            parent.kill()
            parent.wait()
