"""The handover (rory_runtime/supervisor/handover.py) on its own: what each status of a new
process decides, as Steps, over fakes (no ManagedNode, no ROS)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import yaml
from fake_supervisor import (
    HELLO,
    INPUT,
    RELEASED_STATS,
    FakeClock,
    FakeEvents,
    FakeRing,
    FakeSafety,
)

from rory_runtime import protocol
from rory_runtime.freshness import Verdict
from rory_runtime.log import SegmentStore
from rory_runtime.protocol import OpenedStatus, ReleasedStatus, RestoredCheckpoint
from rory_runtime.store import CheckpointStore
from rory_runtime.supervisor.config import NodeConfig, load_config
from rory_runtime.supervisor.gate import SYNC_PERIOD, Gate
from rory_runtime.supervisor.handover import Handover, Step, stale_refusal
from rory_runtime.supervisor.health import NodeRecord
from rory_runtime.supervisor.incarnation import Incarnation
from rory_runtime.supervisor.loop_events import Released
from rory_runtime.supervisor.recovery import GapReports, Recovery
from rory_runtime.supervisor.states import NodeState as S

KEY = b'k' * 32


class Shadow:
    """A shadow-topic writer that keeps what it was given."""

    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def publish(self, raw: bytes) -> None:
        self.sent.append(raw)

    def kinds(self) -> list[str]:
        return [type(protocol.unpack(protocol.sign(raw, KEY), KEY)).__name__ for raw in self.sent]


class Parts:
    """A Handover over fakes, with the node's current process and (if made) its recovery."""

    def __init__(self, tmp_path: Path, **node: Any) -> None:
        entry = {'name': 'n', 'command': ['true'], 'method': 'restart', 'warm_standby': False,
                 **node}
        path = tmp_path / 'supervise.yaml'
        path.write_text(yaml.safe_dump({'nodes': [entry], 'store': 'store'}))
        self.cfg: NodeConfig = load_config(path).nodes[0]
        self.clock = FakeClock()
        self.events = FakeEvents(self.clock)
        self.safety = FakeSafety()
        self.record = NodeRecord()
        self.posted: list[Released] = []
        self.shadow = Shadow()
        self.current = Incarnation(1, 7, replay_pub=self.shadow)
        store = tmp_path / 'store'
        self.segments = SegmentStore(store, 'n')
        self.checkpoints = CheckpointStore(store, 'n')
        gate = (None if self.cfg.release_gate is None else
                Gate('n', self.cfg.release_gate, '/rory/n/release', self.clock,
                     self.current.send_open))
        self.handover = Handover(self.cfg, self.clock, self.events, gate, self.record,
                                 GapReports('n', self.events), self.posted.append,
                                 self.segments.next_number)

    def recovery(self) -> Recovery:
        rec = Recovery(node_id='n', crashed=self.clock(), crashed_ns=1, safety=self.safety,
                       ring=None, segments=self.segments, checkpoints=self.checkpoints,
                       clock=self.clock)
        rec.begin()
        return rec

    def hello(self, **fields: Any) -> Any:
        hello = dataclasses.replace(HELLO, method=self.cfg.method, **fields)
        self.current.hello = hello
        return hello


def _stats(**counts: int) -> ReleasedStatus:
    return ReleasedStatus(**{**RELEASED_STATS, **counts})


def test_a_stale_checkpoint_under_refuse_is_a_give_up_with_its_verdict(tmp_path: Path) -> None:
    p = Parts(tmp_path, method='checkpoint')
    verdict = Verdict(age_s=42.0, clock='system', refused=['pose'], max_age={'pose': 5.0})
    restored = RestoredCheckpoint(seq=3, cut=None, created_ns=1, parameters=(), lifecycle=None,
                                  freshness=verdict)
    step = p.handover.hello(p.current, p.hello(restored=restored), S.RESTORING, p.recovery())
    assert step == Step(give_up=stale_refusal(verdict), fields={'freshness': verdict.to_json()})
    assert step.give_up is not None and step.give_up.startswith(
        'checkpoint too old for pose (age 42.0 s on the system clock; on_stale: refuse)')
    assert p.record.freshness == verdict and p.shadow.sent == []


def test_a_method_without_a_log_goes_on_at_hello_without_a_state(tmp_path: Path) -> None:
    p = Parts(tmp_path, method='restart')
    rec = p.recovery()
    p.clock.advance(0.5)
    assert p.handover.hello(p.current, p.hello(), S.RESTORING, rec) == Step()
    assert rec.timings.hello == p.clock() and p.shadow.sent == []


def test_a_fresh_start_that_logs_arms_syncs_then_releases_once_the_ring_matches(
    tmp_path: Path
) -> None:
    p = Parts(tmp_path, method='rory')
    step = p.handover.hello(p.current, p.hello(inputs=(INPUT,)), S.STARTING, None)
    assert (step.state, step.reason) == (S.ARMING, 'waiting for RORY readers to match')
    assert p.shadow.sent == [] and step.then is not None
    step.then()  # once the state is entered
    assert p.shadow.kinds() == ['Sync']
    ring = FakeRing()
    assert p.handover.tick(p.clock.advance(SYNC_PERIOD / 2), p.current, S.ARMING, ring) == Step()
    assert p.shadow.kinds() == ['Sync']  # not yet
    p.handover.tick(p.clock.advance(SYNC_PERIOD), p.current, S.ARMING, ring)
    assert p.shadow.kinds() == ['Sync', 'Sync']  # no SYNCED yet: again
    assert p.current.synced(7, {INPUT.topic: 1})
    p.handover.tick(p.clock.advance(SYNC_PERIOD), p.current, S.ARMING, ring)
    assert p.shadow.kinds() == ['Sync', 'Sync']  # the ring has no reader of /in yet
    ring.ensure([INPUT])
    for _ in range(2):
        p.handover.tick(p.clock.advance(SYNC_PERIOD), p.current, S.ARMING, ring)
    assert p.shadow.kinds() == ['Sync', 'Sync', 'Release']  # once
    step = p.handover.released(p.current, _stats(), S.ARMING, None)
    assert step == Step(S.RUNNING, 'released') and p.current.running_since == p.clock()


def test_a_recovery_that_logs_replays_after_synced_and_posts_released(tmp_path: Path) -> None:
    p = Parts(tmp_path, method='rory')
    rec = p.recovery()
    rec.join_ring(FakeRing())
    step = p.handover.hello(p.current, p.hello(inputs=(INPUT,)), S.RESTORING, rec)
    assert (step.state, step.reason) == (S.REPLAYING, 'replay after segment None')
    p.handover.synced(p.current, S.RESTORING, rec)  # not replaying yet: nothing
    assert rec.streamer is None
    p.handover.synced(p.current, S.REPLAYING, rec)
    assert rec.streamer is not None
    deadline = time.monotonic() + 5.0
    while not p.posted and time.monotonic() < deadline:
        time.sleep(0.01)
    rec.stop()  # the streamer relays on after RELEASE
    assert p.posted == [Released('n', 1, 0)]
    assert 'Release' in p.shadow.kinds()  # nothing to replay: RELEASE at once


def test_a_recovery_at_a_gate_waits_then_opened_finishes_s4(tmp_path: Path) -> None:
    p = Parts(tmp_path, method='restart', release_gate={'timeout': 30.0})
    rec = p.recovery()
    step = p.handover.released(p.current, _stats(applied=3), S.RESTORING, rec)
    assert step.state == S.GATED and step.reason.startswith('caught up; outputs muted')
    assert p.events.of('gated') == [] and step.then is not None
    step.then()
    assert p.events.of('gated')[0]['service'] == '/rory/n/release'
    assert p.handover.on_call(S.GATED) == (True, 'n: released')
    assert p.shadow.kinds() == ['Open']
    assert p.handover.opened(p.current, OpenedStatus(muted=2), S.RESTORING, rec) == Step()
    step = p.handover.opened(p.current, OpenedStatus(muted=2), S.GATED, rec)
    assert (step.state, step.reason, step.end_recovery) == (S.RUNNING, 'released', True)
    assert p.events.of('gate_opened')[0]['muted'] == 2
    assert p.safety.log == [('hold', 'n'), ('release', 'n')]  # S4, before RUNNING is entered
    assert p.events.of('recovered') == [] and step.then is not None
    step.then()
    (recovered,) = p.events.of('recovered')
    assert recovered['applied'] == 3 and recovered['gate'] == '/rory/n/release called'
    assert p.record.last_recovery is not None


def test_a_gate_nobody_calls_is_given_up_at_its_timeout(tmp_path: Path) -> None:
    p = Parts(tmp_path, method='restart', release_gate={'timeout': 5.0,
                                                        'on_timeout': 'give_up'})
    p.handover.released(p.current, _stats(), S.REPLAYING, p.recovery())
    assert p.handover.tick(p.clock.advance(4.0), p.current, S.GATED, None) == Step()
    step = p.handover.tick(p.clock.advance(1.0), p.current, S.GATED, None)
    assert step.give_up is not None and step.give_up.startswith('no call on /rory/n/release')
    p.handover.drop()
    assert p.handover.gate is not None and p.handover.gate.held is None


def test_without_a_gate_a_call_is_refused_and_a_first_start_runs_at_released(
    tmp_path: Path
) -> None:
    p = Parts(tmp_path)
    assert p.handover.on_call(S.RUNNING) == (False, 'n: no release gate')
    assert p.handover.released(p.current, _stats(), S.STARTING, None) == Step(S.RUNNING,
                                                                               'released')
    assert p.handover.released(p.current, _stats(), S.RUNNING, None) == Step()
