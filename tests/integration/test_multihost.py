"""Recovery across hosts: the node and its supervisor on host a, its publisher on host b.

Hosts are Linux network namespaces joined by a veth pair (rory_eval.harness.hosts); every process
speaks UDPv4 only (namespaces share /dev/shm: shared memory must not bypass the link) with
discovery range SUBNET. The integrator is SIGKILLed mid-run; with nothing lost or applied
twice its final history is exactly 1..N (rory_eval.harness.scenario). Two outages of the link during
the recovery show where the network's own guarantee ends, and that RORY reports it: its Fast
DDS profile (rory_runtime/dds/fast_rediscovery.xml) declares a participant gone after a 3 s
lease, so a shorter outage is bridged by DDS's reliable resends, and a longer one makes the
publisher drop the readers on host a, and with them every number it sends until the hosts
rediscover each other."""

from __future__ import annotations

import signal
import subprocess
import threading
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

from rory_eval.bench.multihost_bench import HostRun, Outage, run_on_hosts
from rory_eval.harness.hosts import Host, Hosts, netns_available

pytestmark = pytest.mark.ros

COUNT = 375  # 7.5 s at 50 Hz: numbers still flow after the recovery and after the outage
RATE = 50.0
# Seconds after the first number: by then the node's warm standby (started 1 s after the node,
# ready 0.5-1.6 s later here) is ready, so the replacement is its usual fast self.
KILL_AT = 2.0


@pytest.fixture
def hosts(ros_domain: int) -> Iterator[Hosts]:
    """Hosts a and b, named after this process and domain (parallel workers never collide)."""
    ok, why = netns_available()
    if not ok:
        pytest.skip(f'no network namespaces here: {why}')
    with Hosts(['a', 'b'], tag=f'd{ros_domain}', subnet=ros_domain) as made:
        yield made


def _run(hosts: Hosts, tmp_path: Path, domain: int, *, kill_at: float, interval: float,
         outage: Outage | None = None, count: int = COUNT) -> HostRun:
    return run_on_hosts(
        hosts, tmp_path, node_host=hosts['a'], publisher_host=hosts['b'], domain_id=domain,
        count=count, rate=RATE, kill_at=kill_at, interval=interval, outage=outage,
    )


def _ring_found_late(hosts: Hosts, monkeypatch: pytest.MonkeyPatch,
                     seconds: float) -> list[threading.Timer]:
    """Freeze the supervisor (SIGSTOP) for ``seconds`` from the moment the link comes back.

    Its participant, and with it RORY's ring, is then found again by the publisher after the
    node's live reader (the node is a process of its own): the order issue 35 met on another
    machine, here made likely rather than left to DDS's schedule. Shorter than the node's
    RELAY_SILENCE_NS (2 s) less the relay's keepalive period: the node must not take the relay
    for dead meanwhile. Returns the timers that thaw it (joined after the run).
    """
    supervisors: list[subprocess.Popen[bytes]] = []
    popen, link_up = hosts.popen, hosts.link_up

    def popen_noting(host: Host, args: Sequence[str], **kwargs: Any) -> subprocess.Popen[bytes]:
        proc = popen(host, args, **kwargs)
        if 'supervise' in args:
            supervisors.append(proc)
        return proc

    def link_up_frozen(host: Host) -> None:
        (supervisor,) = supervisors
        supervisor.send_signal(signal.SIGSTOP)
        link_up(host)  # returns at once: the run notes the time the link came back
        thaw = threading.Timer(seconds, supervisor.send_signal, (signal.SIGCONT,))
        thaw.start()
        thawing.append(thaw)

    thawing: list[threading.Timer] = []
    monkeypatch.setattr(hosts, 'popen', popen_noting)
    monkeypatch.setattr(hosts, 'link_up', link_up_frozen)
    return thawing


def _recovered(run: HostRun) -> dict[str, object]:
    recovered = [e for e in run.result.events if e['kind'] == 'recovered']
    assert len(recovered) == 1, f'expected one recovery:\n{run.result.log[-3000:]}'
    assert recovered[0]['crashes'] == 1
    return recovered[0]


def _assert_link_was_the_path(run: HostRun) -> None:
    """Nothing from host b reached host a while the link was down; it came after."""
    assert run.link_down is not None and run.link_up is not None
    # 0.1 s: a callback may stamp a number that was already in host a's socket buffer.
    assert run.seen_between(run.link_down + 0.1, run.link_up) == []
    assert run.seen_between(run.link_up, run.link_up + 2.0), 'nothing came after the outage'


def test_recovery_across_hosts_is_exact(hosts: Hosts, tmp_path: Path, ros_domain: int) -> None:
    # Checkpoint every 1 s: restored from a checkpoint, then the numbers after its cut
    # replayed - all of them sent over the link.
    run = _run(hosts, tmp_path, ros_domain, kill_at=KILL_AT, interval=1.0)
    recovered = _recovered(run)
    hello = [e for e in run.result.events if e['kind'] == 'hello'][-1]
    assert hello['mode'] == 'recover' and hello['restored'] is not None
    assert int(str(recovered['replayed'])) > 0
    assert run.result.history == list(range(1, COUNT + 1)), run.result.log[-3000:]
    # /numbers crossed the veth (rx on host a's interface), not loopback or shared memory.
    assert run.link_packets[0] > COUNT


def test_short_link_outage_during_recovery_is_exact(
    hosts: Hosts, tmp_path: Path, ros_domain: int
) -> None:
    # Killed before its first checkpoint (every 6 s): the replacement replays ~2 s of numbers,
    # paced, and the link is down for 0.6 s from its spawn on (less than the 3 s lease).
    run = _run(hosts, tmp_path, ros_domain, kill_at=KILL_AT, interval=6.0, outage=Outage(0.6))
    recovered = _recovered(run)
    _assert_link_was_the_path(run)
    assert run.link_down is not None
    assert run.link_down < float(str(recovered['t'])), 'the outage began after the release'
    # DDS resent what was published during the outage once the link was back: nothing skipped,
    # on host a and in the node alike.
    assert [n for _, n in run.numbers_seen] == list(range(1, COUNT + 1))
    assert run.result.history == list(range(1, COUNT + 1)), run.result.log[-3000:]


@pytest.mark.parametrize('ring_late', [0.0, 1.2], ids=['as-dds-rematches', 'ring-found-late'])
def test_link_outage_longer_than_the_lease_loses_only_what_never_arrived_and_says_so(
    hosts: Hosts, tmp_path: Path, ros_domain: int, monkeypatch: pytest.MonkeyPatch,
    ring_late: float,
) -> None:
    # The same, with the link down for 4 s. After 3 s without a word from host a the
    # publisher on b drops its readers there (lease expired); what it sends until they are
    # matched again is delivered to nobody on host a (volatile: a new match gets no history).
    # The node's live reader and RORY's ring are matched again each on its own schedule:
    # here the ring usually first; with ring_late, the live reader. Numbers must still flow
    # well after the ring is back, so that run publishes for longer.
    count, thawing = COUNT, []
    if ring_late:
        thawing = _ring_found_late(hosts, monkeypatch, ring_late)
        count = COUNT + 250
    run = _run(hosts, tmp_path, ros_domain, kill_at=KILL_AT, interval=6.0, outage=Outage(4.0),
               count=count)
    for thaw in thawing:
        thaw.join()
    _recovered(run)
    _assert_link_was_the_path(run)
    assert run.link_down is not None and run.link_up is not None
    assert run.published_from is not None
    history = run.result.history
    assert history == sorted(set(history)), 'applied twice or out of order'
    missing = sorted(set(range(1, count + 1)) - set(history))
    assert missing, 'a 4 s outage lost nothing: has the lease changed?'
    # One run of numbers, published (at RATE from number 1 on) while the link was down or
    # before the hosts had rediscovered each other - the ones DDS dropped, nothing of RORY's.
    assert missing == list(range(missing[0], missing[-1] + 1))
    published = [run.published_from + (n - 1) / RATE for n in (missing[0], missing[-1])]
    # Rediscovery after the link is back takes up to an announcement period (1 s) and more.
    assert run.link_down - 0.1 <= published[0] and published[1] <= run.link_up + 2.0
    # A live subscriber on host a that never crashed (the observer) lost a run of numbers
    # too, from the same moment on: the loss is the network's, not RORY's. Where each run
    # ends is where that reader was matched again, and the publisher matches each reader of
    # host a on its own schedule: the node's run ends where the first of its two readers (its
    # live reader, RORY's ring) was matched again, the observer's where it was. So the runs
    # overlap, but either may be the longer (before issue 35 this asserted the observer had
    # none of the node's missing numbers: true only when the observer was matched no earlier
    # than the node's readers).
    observed = {n for _, n in run.numbers_seen}
    observer_missed = sorted(set(range(1, count + 1)) - observed)
    assert observer_missed == list(range(observer_missed[0], observer_missed[-1] + 1))
    assert set(missing) & set(observer_missed), (missing, observer_missed)
    # RORY cannot bring back what reached neither of its readers (a node that had not crashed
    # lost them too), but it says so: an input_gap record with exactly what the node missed,
    # and a warning. That holds in either order of the re-matching: the ring first (the node
    # misses what the ring missed), or the node's live reader first (what only it got is
    # applied before the first relayed message, and left out of the gap: the switched event's
    # live_only).
    gaps = [(e['topic'], e['first'], e['last']) for e in run.result.events
            if e['kind'] == 'input_gap']
    switched = [e for e in run.result.events if e['kind'] == 'switched']
    assert gaps == [('/numbers', missing[0], missing[-1])], (switched, run.result.log[-3000:])
    assert 'never reached this host' in run.result.log
    # The relay said it was alive while its ring got nothing: the node never took it for dead.
    assert 'no relay for /numbers' not in run.result.log


def test_hosts_links_run_when_made(hosts: Hosts) -> None:
    # Hosts returns only once each interface runs: no process of a test starts before.
    assert all(hosts.running(host) for host in hosts.hosts)
    hosts.link_down(hosts['b'])  # a loses its carrier too
    assert not hosts.running(hosts['a'])
    hosts.link_up(hosts['b'])
    hosts.wait_running()
    assert all(hosts.running(host) for host in hosts.hosts)
    # What a failed run writes beside its logs: every host's addresses and UDP sockets.
    snapshot = hosts.snapshot()
    for host in hosts.hosts:
        assert f'## {host.label} ({host.netns}): ss -uanp' in snapshot
        assert host.address in snapshot
