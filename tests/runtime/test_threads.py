"""RORY's threads carry their names in /proc (rory_runtime/threads.py)."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import pytest

from rory_runtime.threads import name_this_thread


@pytest.mark.skipif(not sys.platform.startswith('linux'), reason='/proc thread names')
def test_a_thread_names_itself_for_the_os() -> None:
    seen: list[str] = []

    def run() -> None:
        name_this_thread('rory-io-and-more-than-15-bytes')
        seen.append(Path(f'/proc/self/task/{threading.get_native_id()}/comm').read_text())

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    assert seen == ['rory-io-and-mor\n']  # the kernel keeps 15 bytes
    # The caller's own name is untouched.
    assert Path(f'/proc/self/task/{threading.get_native_id()}/comm').read_text() != seen[0]
