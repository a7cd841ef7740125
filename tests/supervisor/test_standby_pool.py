"""The pool of warm standbys (supervisor/standby.py), driven by a fake zygote whose forks are
real processes that wait (no rclpy): how many are kept, which is handed out, when the pool is
filled again, and that none is leaked.

What a standby does once activated, with real rclpy, is tests/supervisor/test_standby_launcher.py.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, cast

import pytest

from rory_runtime.supervisor.process import Child
from rory_runtime.supervisor.standby import REFILL_DELAY, ForkLauncher, PidChild
from rory_runtime.supervisor.zygote import ForkedStandby, Zygote

ARGV_A = [sys.executable, 'a.py']
ARGV_B = [sys.executable, 'b.py']
FOUR = [[sys.executable, f'{name}.py'] for name in 'abcd']


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


class FakeZygote:
    """Forks are `sleep` processes, children of this test; a standby is ready when told."""

    def __init__(self) -> None:
        self.env = {k: v for k, v in os.environ.items()
                    if k.startswith(('PYTHON', 'LD_', 'OPENBLAS_', 'OMP_', 'MKL_'))}
        self.procs: list[subprocess.Popen[bytes]] = []
        self.ready_ends: dict[int, int] = {}  # standby pid -> write end of its ready pipe
        self.controls: dict[int, int] = {}  # standby pid -> read end of its control pipe
        self.nodes: list[int] = []  # cold forks: a round trip on the supervisor's main loop
        self.spares: list[int] = []

    def _start(self) -> int:
        proc = subprocess.Popen(['sleep', '60'])
        self.procs.append(proc)
        return proc.pid

    def fork_standby(self, init_args: Sequence[str], env: Mapping[str, str], cwd: Path,
                     output: Sequence[int] = (), *, spare: bool = False) -> ForkedStandby:
        pid = self._start()
        if spare:
            self.spares.append(pid)
        control_r, control_w = os.pipe()
        ready_r, ready_w = os.pipe()
        self.ready_ends[pid] = ready_w
        self.controls[pid] = control_r
        return ForkedStandby(pid, control_w, ready_r)

    def ready(self, pid: int) -> None:
        os.write(self.ready_ends.pop(pid), b'1')

    def activation(self, pid: int) -> bytes:
        return os.read(self.controls[pid], 65536)

    def fork_node(self, argv: Sequence[str], env: Mapping[str, str], cwd: Path,
                  output: Sequence[int] = ()) -> int:
        pid = self._start()
        self.nodes.append(pid)
        return pid

    def close(self) -> None:
        for proc in self.procs:
            if proc.returncode is None:
                proc.kill()
        for fd in [*self.ready_ends.values(), *self.controls.values()]:
            os.close(fd)
        self.ready_ends.clear()
        self.controls.clear()

    def alive(self) -> list[int]:
        return [p.pid for p in self.procs if Path(f'/proc/{p.pid}').exists()
                and 'Z' not in Path(f'/proc/{p.pid}/stat').read_text().split()[2]]


@pytest.fixture
def zygote() -> Iterator[FakeZygote]:
    fake = FakeZygote()
    try:
        yield fake
    finally:
        fake.close()
        for proc in fake.procs:
            # reaped by the launcher (PidChild) or here: never left behind
            with contextlib.suppress(ChildProcessError):
                os.waitpid(proc.pid, 0)
            proc.returncode = 0  # so Popen does not warn about a process it did not wait for


def _launcher(zygote: FakeZygote, clock: FakeClock, size: int) -> ForkLauncher:
    return ForkLauncher(cast(Zygote, zygote), clock=clock, pool_size=size)


def _env() -> dict[str, str]:
    return dict(os.environ)


def _wait_ready(launcher: ForkLauncher, pids: list[int]) -> None:
    deadline = time.monotonic() + 5.0
    while not all(s.ready_at is not None for s in launcher.standbys(ARGV_A, Path('/'))
                  if s.pid in pids):
        assert time.monotonic() < deadline
        time.sleep(0.005)


def test_prepare_fills_the_pool_once(zygote: FakeZygote) -> None:
    launcher = _launcher(zygote, FakeClock(), 3)
    started = launcher.prepare(ARGV_A, _env(), Path('/'))
    assert started is not None and len(started) == 3 and len(set(started)) == 3
    assert launcher.prepare(ARGV_A, _env(), Path('/')) == []  # full: nothing more
    assert sorted(s.pid for s in launcher.standbys(ARGV_A, Path('/'))) == sorted(started)
    launcher.close()
    assert zygote.alive() == []


def test_three_nodes_struck_together_each_take_a_standby_the_fourth_starts_cold(
    zygote: FakeZygote
) -> None:
    clock = FakeClock()
    launcher = _launcher(zygote, clock, 3)
    pool = launcher.prepare(ARGV_A, _env(), Path('/'))
    assert pool is not None
    launcher.prepare(ARGV_B, _env(), Path('/'))  # B shares A's init: the same pool
    children = [cast(PidChild, launcher.spawn(argv, _env(), Path('/'), label=str(i)))
                for i, argv in enumerate([ARGV_A, ARGV_B, ARGV_A, ARGV_B])]
    assert [c.warm for c in children] == [True, True, True, False]
    assert sorted(c.pid for c in children[:3]) == sorted(pool)
    assert 'the pool of 3 is in use' in children[3].why_cold
    assert children[3].pid in zygote.nodes
    # each warm one got its own node's activation line
    assert all(b'a.py' in zygote.activation(children[i].pid) for i in (0, 2))
    assert b'b.py' in zygote.activation(children[1].pid)
    launcher.close()
    for child in children:
        child.send_signal(9)
        child.wait(timeout=5)
    assert zygote.alive() == []


def test_the_ready_one_is_handed_out_first(zygote: FakeZygote) -> None:
    clock = FakeClock()
    launcher = _launcher(zygote, clock, 2)
    first, second = cast(list[int], launcher.prepare(ARGV_A, _env(), Path('/')))
    zygote.ready(second)
    _wait_ready(launcher, [second])
    assert cast(Any, launcher.standby(ARGV_A, Path('/'))).pid == second
    assert launcher.spawn(ARGV_A, _env(), Path('/')).pid == second
    assert launcher.spawn(ARGV_A, _env(), Path('/')).pid == first  # starting beats cold
    launcher.close()


def test_the_pool_is_filled_again_only_after_the_refill_delay(zygote: FakeZygote) -> None:
    # Standbys forked while nodes recover would compete with them for the CPU.
    clock = FakeClock()
    launcher = _launcher(zygote, clock, 2)
    launcher.prepare(ARGV_A, _env(), Path('/'))
    launcher.spawn(ARGV_A, _env(), Path('/'))
    clock.now += REFILL_DELAY / 2
    assert launcher.prepare(ARGV_A, _env(), Path('/')) == []
    assert len(launcher.standbys(ARGV_A, Path('/'))) == 1
    clock.now += REFILL_DELAY / 2
    started = launcher.prepare(ARGV_A, _env(), Path('/'))
    assert started is not None and len(started) == 1
    assert len(launcher.standbys(ARGV_A, Path('/'))) == 2
    launcher.close()


def test_a_dead_standby_is_replaced_and_reaped(zygote: FakeZygote) -> None:
    clock = FakeClock()
    launcher = _launcher(zygote, clock, 2)
    first, second = cast(list[int], launcher.prepare(ARGV_A, _env(), Path('/')))
    os.kill(first, 9)
    standby = next(s for s in launcher.standbys(ARGV_A, Path('/')) if s.pid == first)
    standby.child.wait(timeout=5)
    clock.now += 0.1
    assert launcher.prepare(ARGV_A, _env(), Path('/')) == []  # seen dead: refill waits
    assert [s.pid for s in launcher.standbys(ARGV_A, Path('/'))] == [second]
    clock.now += REFILL_DELAY
    started = launcher.prepare(ARGV_A, _env(), Path('/'))
    assert started is not None and len(started) == 1
    assert not Path(f'/proc/{first}').exists()  # reaped, no zombie
    launcher.close()


def test_twenty_storms_leave_no_process_behind(zygote: FakeZygote) -> None:
    # Every standby taken or dropped is reaped or becomes a node; the pool never grows.
    clock = FakeClock()
    launcher = _launcher(zygote, clock, 3)
    nodes: list[PidChild] = []
    for _ in range(20):
        launcher.prepare(ARGV_A, _env(), Path('/'))
        assert len(launcher.standbys(ARGV_A, Path('/'))) == 3
        struck = [cast(PidChild, launcher.spawn(ARGV_A, _env(), Path('/'))) for _ in range(4)]
        for old in nodes:
            old.send_signal(9)
            old.wait(timeout=5)
        nodes = struck
        clock.now += REFILL_DELAY
    launcher.prepare(ARGV_A, _env(), Path('/'))
    assert len(zygote.alive()) == 3 + 4  # the pool, full again, and the last storm's nodes
    launcher.discard(ARGV_A, Path('/'))
    assert launcher.standbys(ARGV_A, Path('/')) == []
    for node in nodes:
        node.send_signal(9)
        node.wait(timeout=5)
    assert zygote.alive() == []
    launcher.close()


def test_discard_keeps_the_pool_while_another_command_wants_it(zygote: FakeZygote) -> None:
    launcher = _launcher(zygote, FakeClock(), 2)
    launcher.prepare(ARGV_A, _env(), Path('/'))
    launcher.prepare(ARGV_B, _env(), Path('/'))
    launcher.discard(ARGV_A, Path('/'))
    assert len(launcher.standbys(ARGV_B, Path('/'))) == 2
    launcher.discard(ARGV_B, Path('/'))
    assert launcher.standbys(ARGV_B, Path('/')) == []
    assert zygote.alive() == []
    launcher.close()


def _prepare_all(launcher: ForkLauncher, commands: Sequence[Sequence[str]]) -> None:
    for argv in commands:
        launcher.prepare(argv, _env(), Path('/'))


def test_each_command_beyond_the_pool_has_a_spare_fork(zygote: FakeZygote) -> None:
    launcher = _launcher(zygote, FakeClock(), 2)
    _prepare_all(launcher, FOUR)
    assert len(launcher.standbys(FOUR[0], Path('/'))) == 2
    assert sorted(s.pid for s in launcher.spares(FOUR[0], Path('/'))) == sorted(zygote.spares)
    assert len(zygote.spares) == 2
    assert all(not s.child.warm for s in launcher.spares(FOUR[3], Path('/')))
    assert launcher.full(FOUR[1], Path('/'))
    _prepare_all(launcher, FOUR)  # full: nothing more
    assert len(zygote.procs) == 4
    launcher.close()
    assert zygote.alive() == []


def test_no_spare_while_the_pool_covers_every_command(zygote: FakeZygote) -> None:
    launcher = _launcher(zygote, FakeClock(), 3)
    _prepare_all(launcher, FOUR[:3])
    assert launcher.spares(FOUR[0], Path('/')) == [] and zygote.spares == []
    launcher.close()


def test_four_struck_together_two_warm_two_from_spares_none_forked_on_the_loop(
    zygote: FakeZygote
) -> None:
    launcher = _launcher(zygote, FakeClock(), 2)
    _prepare_all(launcher, FOUR)
    children = [cast(PidChild, launcher.spawn(argv, _env(), Path('/'), label=str(i)))
                for i, argv in enumerate(FOUR)]
    assert [c.warm for c in children] == [True, True, False, False]
    assert sorted(c.pid for c in children[2:]) == sorted(zygote.spares)
    assert zygote.nodes == []  # no round trip to the zygote while the crashes are taken
    assert all('from a spare fork' in c.why_cold for c in children[2:])
    assert all('the pool of 2 is in use' in c.why_cold for c in children[2:])
    # each got its own node's activation line
    for child, argv in zip(children, FOUR, strict=True):
        assert argv[1].encode() in zygote.activation(child.pid)
    fifth = cast(PidChild, launcher.spawn(FOUR[0], _env(), Path('/')))
    assert not fifth.warm and fifth.pid in zygote.nodes  # none left: a cold fork
    launcher.close()
    for child in [*children, fifth]:
        child.send_signal(9)
        child.wait(timeout=5)
    assert zygote.alive() == []


def test_spares_are_refilled_after_the_refill_delay(zygote: FakeZygote) -> None:
    clock = FakeClock()
    launcher = _launcher(zygote, clock, 2)
    _prepare_all(launcher, FOUR)
    taken = [launcher.spawn(argv, _env(), Path('/')) for argv in FOUR]
    assert not launcher.full(FOUR[0], Path('/'))
    clock.now += REFILL_DELAY / 2
    _prepare_all(launcher, FOUR)
    assert launcher.spares(FOUR[0], Path('/')) == []
    clock.now += REFILL_DELAY / 2
    _prepare_all(launcher, FOUR)
    assert len(launcher.spares(FOUR[0], Path('/'))) == 2
    assert len(launcher.standbys(FOUR[0], Path('/'))) == 2
    launcher.close()
    for child in taken:
        child.send_signal(9)
        child.wait(timeout=5)
    assert zygote.alive() == []


def test_a_dead_spare_is_replaced_and_reaped(zygote: FakeZygote) -> None:
    clock = FakeClock()
    launcher = _launcher(zygote, clock, 2)
    _prepare_all(launcher, FOUR)
    dead = launcher.spares(FOUR[0], Path('/'))[0]
    os.kill(dead.pid, 9)
    dead.child.wait(timeout=5)
    assert not launcher.full(FOUR[0], Path('/'))
    clock.now += REFILL_DELAY
    _prepare_all(launcher, FOUR[:1])  # seen dead: the refill waits
    clock.now += REFILL_DELAY
    _prepare_all(launcher, FOUR[:1])
    assert len(launcher.spares(FOUR[0], Path('/'))) == 2
    assert dead.pid not in [s.pid for s in launcher.spares(FOUR[0], Path('/'))]
    assert not Path(f'/proc/{dead.pid}').exists()  # reaped, no zombie
    launcher.close()
    assert zygote.alive() == []


def test_a_command_that_goes_takes_its_spare_with_it(zygote: FakeZygote) -> None:
    launcher = _launcher(zygote, FakeClock(), 2)
    _prepare_all(launcher, FOUR)
    launcher.discard(FOUR[3], Path('/'))
    assert len(launcher.spares(FOUR[0], Path('/'))) == 1
    assert len(zygote.alive()) == 3
    for argv in FOUR[:3]:
        launcher.discard(argv, Path('/'))
    assert zygote.alive() == []
    launcher.close()


def test_twenty_storms_with_spares_leave_no_process_behind(zygote: FakeZygote) -> None:
    clock = FakeClock()
    launcher = _launcher(zygote, clock, 2)
    nodes: list[Child] = []
    for _ in range(20):
        _prepare_all(launcher, FOUR)
        assert launcher.full(FOUR[0], Path('/'))
        struck = [launcher.spawn(argv, _env(), Path('/')) for argv in FOUR]
        for old in nodes:
            old.send_signal(9)
            old.wait(timeout=5)
        nodes = struck
        clock.now += REFILL_DELAY
    assert zygote.nodes == []
    _prepare_all(launcher, FOUR)
    assert len(zygote.alive()) == 4 + 4  # pool and spares, full again, and the last storm's
    for argv in FOUR:
        launcher.discard(argv, Path('/'))
    for node in nodes:
        node.send_signal(9)
        node.wait(timeout=5)
    assert zygote.alive() == []
    launcher.close()


def test_without_spare_forks_a_node_beyond_the_pool_is_forked_cold(zygote: FakeZygote) -> None:
    launcher = ForkLauncher(cast(Zygote, zygote), clock=FakeClock(), pool_size=2, spares=False)
    _prepare_all(launcher, FOUR)
    assert launcher.spares(FOUR[0], Path('/')) == [] and launcher.full(FOUR[0], Path('/'))
    children = [cast(PidChild, launcher.spawn(argv, _env(), Path('/'))) for argv in FOUR]
    assert [c.warm for c in children] == [True, True, False, False]
    assert sorted(c.pid for c in children[2:]) == sorted(zygote.nodes)
    launcher.close()
    for child in children:
        child.send_signal(9)
        child.wait(timeout=5)
    assert zygote.alive() == []
