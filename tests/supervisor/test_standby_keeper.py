"""A node's side of the warm standbys (supervisor/standby_keeper.py), over the fake supervisor:
when it asks the launcher's pool, and that a full pool costs no ``prepare``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fake_supervisor import FakeLauncher, Harness

from rory_runtime.supervisor.standby_keeper import STANDBY_DELAY


class _Child:
    def __init__(self, code: int | None = None) -> None:
        self.code = code

    def poll(self) -> int | None:
        return self.code


class _Standby:
    def __init__(self, code: int | None = None) -> None:
        self.child = _Child(code)


class PoolLauncher(FakeLauncher):
    """A launcher with a pool (``standby.ForkLauncher``): ``full`` says whether ``prepare``
    would start anything."""

    def __init__(self, pool_size: int) -> None:
        super().__init__()
        self.pool_size = pool_size
        self.waiting: list[_Standby] = []

    def full(self, argv: Any, cwd: Path) -> bool:
        return (len(self.waiting) >= self.pool_size
                and all(s.child.poll() is None for s in self.waiting))


def _running(tmp_path: Path, launcher: FakeLauncher) -> Harness:
    h = Harness(tmp_path, warm_standby=True)
    h.sup.launcher = launcher
    h.node.start()
    h.up()
    h.tick(STANDBY_DELAY)
    return h


def test_a_full_pool_of_live_standbys_is_not_asked_again(tmp_path: Path) -> None:
    launcher = PoolLauncher(pool_size=2)
    h = _running(tmp_path, launcher)
    assert len(launcher.prepared) == 1  # the first time always asks (and says if it cannot)
    launcher.waiting = [_Standby(), _Standby()]
    h.tick(STANDBY_DELAY)
    assert len(launcher.prepared) == 1


def test_a_short_pool_or_a_dead_standby_asks_the_launcher(tmp_path: Path) -> None:
    launcher = PoolLauncher(pool_size=2)
    h = _running(tmp_path, launcher)
    launcher.waiting = [_Standby()]
    h.tick(STANDBY_DELAY)
    assert len(launcher.prepared) == 2
    launcher.waiting = [_Standby(), _Standby(code=-9)]  # prepare replaces the dead one
    h.tick(STANDBY_DELAY)
    assert len(launcher.prepared) == 3


def test_a_launcher_without_a_pool_is_asked_every_time(tmp_path: Path) -> None:
    launcher = FakeLauncher()
    h = _running(tmp_path, launcher)
    h.tick(STANDBY_DELAY)
    assert len(launcher.prepared) == 2
    assert h.node.standby.status() == 'none'
