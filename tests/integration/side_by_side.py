"""Independent runs of a module's tests started together, each test waiting for its own.

A module fixture makes a :class:`SideBySide` of the runs (each its own domain, folder and
processes); the first test that asks for a run starts them all, at most ``at_once`` at a time,
and every test then asserts on its own run's result. The module's tests go to one xdist
worker (``pytest.mark.xdist_group``), which holds the runs. Every run reaps its processes
however it ends; the fixture waits for all of them at its end.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Generic, TypeVar

T = TypeVar('T')


class SideBySide(Generic[T]):
    """Runs by key, started together on first use."""

    def __init__(self, runs: dict[str, Callable[[int, Path], T]], domains: Callable[[], int],
                 folder: Path, at_once: int | None = None) -> None:
        self._runs, self._domains, self._folder = runs, domains, folder
        self._at_once = at_once or len(runs)
        self._pool: ThreadPoolExecutor | None = None
        self._futures: dict[str, Future[T]] = {}

    def __getitem__(self, key: str) -> T:
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self._at_once)
            # Submitted in order: with fewer threads than runs, the first keys start first.
            self._futures = {k: self._pool.submit(r, self._domains(), self._folder / k)
                             for k, r in self._runs.items()}
        return self._futures[key].result()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)


@contextlib.contextmanager
def side_by_side(runs: dict[str, Callable[[int, Path], T]], domains: Callable[[], int],
                 folder: Path, at_once: int | None = None) -> Iterator[SideBySide[T]]:
    """A :class:`SideBySide` closed (every run waited for) on the way out."""
    together = SideBySide(runs, domains, folder, at_once)
    try:
        yield together
    finally:
        together.close()
