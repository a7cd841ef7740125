"""The instructions bench's arithmetic, on captured callgrind_annotate output (no valgrind run):
self costs read per function, recursion levels and inlined files added into one, the idle
threads (OpenBLAS's, Fast DDS's flow controller) left out, start-up cancelled by the difference
of two runs."""
# ruff: noqa: E501 (lines of annotate output as it prints them)

from __future__ import annotations

import pytest

from rory_eval.bench.instructions_bench import (
    Profile,
    calls_to,
    combined,
    idle_thread,
    main,
    parse_annotate,
    per_message,
    report,
    top_added,
)

# Cut from `callgrind_annotate --inclusive=no --threshold=100 --auto=no` of the main thread of
# a bare scan_sink run (2026-11-28), counts scaled down so the lines add up to the total.
ANNOTATE = """\
--------------------------------------------------------------------------------
Profile data file '/tmp/ib/bare-50/callgrind.20213.out' (creator: callgrind-3.19.0)
--------------------------------------------------------------------------------
I1 cache:
Timerange: Basic block 0 - 233262316
Trigger: Program termination
Profiled target:  /work/main/.venv/bin/python -c ... 50 (PID 20213, part 1)
Events recorded:  Ir
Thresholds:       100
Auto-annotation:  off

--------------------------------------------------------------------------------
Ir
--------------------------------------------------------------------------------
1,000,000 (100.0%)  PROGRAM TOTALS

--------------------------------------------------------------------------------
Ir                    file:function
--------------------------------------------------------------------------------
500,000 (50.00%)  tmp/python-build.1/Python-3.11.7/Python/ceval.c:_PyEval_EvalFrameDefault'2 [/root/.pyenv/versions/3.11.7/lib/libpython3.11.so.1.0]
200,000 (20.00%)  ???:eprosima::fastdds::rtps::FlowControllerImpl<eprosima::fastdds::rtps::FlowControllerSyncPublishMode, eprosima::fastdds::rtps::FlowControllerFifoSchedule>::add_new_sample(eprosima::fastrtps::rtps::RTPSWriter*) [/work/main/.venv/lib/libfastrtps.so.2.14]
150,000 (15.00%)  tmp/python-build.1/Python-3.11.7/Python/ceval.c:_PyEval_EvalFrameDefault [/root/.pyenv/versions/3.11.7/lib/libpython3.11.so.1.0]
 80,000 ( 8.00%)  tmp/python-build.1/Python-3.11.7/Objects/tupleobject.c:tupledealloc [/root/.pyenv/versions/3.11.7/lib/libpython3.11.so.1.0]
 40,000 ( 4.00%)  ???:std::basic_string<char>::basic_string(char const*) [clone .isra.0] [/work/main/.venv/lib/libfastrtps.so.2.14]
 29,999 ( 3.00%)  tmp/python-build.1/Python-3.11.7/./Include/object.h:tupledealloc
      1 ( 0.00%)  ???:blas_shutdown [/work/main/.venv/lib/python3.11/site-packages/numpy.libs/libscipy_openblas64_-32a4b2a6.so]
"""


def test_annotate_output_is_read_per_function() -> None:
    profile = parse_annotate(ANNOTATE)
    assert profile.total == 1_000_000
    assert profile.functions == {
        '_PyEval_EvalFrameDefault': 650_000,  # two recursion levels
        'eprosima::fastdds::rtps::FlowControllerImpl<eprosima::fastdds::rtps::'
        'FlowControllerSyncPublishMode, eprosima::fastdds::rtps::FlowControllerFifoSchedule>::'
        'add_new_sample(eprosima::fastrtps::rtps::RTPSWriter*)': 200_000,
        'tupledealloc': 109_999,  # two files: one inlined
        'std::basic_string<char>::basic_string(char const*) [clone .isra.0]': 40_000,
        'blas_shutdown': 1,
    }
    assert sum(profile.functions.values()) == profile.total
    assert profile.where['_PyEval_EvalFrameDefault'] == 'ceval.c'
    assert profile.where['tupledealloc'] == 'tupleobject.c'  # (its largest line's)
    assert profile.where['blas_shutdown'] == 'libscipy_openblas64_-32a4b2a6.so'


def test_text_without_totals_is_refused() -> None:
    with pytest.raises(ValueError, match='PROGRAM TOTALS'):
        parse_annotate('valgrind: no such file\n')


# Cut from two threads of a bare run of 5 scans (--separate-threads=yes, files -04 and -12).
BLAS_THREAD = """\
--------------------------------------------------------------------------------
13,500,520 (100.0%)  PROGRAM TOTALS

--------------------------------------------------------------------------------
Ir                   file:function
--------------------------------------------------------------------------------
13,499,909 (100.0%)  ???:blas_thread_server [/work/main/.venv/lib/python3.11/site-packages/numpy.libs/libscipy_openblas64_-32a4b2a6.so]
       108 ( 0.00%)  ./nptl/./nptl/pthread_cond_wait.c:pthread_cond_wait@@GLIBC_2.3.2 [/usr/lib/x86_64-linux-gnu/libc.so.6]
       403 ( 0.00%)  ./nptl/./nptl/pthread_create.c:start_thread [/usr/lib/x86_64-linux-gnu/libc.so.6]
"""
FLOW_CONTROLLER_THREAD = """\
849,695 (100.0%)  PROGRAM TOTALS
722,138 (84.99%)  ???:std::_Rb_tree<eprosima::fastrtps::rtps::GUID_t, std::pair<eprosima::fastrtps::rtps::GUID_t const, eprosima::fastrtps::rtps::RTPSWriter*> >::find(eprosima::fastrtps::rtps::GUID_t const&) [/work/main/.venv/lib/libfastrtps.so.2.14]
127,557 (15.01%)  ???:eprosima::fastdds::rtps::FlowControllerImpl<eprosima::fastdds::rtps::FlowControllerSyncPublishMode, eprosima::fastdds::rtps::FlowControllerFifoSchedule>::run() [/work/main/.venv/lib/libfastrtps.so.2.14]
"""


def test_the_idle_threads_are_told_apart() -> None:
    assert idle_thread(parse_annotate(BLAS_THREAD))
    assert idle_thread(parse_annotate(FLOW_CONTROLLER_THREAD))
    # The main thread calls OpenBLAS's and the flow controller's functions too: not idle.
    assert not idle_thread(parse_annotate(ANNOTATE))
    threads = [parse_annotate(t) for t in (ANNOTATE, BLAS_THREAD, FLOW_CONTROLLER_THREAD)]
    kept = combined(t for t in threads if not idle_thread(t))
    assert kept.total == 1_000_000


# Cut from a callgrind output file of a main thread (250 scans): rcl_wait named at its first
# use and by its id after; a call of another function in between.
CALLGRIND_OUT = """\
fn=(54078)
0 6000
cfn=(54134) rcl_wait
calls=300 0
0 3000
fn=(54134)
0 6000
cfn=(53850)
calls=500 0
0 19000
fn=(5856) rclpy::WaitSet::wait(rclpy::Context&, long)
cob=(105)
cfi=(693)
cfn=(54134)
calls=200 0
0 5857431
cfn=(54135) rcl_wait_set_clear
calls=7 0
0 10
"""


def test_the_executors_waits_are_counted() -> None:
    assert calls_to(CALLGRIND_OUT, 'rcl_wait') == 500
    assert calls_to(CALLGRIND_OUT, 'rcl_wait_set_clear') == 7
    assert calls_to('', 'rcl_wait') == 0


def test_per_message_cancels_start_up_and_adds_a_runs_processes() -> None:
    start_up = {'import': 900.0, 'ldconfig': 50.0}
    small = combined([Profile(1_000 + 5 * 100, {**start_up, 'take': 5 * 100.0}, {}),
                      Profile(50, {}, {})])
    large = Profile(1_050 + 25 * 100, {**start_up, 'take': 25 * 100.0}, {'take': 'x.c'},
                    waits=2.0 * 25)  # (the small run's waits: none)
    assert small.total == 1_550
    result = per_message(small, large, 5, 25)
    assert result.total == 100
    assert result.waits == 2.5
    assert result.functions == {'import': 0, 'ldconfig': 0, 'take': 100}
    with pytest.raises(ValueError):
        per_message(large, small, 25, 25)


def test_the_table_shows_what_is_added_and_where() -> None:
    bare = Profile(1_000_000, {'take': 900_000, 'wait': 100_000}, {'take': 'a.c'}, 2.0)
    restart = Profile(1_040_000, {'take': 900_000, 'wait': 105_000, 'route': 35_000},
                      {'route': 'routing.py'}, 2.0)
    assert top_added(restart, bare, top=2) == [('route', 35_000), ('wait', 5_000)]
    text = report({'bare': bare, 'restart': restart}, (50, 250), 10)
    assert '| bare | 1,000,000 | - | - | 2.00 |' in text
    assert '| restart | 1,040,000 | +40,000 | +4.0 % | 2.00 |' in text
    assert '| `route` (routing.py) | +35,000 |' in text


def test_bad_options_are_refused(capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (['--configs', 'replay'], ['--counts', '250,50'], ['--counts', '50']):
        with pytest.raises(SystemExit):
            main(argv)
    assert 'bare, restart, checkpoint, rory' in capsys.readouterr().err


def test_without_valgrind_one_line_and_exit_2(monkeypatch: pytest.MonkeyPatch,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr('shutil.which', lambda _tool: None)
    assert main(['--configs', 'bare']) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'valgrind' in err
