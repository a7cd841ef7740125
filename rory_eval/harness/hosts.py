"""Several "hosts" on one machine: Linux network namespaces joined by a virtual link.

Each host is a network namespace with its loopback and one interface ``eth0`` holding a private
address (``10.231.<subnet>.<i>/24``); the addresses exist only inside the namespaces, so
nothing of the machine's own network is touched and parallel runs (pytest-xdist workers, a
bench beside a test) cannot collide: namespace names carry the pid and a tag, and two runs'
namespaces never share a link even when their addresses are equal. Two hosts are joined by a
veth pair; three or more by a bridge in a namespace of its own (the "switch").

What DDS needs across these hosts (measured here, Fast DDS from the Jazzy wheels):

* ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4`` in *every* process. Network namespaces do not separate
  ``/dev/shm``; a Fast DDS that took two namespaces for one host would carry data over shared
  memory, past the link, and taking the link down would prove nothing. Fast DDS 2.14 (these
  wheels) did not: it tells hosts apart by a hash of the hostname and the IPv4 addresses, which
  differ per namespace, and with its default transports an outage still stopped all data. UDPv4
  only makes that independent of the version's rule (RORY's processes use UDPv4 anyway).
* ``ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET`` (LOCALHOST limits discovery to the host itself).
* No multicast route and no ``ROS_STATIC_PEERS``: SPDP discovery goes to 239.255.0.1 from one
  socket per interface, each with ``IP_MULTICAST_IF`` set to that interface (seen with strace),
  so the kernel needs no route for 224.0.0.0/4 (``ip route get 239.255.0.1`` fails in these
  namespaces, and discovery across the link works). Not needing a route also keeps
  :meth:`Hosts.link_up` simple: ``ip link set ... down`` flushes routes added by hand.

No process starts before every host's interface runs (:meth:`Hosts.wait_running`): Fast DDS
lists a host's interfaces when a participant is made, and leaves out one not yet running.

Every process is started through ``ip netns exec``, which execs the command: the pid is the
program's own. Leaving the :class:`Hosts` context (also on an exception) stops every process
started through it, kills whatever else still runs inside the namespaces (a supervisor's
children), and deletes the namespaces.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import shutil
import signal
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

PREFIX = 'rory'
"""Namespace names start ``rory-<pid>-<tag>-``: whose they are is visible in ``ip netns``."""


@dataclass(frozen=True)
class Host:
    """One namespace: its name for ``ip netns``, its label and its address on the link."""

    label: str
    netns: str
    address: str
    device: str = 'eth0'


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(['ip', *args], check=check, capture_output=True, text=True,
                          timeout=10)


@functools.cache
def netns_available() -> tuple[bool, str]:
    """Whether this machine lets us make hosts: root, ``ip``, namespaces, veth, ``netns exec``.

    Returns:
        (True, '') or (False, the reason), for a ``pytest.skip`` that says why.
    """
    if not hasattr(os, 'geteuid') or os.geteuid() != 0:
        return False, 'network namespaces need root (ip netns add); not running as root'
    if shutil.which('ip') is None:
        return False, 'the ip command (iproute2) is not installed'
    probe = Hosts(['a', 'b'], tag='probe')
    try:
        with probe:
            run = probe.run(probe.hosts[0], ['true'])
            if run.returncode != 0:
                return False, f'ip netns exec fails: {run.stderr.strip()}'
    except (OSError, subprocess.SubprocessError) as err:
        detail = err.stderr.strip() if isinstance(err, subprocess.CalledProcessError) else ''
        return False, f'cannot make network namespaces joined by veth: {err} {detail}'.strip()
    return True, ''


class Hosts:
    """Hosts as network namespaces, for a ``with`` block.

    Args:
        labels: One label per host (e.g. ``['a', 'b']``), at least two.
        tag: Makes the names unique beside the pid (e.g. the ROS domain id).
        subnet: Third octet of the hosts' addresses, 0-255.
    """

    def __init__(self, labels: Sequence[str], *, tag: str, subnet: int = 0) -> None:
        if len(labels) < 2 or len(set(labels)) != len(labels):
            raise ValueError(f'need two or more distinct host labels, got {labels!r}')
        base = f'{PREFIX}-{os.getpid()}-{tag}'
        self.hosts = [
            Host(label, f'{base}-{label}', f'10.231.{subnet % 256}.{i + 1}')
            for i, label in enumerate(labels)
        ]
        # Two hosts: a veth pair between them. More: each host's veth ends on a bridge.
        self.switch = f'{base}-switch' if len(labels) > 2 else None
        self._made: list[str] = []
        self._procs: list[subprocess.Popen[bytes]] = []
        self._logs: list[contextlib.ExitStack] = []

    def __getitem__(self, label: str) -> Host:
        for host in self.hosts:
            if host.label == label:
                return host
        raise KeyError(label)

    # -- setup and teardown ---------------------------------------------------------------------

    def __enter__(self) -> Hosts:
        try:
            self._create()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _add_netns(self, name: str) -> None:
        _ip('netns', 'add', name)
        self._made.append(name)
        _ip('-n', name, 'link', 'set', 'lo', 'up')

    def _create(self) -> None:
        for host in self.hosts:
            self._add_netns(host.netns)
        if self.switch is None:
            a, b = self.hosts
            # Created inside the namespaces: no name ever exists in the machine's own namespace.
            _ip('-n', a.netns, 'link', 'add', a.device, 'type', 'veth',
                'peer', 'name', b.device, 'netns', b.netns)
        else:
            self._add_netns(self.switch)
            _ip('-n', self.switch, 'link', 'add', 'br0', 'type', 'bridge')
            _ip('-n', self.switch, 'link', 'set', 'br0', 'up')
            for i, host in enumerate(self.hosts):
                port = f'p{i}'
                _ip('-n', self.switch, 'link', 'add', port, 'type', 'veth',
                    'peer', 'name', host.device, 'netns', host.netns)
                _ip('-n', self.switch, 'link', 'set', port, 'master', 'br0')
                _ip('-n', self.switch, 'link', 'set', port, 'up')
        for host in self.hosts:
            _ip('-n', host.netns, 'addr', 'add', f'{host.address}/24', 'dev', host.device)
            _ip('-n', host.netns, 'link', 'set', host.device, 'up')
        self.wait_running()

    def running(self, host: Host) -> bool:
        """Whether ``host``'s interface is operationally up (IFF_RUNNING, as getifaddrs says)."""
        shown = _ip('-j', '-n', host.netns, 'link', 'show', host.device, check=False).stdout
        try:
            return bool(json.loads(shown)[0].get('operstate') == 'UP')
        except (ValueError, IndexError, KeyError):
            return False

    def wait_running(self, timeout: float = 5.0) -> None:
        """Return once every host's interface is operationally up; RuntimeError after ``timeout``.

        ``ip link set up`` returns before the kernel marks the link running (the carrier is
        reported by the kernel's linkwatch worker, measured 4-126 ms later here), and Fast DDS
        lists a host's interfaces when a participant is created, leaving out those not running:
        a participant made in a namespace whose veth had never had carrier sent its
        announcements on 127.0.0.1 only, and still did 3 s after the carrier came (captured
        with tcpdump). So no process starts in a host before its link runs.
        """
        deadline = time.monotonic() + timeout
        waiting = list(self.hosts)
        while waiting:
            waiting = [host for host in waiting if not self.running(host)]
            if waiting and time.monotonic() > deadline:
                raise RuntimeError(
                    f'link not running after {timeout:g} s: {[h.netns for h in waiting]}')
            if waiting:
                time.sleep(0.005)

    def close(self) -> None:
        """Stop every process, kill what else runs in the namespaces, delete them (idempotent).

        Each step runs even when an earlier one failed: a test that fails must not leave
        namespaces or processes behind.
        """
        for proc in self._procs:
            with contextlib.suppress(Exception):
                stop(proc)
        self._procs.clear()
        for stack in self._logs:
            with contextlib.suppress(Exception):
                stack.close()
        self._logs.clear()
        for name in reversed(self._made):
            # A supervisor's nodes and standbys run in sessions of their own: a process-group
            # signal to the supervisor does not reach them when it was SIGKILLed. Everything
            # in a namespace made here was started by us.
            with contextlib.suppress(Exception):
                pids = _ip('netns', 'pids', name, check=False).stdout.split()
                for pid in pids:
                    with contextlib.suppress(ProcessLookupError, ValueError):
                        os.kill(int(pid), signal.SIGKILL)
                if pids:
                    time.sleep(0.1)  # let the kernel tear the processes' sockets down
            with contextlib.suppress(Exception):
                _ip('netns', 'del', name, check=False)
        self._made.clear()

    # -- processes ------------------------------------------------------------------------------

    def command(self, host: Host, args: Sequence[str]) -> list[str]:
        """``args`` run inside ``host``."""
        return ['ip', 'netns', 'exec', host.netns, *args]

    def run(self, host: Host, args: Sequence[str], *, env: dict[str, str] | None = None,
            timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
        """Run a short command inside ``host`` and wait for it (killed after ``timeout``)."""
        return subprocess.run(self.command(host, args), capture_output=True, text=True,
                              env=env, timeout=timeout, check=False)

    def popen(
        self, host: Host, args: Sequence[str], *, env: dict[str, str], cwd: Path, log: Path
    ) -> subprocess.Popen[bytes]:
        """Start ``args`` inside ``host`` in a session of its own, output to ``log``.

        The process is stopped when the context ends, if it has not been already.
        """
        stack = contextlib.ExitStack()
        out = stack.enter_context(log.open('wb'))
        self._logs.append(stack)
        proc = subprocess.Popen(self.command(host, args), env=env, cwd=cwd, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)
        self._procs.append(proc)
        return proc

    # -- the link -------------------------------------------------------------------------------

    def link_down(self, host: Host) -> None:
        """Cut ``host`` off the link (its interface down; the far end loses carrier).

        The other hosts' own traffic (between processes on one host) goes on unchanged, as when
        a cable is pulled.
        """
        _ip('-n', host.netns, 'link', 'set', host.device, 'down')

    def link_up(self, host: Host) -> None:
        """Put ``host`` back on the link (its address and connected route come back with it)."""
        _ip('-n', host.netns, 'link', 'set', host.device, 'up')

    def snapshot(self) -> str:
        """What each host's network looked like now: its link and addresses, its routes, its
        UDP sockets with their processes, and its interface counters. Written when a run fails
        to discover across the hosts, so that the failure explains itself
        (docs/faults.md, "test_multihost")."""
        parts = []
        for host in self.hosts:
            for args in (['ip', '-br', 'link'], ['ip', '-br', 'addr'], ['ip', 'route'],
                         ['ss', '-uanp'], ['ip', '-s', 'link', 'show', host.device]):
                try:
                    done = self.run(host, args, timeout=10.0)
                    text = done.stdout + done.stderr
                except (OSError, subprocess.TimeoutExpired) as err:
                    text = f'{err}\n'
                parts.append(f'## {host.label} ({host.netns}): {" ".join(args)}\n{text}')
        return '\n'.join(parts)

    def interface_packets(self, host: Host) -> tuple[int, int]:
        """(received, sent) packets of ``host``'s link interface so far."""
        shown = _ip('-j', '-s', '-n', host.netns, 'link', 'show', host.device).stdout
        stats = json.loads(shown)[0]['stats64']
        return int(stats['rx']['packets']), int(stats['tx']['packets'])


def stop(proc: subprocess.Popen[bytes], grace: float = 10.0) -> None:
    """SIGINT the process group, SIGKILL it after ``grace`` seconds; always reaped."""
    if proc.poll() is not None:
        return  # what it left behind in its namespace goes with the namespace sweep
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGINT)
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
