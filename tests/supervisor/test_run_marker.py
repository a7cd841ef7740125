"""The store's owner and whether its previous run stopped cleanly."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from rory_runtime.supervisor.run_marker import (
    MARKER_NAME,
    RunMarker,
    StoreInUseError,
    make_room_for_previous,
)


def test_first_run_then_unclean_then_clean(tmp_path: Path) -> None:
    store = tmp_path / 'store'
    first = RunMarker(store)
    assert first.acquire() is None
    assert stat.S_IMODE(store.stat().st_mode) == 0o700
    assert stat.S_IMODE((store / MARKER_NAME).stat().st_mode) == 0o600
    first.release()  # as if killed: never marked clean
    second = RunMarker(store)
    previous = second.acquire()
    assert previous is not None and previous.clean is False and previous.pid == os.getpid()
    second.mark_clean()
    second.release()
    third = RunMarker(store)
    previous = third.acquire()
    assert previous is not None and previous.clean is True and previous.stopped is not None
    third.release()


def test_a_live_owner_keeps_the_store(tmp_path: Path) -> None:
    owner = RunMarker(tmp_path)
    owner.acquire()
    expected = rf'in use by another supervisor \(pid {os.getpid()}\)'
    with pytest.raises(StoreInUseError, match=expected):
        RunMarker(tmp_path).acquire()
    owner.release()
    RunMarker(tmp_path).acquire()


@pytest.mark.parametrize('text', ['', '{', '[]', '{"pid": "x"}', '\xff'])
def test_an_unreadable_marker_means_unclean(tmp_path: Path, text: str) -> None:
    (tmp_path / MARKER_NAME).write_text(text, errors='surrogateescape')
    previous = RunMarker(tmp_path).acquire()
    assert previous is not None and previous.clean is False


def _run(folder: Path, name: str) -> None:
    folder.mkdir(parents=True)
    (folder / 'events.jsonl').write_text(name)


def _names(store: Path) -> dict[str, str]:
    return {p.name: (p / 'events.jsonl').read_text()
            for p in sorted(store.glob('.previous*'))}


def test_earlier_runs_move_one_older_and_the_oldest_beyond_keep_goes(tmp_path: Path) -> None:
    store = tmp_path / 'store'
    store.mkdir()
    assert make_room_for_previous(store, 3) == []  # nothing set aside yet
    for run in ('run1', 'run2', 'run3', 'run4'):
        make_room_for_previous(store, 3)
        _run(store / '.previous', run)  # what the fresh start then sets aside there
    assert _names(store) == {'.previous': 'run4', '.previous.1': 'run3', '.previous.2': 'run2'}
    kept = make_room_for_previous(store, 3)
    assert kept == [store / '.previous.1', store / '.previous.2']
    assert _names(store) == {'.previous.1': 'run4', '.previous.2': 'run3'}


def test_keeping_one_run_keeps_only_the_newest(tmp_path: Path) -> None:
    store = tmp_path / 'store'
    _run(store / '.previous', 'run1')
    _run(store / '.previous.1', 'from a larger keep_runs')
    assert make_room_for_previous(store, 1) == []
    assert _names(store) == {}
