"""The output prefixer (supervisor/output.py) with real pipes, no ROS: whole lines, prefixed,
each on its own stream; partial and overlong lines; a relabelled standby."""

from __future__ import annotations

import io
import os
import time

from rory_runtime.supervisor.output import LONGEST_LINE, OutputPrefixer


class _Sink(io.BytesIO):
    def close(self) -> None:  # keep the value readable after the prefixer is done
        pass


def _wait_for(sink: _Sink, text: bytes) -> None:
    deadline = time.monotonic() + 5
    while text not in sink.getvalue():
        assert time.monotonic() < deadline, sink.getvalue()
        time.sleep(0.005)


def test_lines_are_prefixed_and_kept_on_their_own_stream() -> None:
    out, err = _Sink(), _Sink()
    prefixer = OutputPrefixer(out, err)
    a, b = prefixer.open('a'), prefixer.open('b')
    os.write(a.child_fds[0], b'one\ntw')
    os.write(b.child_fds[1], b'bee\n')
    os.write(a.child_fds[0], b'o\n')
    _wait_for(out, b'[a] two\n')
    _wait_for(err, b'[b] bee\n')
    a.close_child_ends()
    b.close_child_ends()
    prefixer.close()
    assert out.getvalue() == b'[a] one\n[a] two\n'
    assert err.getvalue() == b'[b] bee\n'


def test_a_line_cut_by_the_end_is_written_whole_and_a_long_one_is_not_held() -> None:
    out, err = _Sink(), _Sink()
    prefixer = OutputPrefixer(out, err)
    streams = prefixer.open('n')
    os.write(streams.child_fds[0], b'x' * LONGEST_LINE)
    _wait_for(out, b'[n] ' + b'x' * LONGEST_LINE + b'\n')
    os.write(streams.child_fds[0], b'cut')
    streams.close_child_ends()  # as a killed process's pipe closes
    _wait_for(out, b'[n] cut\n')
    prefixer.close()


def test_a_relabelled_process_carries_its_new_name() -> None:
    out, err = _Sink(), _Sink()
    prefixer = OutputPrefixer(out, err)
    streams = prefixer.open('rory-standby')
    os.write(streams.child_fds[1], b'waiting\n')
    _wait_for(err, b'[rory-standby] waiting\n')
    streams.relabel('amcl')
    os.write(streams.child_fds[1], b'running\n')
    _wait_for(err, b'[amcl] running\n')
    streams.close_child_ends()
    prefixer.close()
    assert out.getvalue() == b''


def test_close_writes_what_a_process_that_still_runs_left_unfinished() -> None:
    out, err = _Sink(), _Sink()
    prefixer = OutputPrefixer(out, err)
    streams = prefixer.open('slow')
    os.write(streams.child_fds[0], b'half')
    time.sleep(0.05)
    prefixer.close(timeout=0.1)  # the write end is still open: the process has not ended
    assert out.getvalue() == b'[slow] half\n'
    streams.close_child_ends()
