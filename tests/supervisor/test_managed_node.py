"""The supervisor's per-node decisions with fakes for every port (fake_supervisor.py): no ROS
process, no DDS, a clock that moves when told. Crashes in each state (starting, arming,
running, restoring, replaying, gated, during the handover), hangs and the early capture of a
late node's inputs, backoff and its reset, giving up, a second crash during a recovery, a
supervisor restarted on its store, the release gate, a refused stale checkpoint, a clean exit
and a stop during a recovery; on each path the safe state is held once per recovery and
released once, or kept held when nothing will bring the node back (``safety.log`` records
every call)."""

from __future__ import annotations

import logging
import signal
from pathlib import Path

import pytest
from fake_supervisor import INPUT, Harness

from rory_runtime import protocol
from rory_runtime.freshness import Verdict
from rory_runtime.log import LogEntry
from rory_runtime.protocol import OpenedStatus, RestoredCheckpoint, SwitchedStatus
from rory_runtime.supervisor.ports import Capture
from rory_runtime.supervisor.recovery import RecoveryLog
from rory_runtime.supervisor.standby_keeper import STANDBY_DELAY
from rory_runtime.supervisor.states import NodeState
from rory_runtime.supervisor.watchdog import HANG_DUMP_GRACE, HELLO_TIMEOUT, STALL_SUSPECT

S = NodeState
HELD = [('hold', 'n')]
ONCE = [('hold', 'n'), ('release', 'n')]


def _started(tmp_path: Path, **node: object) -> Harness:
    h = Harness(tmp_path, **node)
    h.node.start()
    h.beat()
    h.up()
    assert h.state() == S.RUNNING
    return h


def test_a_fresh_start_runs_once_the_process_says_released(tmp_path: Path) -> None:
    h = Harness(tmp_path)
    h.node.start()
    assert h.state() == S.STARTING and len(h.sup.launcher.children) == 1
    assert h.child.env[protocol.ENV_MODE] == 'fresh' and h.child.env[protocol.ENV_NODE] == 'n'
    h.hello()
    assert h.state() == S.STARTING  # restart releases itself: RELEASED comes next
    h.released()
    assert h.states() == ['STARTING', 'RUNNING']
    assert not h.sup.safety.log  # a fresh start holds nothing


def test_a_crash_while_running_holds_the_safe_state_until_the_new_process_is_released(
    tmp_path: Path
) -> None:
    h = _started(tmp_path)
    h.exit(-signal.SIGKILL)
    assert h.states()[-2:] == ['CRASHED', 'RESTORING']
    assert h.sup.safety.holders == {'n'}
    assert len(h.sup.launcher.children) == 2 and h.child.env[protocol.ENV_MODE] == 'recover'
    assert h.child.env[protocol.ENV_INCARNATION] == '2'
    h.up()
    assert h.state() == S.RUNNING and h.sup.safety.log == [('hold', 'n'), ('release', 'n')]
    (recovered,) = h.sup.events_log.of('recovered')
    assert recovered['crashes'] == 1 and recovered['incarnation'] == 2


def test_a_clean_exit_is_the_node_finishing_not_a_crash(tmp_path: Path) -> None:
    h = _started(tmp_path)
    h.exit(0)
    assert h.state() == S.EXITED and len(h.sup.launcher.children) == 1
    assert not h.sup.safety.log


def test_a_crash_during_the_first_start_is_recovered_like_any_other(tmp_path: Path) -> None:
    h = Harness(tmp_path)
    h.node.start()
    h.exit(1)
    assert h.states() == ['STARTING', 'CRASHED', 'RESTORING'] and h.sup.safety.holders == {'n'}
    h.up()
    assert h.state() == S.RUNNING and h.sup.safety.log == ONCE


@pytest.mark.parametrize('before', ['hello', 'nothing'])
def test_a_second_crash_before_the_release_is_the_same_recovery_after_a_backoff(
    tmp_path: Path, before: str
) -> None:
    h = _started(tmp_path)
    h.exit(-signal.SIGSEGV)
    if before == 'hello':
        h.hello()
    h.exit(1)
    assert h.states()[-3:] == ['RESTORING', 'CRASHED', 'BACKOFF']
    assert h.sup.safety.holders == {'n'}  # held throughout: one episode
    h.tick(0.4)
    assert h.state() == S.BACKOFF and len(h.sup.launcher.children) == 2
    h.tick(0.2)  # the second consecutive crash waits backoff.step (0.5 s)
    assert h.state() == S.RESTORING and len(h.sup.launcher.children) == 3
    h.up()
    (recovered,) = h.sup.events_log.of('recovered')
    assert recovered['crashes'] == 2 and h.sup.safety.log == [('hold', 'n'), ('release', 'n')]


def test_a_crash_loop_backs_off_doubling_then_gives_up_holding_the_safe_state(
    tmp_path: Path
) -> None:
    h = _started(tmp_path, backoff={'max_restarts': 3, 'step': 0.5, 'maximum': 8})
    delays = []
    for _ in range(3):
        h.exit(1)
        if h.state() == S.BACKOFF:
            assert h.node.restart_at is not None
            delays.append(h.node.restart_at - h.clock())
            h.tick(10.0)
        assert h.state() == S.RESTORING
    assert delays == [0.5, 1.0]  # the first restart at once, then 0.5 s doubling
    h.exit(1)
    assert h.state() == S.FATAL and '3 restarts in a row failed' in h.states()[-1] + (
        h.sup.events_log.of('fatal')[0]['reason'])
    assert h.sup.safety.log == HELD  # nothing will release it
    assert len(h.sup.launcher.children) == 4
    h.node.stop()
    assert h.state() == S.STOPPED and h.sup.safety.log == HELD


def test_a_start_that_ran_stable_after_resets_the_crash_count(tmp_path: Path) -> None:
    h = _started(tmp_path, backoff={'max_restarts': 2, 'stable_after': 10})
    for _ in range(5):  # each crash after a long stable run: never a loop
        h.tick(11.0)
        h.beat()
        h.exit(1)
        assert h.state() == S.RESTORING  # restarted at once, no backoff
        h.beat()
        h.up()
    assert not h.sup.events_log.of('fatal') and h.node.policy.consecutive == 1


def test_a_hung_node_prints_its_stacks_then_is_killed_and_recovered(tmp_path: Path) -> None:
    h = _started(tmp_path, hang_timeout=5.0)
    h.tick(4.0)
    assert h.child.signals == []
    h.tick(1.5)  # 5.5 s without a beat
    assert h.child.signals == [signal.SIGUSR1]
    (hang,) = h.sup.events_log.of('hang')
    assert hang['waiting_for'] == 'heartbeat' and hang['stalled_s'] == pytest.approx(5.5)
    h.tick(HANG_DUMP_GRACE)
    assert h.child.signals == [signal.SIGUSR1, signal.SIGKILL]
    h.reap()
    assert h.states()[-2:] == ['CRASHED', 'RESTORING']
    assert 'hung (no heartbeat for 5.5 s)' in h.sup.events_log.of('state')[-2]['reason']


def test_a_beating_node_is_not_hung_however_long_it_runs(tmp_path: Path) -> None:
    h = _started(tmp_path, hang_timeout=5.0)
    for _ in range(20):
        h.tick(1.0)
        h.beat()
    assert h.child.signals == [] and h.state() == S.RUNNING


def test_a_process_that_never_beats_is_killed_at_its_start_timeout(tmp_path: Path) -> None:
    h = Harness(tmp_path, start_timeout=30.0)
    h.node.start()
    h.tick(29.0)
    assert h.child.signals == []
    h.tick(2.0)
    assert h.child.signals == [signal.SIGKILL]  # no stack to print: it never got going
    h.reap()
    assert h.sup.events_log.of('hang')[0]['waiting_for'] == 'start'


def test_a_process_beating_but_never_heard_is_replaced(tmp_path: Path) -> None:
    h = Harness(tmp_path)
    h.node.start()
    h.beat()
    h.tick(0.1)
    for _ in range(int(HELLO_TIMEOUT) + 2):
        h.beat()
        h.tick(1.0)
    assert signal.SIGKILL in h.child.signals


def test_a_supervisor_restarted_on_its_store_resumes_the_node_as_a_recovery(
    tmp_path: Path
) -> None:
    h = Harness(tmp_path, method='checkpoint')
    h.node.start_resumed(down_since=None)
    assert h.states() == ['RESTORING'] and h.sup.safety.holders == {'n'}
    assert h.child.env[protocol.ENV_MODE] == 'recover'
    assert h.sup.events_log.of('resumed')[0]['unrecorded_s'] is None
    h.up()
    assert h.state() == S.RUNNING and h.sup.safety.log == ONCE


GATE = {'release_gate': {'timeout': 30.0, 'on_timeout': 'give_up'}}


def test_a_gated_node_waits_for_the_call_then_opens_and_releases_the_safe_state(
    tmp_path: Path
) -> None:
    h = _started(tmp_path, **GATE)
    assert h.call_release() == (False, 'n: RUNNING, no recovery waits for release')
    h.exit(-signal.SIGKILL)
    assert h.child.env[protocol.ENV_GATED] == '1'
    h.up()
    assert h.state() == S.GATED and h.sup.safety.holders == {'n'}
    assert not h.sup.events_log.of('recovered')
    h.tick(10.0)
    assert h.state() == S.GATED and h.envelopes() == []
    assert h.call_release() == (True, 'n: released')
    assert h.envelopes() == [protocol.Open(2)]
    h.tick(0.06)  # no OPENED yet: OPEN again (SYNC_PERIOD later)
    assert h.envelopes() == [protocol.Open(2)] * 2
    h.status(OpenedStatus(muted=7))
    assert h.state() == S.RUNNING and h.sup.safety.log == ONCE
    (recovered,) = h.sup.events_log.of('recovered')
    assert recovered['gate_ms'] == pytest.approx(10060.0) and 'called' in recovered['gate']
    assert h.sup.events_log.of('gate_opened')[0]['muted'] == 7


def test_a_call_during_the_recovery_opens_the_gate_as_soon_as_it_is_reached(
    tmp_path: Path
) -> None:
    h = _started(tmp_path, **GATE)
    h.exit(-signal.SIGKILL)
    assert h.call_release() == (True, 'n: restoring; released as soon as it has caught up')
    h.up()
    assert h.state() == S.GATED and h.envelopes() == [protocol.Open(2)]
    h.status(OpenedStatus(muted=0))
    assert h.state() == S.RUNNING


def test_a_gate_nobody_calls_gives_up_at_its_timeout_holding_the_safe_state(
    tmp_path: Path
) -> None:
    h = _started(tmp_path, **GATE)
    h.exit(-signal.SIGKILL)
    h.up()
    gated = h.child
    for _ in range(29):  # live while it waits: beating
        h.tick(1.0)
        h.beat()
        assert h.state() == S.GATED
    h.tick(1.5)
    assert h.state() == S.FATAL and gated.signals == [signal.SIGKILL]
    assert 'within 30 s; on_timeout: give_up' in h.sup.events_log.of('fatal')[0]['reason']
    assert h.sup.safety.log == HELD
    h.sup.events.get(timeout=5.0)  # its exit, reaped: ignored, it was ended on purpose
    assert len(h.sup.launcher.children) == 2


def test_a_crash_at_the_gate_is_a_crash_of_the_same_recovery(tmp_path: Path) -> None:
    h = _started(tmp_path, **GATE)
    h.exit(-signal.SIGKILL)
    h.up()
    h.exit(-signal.SIGKILL)
    assert h.states()[-3:] == ['GATED', 'CRASHED', 'BACKOFF']
    h.tick(1.0)
    h.up()
    assert h.state() == S.GATED and h.sup.safety.log == HELD
    h.call_release()
    h.status(OpenedStatus(muted=0))
    assert h.state() == S.RUNNING and h.sup.safety.log == ONCE
    assert h.sup.events_log.of('recovered')[0]['crashes'] == 2


def test_a_stale_variable_under_refuse_stops_the_node_with_the_safe_state_held(
    tmp_path: Path
) -> None:
    h = _started(tmp_path, method='checkpoint')
    h.exit(-signal.SIGKILL)
    verdict = Verdict(age_s=42.0, clock='system', refused=['pose'], max_age={'pose': 5.0})
    h.hello(restored=RestoredCheckpoint(seq=3, cut=None, created_ns=1, parameters=(),
                                        lifecycle=None, freshness=verdict))
    assert h.state() == S.FATAL and h.child.signals == [signal.SIGKILL]
    reason = h.sup.events_log.of('fatal')[0]['reason']
    assert reason.startswith('checkpoint too old for pose (age 42.0 s on the system clock')
    assert h.sup.safety.log == HELD and h.node.health(h.clock()).fatal_reason == reason


# -- methods that log: the ring, R and the replay -------------------------------------------


def _logging(tmp_path: Path, **node: object) -> Harness:
    """A ``rory`` node started and armed: its ring reads its input, passive."""
    h = _started(tmp_path, method='rory', **node)
    assert h.states() == ['STARTING', 'ARMING', 'RUNNING']
    (ring,) = h.sup.rings
    assert set(ring.topics) == {INPUT.topic} and ring.activations == 0
    return h


def test_a_rory_node_arms_then_recovers_with_the_ring_taking_its_inputs_into_r(
    tmp_path: Path
) -> None:
    h = _logging(tmp_path)
    (ring,) = h.sup.rings
    h.exit(-signal.SIGKILL)
    assert h.states()[-2:] == ['CRASHED', 'RESTORING']
    assert ring.activations == 1 and isinstance(ring.sinks[0], RecoveryLog)  # S2
    h.hello()
    assert h.state() == S.REPLAYING
    assert h.envelopes()[-1] == protocol.Sync(2, h.node.current.sync_nonce)
    h.synced()
    h.replayed()  # nothing logged after the cut, R empty: RELEASE at once
    assert isinstance(h.envelopes()[-1], protocol.Release) and ring.sinks[0].sealed
    h.clock.advance(0.25)
    h.released()
    assert h.state() == S.RUNNING and h.sup.safety.log == ONCE
    (recovered,) = h.sup.events_log.of('recovered')
    assert recovered['total_ms'] == pytest.approx(250.0) and recovered['replay'] == 'fast'


def test_a_crash_while_arming_is_recovered_like_any_other(tmp_path: Path) -> None:
    h = Harness(tmp_path, method='rory')
    h.node.start()
    h.hello()
    assert h.state() == S.ARMING
    h.exit(1)
    assert h.states()[-3:] == ['ARMING', 'CRASHED', 'RESTORING']
    assert h.sup.rings[0].activations == 1 and h.sup.safety.log == HELD
    h.up()
    assert h.state() == S.RUNNING and h.sup.safety.log == ONCE


def test_a_crash_before_the_first_hello_starts_r_when_the_ring_is_made(tmp_path: Path) -> None:
    h = Harness(tmp_path, method='rory')
    h.node.start()
    h.exit(1)
    assert h.sup.rings == [] and h.node.recovery is not None and h.node.recovery.rlog is None
    h.hello()  # the ring is made and joins the recovery: S2 now
    (ring,) = h.sup.rings
    assert ring.activations == 1 and h.node.recovery.ring is ring
    h.synced()
    h.replayed()
    h.released()
    assert h.state() == S.RUNNING and h.sup.safety.log == ONCE


@pytest.mark.parametrize('when', ['before_synced', 'after_release_sent'])
def test_a_crash_while_replaying_is_the_same_recovery(tmp_path: Path, when: str) -> None:
    h = _logging(tmp_path)
    (ring,) = h.sup.rings
    h.exit(-signal.SIGKILL)
    h.hello()
    if when == 'after_release_sent':
        h.synced()
        h.replayed()  # R sealed: what comes next is relayed, and the process may have had it
    h.tick(0.1)
    h.exit(-signal.SIGSEGV)
    assert h.states()[-3:] == ['REPLAYING', 'CRASHED', 'BACKOFF'] and h.sup.safety.log == HELD
    # An open R keeps recording; a sealed one is followed by a new R from the ring's backlog.
    assert ring.activations == (2 if when == 'after_release_sent' else 1)
    h.tick(0.5)
    h.up()
    assert h.state() == S.RUNNING and h.sup.safety.log == ONCE
    (recovered,) = h.sup.events_log.of('recovered')
    assert recovered['crashes'] == 2
    assert recovered['total_ms'] == pytest.approx(600.0)  # from the first crash


def test_the_handover_ends_the_recovery_without_releasing_the_safe_state_again(
    tmp_path: Path
) -> None:
    h = _logging(tmp_path)
    (ring,) = h.sup.rings
    h.exit(-signal.SIGKILL)
    h.up()
    assert h.node.recovery is not None and ring.active_topics == {INPUT.topic}  # relaying
    h.status(SwitchedStatus(topic=INPUT.topic, passed_by_relay=()))
    assert h.node.recovery is None and ring.active_topics == set()
    assert h.sup.safety.log == ONCE and h.state() == S.RUNNING


def _relayed(seq: int) -> LogEntry:
    """Message ``seq`` of the node's input, as the ring takes it after the release."""
    return LogEntry(INPUT.topic, INPUT.msgtype, seq, seq, seq, b'\x00\x01\x00\x00')


def test_a_gap_in_the_relay_is_reported_at_the_switch_without_what_the_node_had_live(
    tmp_path: Path
) -> None:
    # After a link outage longer than the lease the ring got 1, 2, then 10; the node's live
    # reader was matched again first and got 7 on, and applied 7-9 before the relayed 10.
    h = _logging(tmp_path)
    h.exit(-signal.SIGKILL)
    h.up()
    rec = h.node.recovery
    assert rec is not None and rec.rlog is not None and rec.rlog.sealed
    for seq in (1, 2, 10):
        rec.rlog.add(_relayed(seq))
    h.tick(1.0)  # held back: only the switch says what the node had live
    assert h.sup.events_log.of('input_gap') == []
    h.status(SwitchedStatus(topic=INPUT.topic, passed_by_relay=(), live_only=(7, 8, 9)))
    assert h.node.recovery is None
    (gap,) = h.sup.events_log.of('input_gap')
    assert (gap['topic'], gap['first'], gap['last'], gap['missing']) == (INPUT.topic, 3, 6, 4)
    assert h.sup.events_log.of('switched')[0]['live_only'] == [7, 8, 9]


def test_a_crash_during_the_handover_is_a_recovery_of_its_own(tmp_path: Path) -> None:
    h = _logging(tmp_path)
    (ring,) = h.sup.rings
    h.exit(-signal.SIGKILL)
    h.up()
    first = h.node.recovery
    h.exit(-signal.SIGKILL)  # released, still relaying
    assert first is not None and first.streamer is None and first.rlog is not None
    assert first.rlog.sealed
    assert h.node.recovery is not first and ring.activations == 2
    h.tick(1.0)  # ran for 0 s: the second crash in a row waits the backoff
    h.up()
    assert [r['crashes'] for r in h.sup.events_log.of('recovered')] == [1, 1]
    assert h.sup.safety.log == ONCE + ONCE


def test_a_supervisor_restarted_on_its_store_joins_the_ring_at_hello(tmp_path: Path) -> None:
    h = Harness(tmp_path, method='rory')
    h.node.start_resumed(down_since=None)
    assert h.sup.rings == [] and h.sup.safety.log == HELD
    h.hello()
    assert h.sup.rings[0].activations == 1 and h.state() == S.REPLAYING
    h.synced()
    h.replayed()
    h.released()
    assert h.state() == S.RUNNING and h.sup.safety.log == ONCE


def test_a_late_heartbeat_keeps_the_inputs_and_a_hang_hands_them_to_r(tmp_path: Path) -> None:
    h = _logging(tmp_path, hang_timeout=5.0)
    (ring,) = h.sup.rings
    h.tick(STALL_SUSPECT)
    assert ring.activations == 1 and isinstance(ring.sinks[0], Capture)  # S2 early
    h.beat()
    h.tick(0.1)  # only slow: the capture is dropped
    assert h.node.inputs.early.capture is None and ring.active_topics == set()
    h.tick(STALL_SUSPECT)
    capture = h.node.inputs.early.capture
    assert capture is not None and ring.activations == 2
    # What the ring takes meanwhile (the node had not logged it).
    taken = LogEntry(INPUT.topic, INPUT.msgtype, 5, 5, 7, b'\x00\x01\x00\x00\x01\x00\x00\x00\x00')
    capture.add(taken)
    h.tick(5.0)
    assert h.child.signals == [signal.SIGUSR1]
    h.tick(HANG_DUMP_GRACE)
    h.reap()
    assert h.node.inputs.early.capture is None and ring.activations == 3
    rlog = ring.sinks[2]
    assert isinstance(rlog, RecoveryLog) and ring.handed_over[2] == [taken]
    assert rlog.entries == [taken] and h.sup.safety.log == HELD


def test_a_starved_node_beating_late_is_never_taken_for_crashed(tmp_path: Path) -> None:
    # CPU starvation: for a minute, every beat comes just inside the hang timeout. Each time
    # the ring keeps the inputs from 0.6 s on and drops them when the beat comes: the node
    # applies only what its own reader gives it. No signal, no safe state, no recovery.
    h = _logging(tmp_path, hang_timeout=5.0)
    (ring,) = h.sup.rings
    for _ in range(12):
        h.tick(STALL_SUSPECT)
        assert h.node.inputs.early.capture is not None
        h.tick(5.0 - STALL_SUSPECT - 0.01)  # 4.99 s without a beat
        h.beat()
        h.tick(0.0)
        assert h.node.inputs.early.capture is None and ring.active_topics == set()
    assert h.child.signals == [] and h.sup.safety.log == []
    assert h.state() == S.RUNNING and h.node.recovery is None
    assert not any(h.sup.events_log.of(kind) for kind in ('hang', 'exit', 'recovered'))
    # The hang timeout itself passing is a hang: stacks dumped, then killed, then recovered.
    h.tick(5.01)
    assert h.child.signals == [signal.SIGUSR1]


def test_a_clean_exit_during_a_recovery_releases_the_safe_state_once(tmp_path: Path) -> None:
    h = _started(tmp_path)
    h.exit(-signal.SIGKILL)
    h.hello()
    h.exit(0)
    assert h.state() == S.EXITED and h.node.recovery is None
    assert h.sup.safety.log == ONCE and not h.sup.events_log.of('recovered')


def test_stopping_during_a_recovery_keeps_the_safe_state_held(tmp_path: Path) -> None:
    h = _logging(tmp_path)
    h.exit(-signal.SIGKILL)
    h.hello()
    h.synced()
    h.replayed()
    recovery = h.node.recovery
    child = h.child
    h.node.stop()
    assert child.signals == [signal.SIGINT] and h.state() == S.STOPPED
    assert recovery is not None and recovery.streamer is None and h.sup.safety.log == HELD


def test_a_running_node_keeps_the_shared_standby_pool_full(tmp_path: Path) -> None:
    # The pool is shared: a crash of another node may take a standby at any time, so a running
    # node tops it up every STANDBY_DELAY (the launcher refills only what is missing, and not
    # while a standby was just taken), and never during its own start or recovery.
    h = Harness(tmp_path, method='rory', warm_standby=True)
    h.sup.launcher.standby = True
    h.node.start()
    h.beat()
    h.tick(STANDBY_DELAY)  # starting: not yet
    assert h.sup.launcher.prepared == []
    h.up()
    h.tick(STANDBY_DELAY / 2)
    assert h.sup.launcher.prepared == []
    h.tick(STANDBY_DELAY / 2)
    assert len(h.sup.launcher.prepared) == 1
    assert [e['pid'] for e in h.sup.events_log.of('standby')] == [999]
    h.tick(STANDBY_DELAY / 2)
    assert len(h.sup.launcher.prepared) == 1
    h.tick(STANDBY_DELAY / 2)
    assert len(h.sup.launcher.prepared) == 2


def test_a_command_that_cannot_have_a_standby_is_said_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger='rory.supervisor')
    h = _started(tmp_path, method='rory', warm_standby=True)
    for _ in range(4):
        h.tick(STANDBY_DELAY)
    assert len(h.sup.launcher.prepared) == 4
    assert caplog.text.count('no warm standby for this command') == 1
