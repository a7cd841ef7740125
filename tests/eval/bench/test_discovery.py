"""rory_eval/bench/discovery.py and dds_fleet_bench.py, end to end with stand-ins for their
processes, /dev/shm and /proc/locks: no process is started.

After each setting both benches clear the shared-memory files their SIGKILLed participants left
behind. They used to remove every ``/dev/shm/fastrtps_*`` on the machine, the live segments and
ports of every other ROS program running beside them (a fault campaign's nodes) included; now
only the files their own processes held, once nobody holds them."""

from __future__ import annotations

import fcntl
import itertools
import os
import signal
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from rory_eval.bench import dds_fleet_bench, discovery

FIRST_PID = 4_000_000  # above any real pid here: nothing is ever sent to one of these


def lock_line(number: int, pid: int, lock: Path) -> str:
    stat = lock.stat()
    return (f'{number}: FLOCK  ADVISORY  WRITE {pid} '
            f'{os.major(stat.st_dev):02x}:{os.minor(stat.st_dev):02x}:{stat.st_ino} 0 EOF')


class Machine:
    """/dev/shm and /proc/locks as a folder and a file, and the processes the benches start:
    each makes a segment and a port with their lock files and holds the locks until killed,
    when (as after a SIGKILL) its files stay."""

    def __init__(self, tmp_path: Path) -> None:
        self.shm = tmp_path / 'shm'
        self.shm.mkdir()
        self.locks = tmp_path / 'locks'
        self.held: dict[int, list[Path]] = {}
        self.pids = itertools.count(FIRST_PID)
        self.ports = itertools.count(7000)
        self.started: list[FakeProcess] = []
        self.write_locks()

    def make(self, name: str) -> Path:
        (self.shm / name).write_bytes(b'\0' * 64)
        lock = self.shm / f'{name}_el'
        lock.touch()
        return lock

    def write_locks(self) -> None:
        lines = [lock_line(i, pid, lock) for i, (pid, lock) in enumerate(
            ((pid, lock) for pid, locks in self.held.items() for lock in locks), start=1)]
        # Locks on other files, of these processes and of others: not in /dev/shm.
        lines.append(f'{len(lines) + 1}: FLOCK  ADVISORY  WRITE {FIRST_PID} fe:00:2738533 0 EOF')
        lines.append(f'{len(lines) + 1}: POSIX  ADVISORY  WRITE 77 fe:00:12 0 EOF')
        self.locks.write_text('\n'.join(lines) + '\n')

    def popen(self, argv: list[str], **_: Any) -> FakeProcess:
        process = FakeProcess(self, next(self.pids), argv[-1] == discovery.LISTENER)
        self.held[process.pid] = [self.make(f'fastrtps_{process.pid:016x}'),
                                  self.make(f'fastrtps_port{next(self.ports)}')]
        self.write_locks()
        self.started.append(process)
        return process

    def died(self, pid: int) -> None:
        self.held.pop(pid, None)
        self.write_locks()

    def ours(self) -> list[str]:
        return sorted(p.name for p in self.shm.iterdir()
                      if p.name.startswith(('fastrtps_0000000', 'fastrtps_port7')))


class FakeProcess:
    def __init__(self, machine: Machine, pid: int, listener: bool) -> None:
        self.machine, self.pid, self.returncode = machine, pid, None
        self.stdout = SimpleNamespace(readline=self.readline) if listener else None
        self.lines = 0

    def readline(self) -> str:
        # 'ready', then each child's publish and its receipt (ns): heard 2 ms later.
        self.lines += 1
        sent = self.lines * 10**9
        return 'ready\n' if self.lines == 1 else f'{sent} {sent + 2_000_000}\n'

    def poll(self) -> int | None:
        return self.returncode

    def kill(self) -> None:
        self.returncode = -9
        self.machine.died(self.pid)

    def wait(self, timeout: float | None = None) -> int | None:
        return self.returncode


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def sleep(self, seconds: float) -> None:
        self.now += seconds

    def monotonic(self) -> float:
        return self.now


@pytest.fixture
def machine(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Machine]:
    machine = Machine(tmp_path)
    monkeypatch.setattr(discovery, 'SHM', machine.shm)
    monkeypatch.setattr(discovery, 'LOCKS', machine.locks)
    fake = SimpleNamespace(Popen=machine.popen, PIPE=-1)
    clock = Clock()
    for module in (discovery, dds_fleet_bench):
        monkeypatch.setattr(module, 'subprocess', fake)
        monkeypatch.setattr(module, 'time', clock)
    killpg = os.killpg

    def fake_killpg(pid: int, signum: int) -> None:
        if pid < FIRST_PID:
            killpg(pid, signum)
            return
        assert signum == signal.SIGKILL
        next(p for p in machine.started if p.pid == pid).kill()

    monkeypatch.setattr(os, 'killpg', fake_killpg)
    monkeypatch.setattr(dds_fleet_bench, 'exit_on_sigterm', lambda: None)
    yield machine
    assert all(p.returncode is not None for p in machine.started)  # every one was killed


@pytest.fixture
def others(machine: Machine) -> Iterator[list[Path]]:
    """Another program's live participant (its lock held, as by a process that runs) and a
    dead one's leftovers."""
    live = machine.make('fastrtps_a1a1a1a1a1a1a1a1')
    port = machine.make('fastrtps_port47411')
    dead = machine.make('fastrtps_deaddeaddeaddead')
    (machine.shm / 'sem.fastrtps_port47411_mutex').touch()
    machine.held[31337] = [live, port]
    machine.write_locks()
    fds = [os.open(lock, os.O_RDONLY) for lock in (live, port)]
    for fd in fds:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    files = sorted(machine.shm.iterdir())
    yield files
    for fd in fds:
        os.close(fd)
    assert dead.exists()


def test_only_files_its_processes_held_and_nobody_holds_now_are_removed(
        machine: Machine, others: list[Path]) -> None:
    dead, held_again = (machine.popen(['python', '-c', discovery.IDLE]) for _ in range(2))
    files = discovery.shm_files_of({dead.pid, held_again.pid})
    assert sorted(f.name for f in files) == machine.ours() and len(files) == 8
    assert {f.name for f in discovery.shm_files_of({31337})} == {
        'fastrtps_a1a1a1a1a1a1a1a1', 'fastrtps_a1a1a1a1a1a1a1a1_el', 'fastrtps_port47411',
        'fastrtps_port47411_el'}
    dead.kill()
    held_again.kill()
    # A new participant took the port the second one had, and holds it.
    fd = os.open(machine.shm / 'fastrtps_port7001_el', os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        removed = discovery.remove_left_over(files)
    finally:
        os.close(fd)
    assert machine.ours() == ['fastrtps_port7001', 'fastrtps_port7001_el']
    assert len(removed) == 6 and not any(p.exists() for p in removed)
    assert sorted(machine.shm.iterdir()) == sorted(
        [*others, machine.shm / 'fastrtps_port7001', machine.shm / 'fastrtps_port7001_el'])


def test_discovery_runs_every_setting_and_leaves_only_other_programs_files(
        machine: Machine, others: list[Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert discovery.main(['--runs', '2', '--peers', '1', '--domain', '160']) == 0
    table = capsys.readouterr().out.splitlines()
    assert len(table) == 5 and table[0].startswith('DDS setting')
    assert all(line.split()[-2:] == ['2.0', '2.0'] for line in table[1:])
    # listener, peer and two children per setting
    assert len(machine.started) == 4 * 4
    assert machine.ours() == []
    assert sorted(machine.shm.iterdir()) == others


def test_dds_fleet_runs_every_setting_and_leaves_only_other_programs_files(
        machine: Machine, others: list[Path], tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(dds_fleet_bench, 'cpu_seconds',
                        lambda pid: dds_fleet_bench.time.monotonic() / 1000.0)
    assert dds_fleet_bench.main(['--participants', '2', '--settle', '1', '--seconds', '1',
                                 '--restarts', '1', '--leases', '3:1', '--domain', '160',
                                 '--out', str(tmp_path / 'out')]) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith('| ')]
    assert [line.split(' | ')[0] for line in table[1:]] == [
        '| Fast DDS defaults', "| RORY's profile", "| RORY's node profile",
        '| lease 3 s, announced every 1 s']
    assert all(line.endswith('| 0.100 | 0.20 | 2 | 2 |') for line in table[1:])
    # at rest two participants; after a crash a listener, four peers and one child
    assert len(machine.started) == 4 * (2 + 6)
    assert machine.ours() == []
    assert sorted(machine.shm.iterdir()) == others
    assert (tmp_path / 'out' / 'dds_fleet.json').exists()
