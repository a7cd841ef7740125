"""Does recording keep up with a robot's sensors? The bare node against the node under RORY.

    python -m rory_eval.bench.recording_bench [--seconds 30] [--out recording-out] [--domain 60]

The load (``examples/sensor_sink/sensor_load.py``): 10 Hz LaserScan (720 beams), 50 Hz
Odometry, 5 Hz PointCloud2 (10 000 points, 160 kB) and a 1 Hz 2000 x 2000 OccupancyGrid
(4 MB), reliable, for ``--seconds``. It is run twice, one after the other on the same domain:

a. against the bare sink (``examples/sensor_sink/sensor_sink.py``, not supervised);
b. against the instrumented sink under ``rory supervise``, method rory, with a checkpoint
   interval far longer than the run, so no segment is pruned and the log holds every message
   the node recorded.

For each run and topic it reports what the publisher published (and had acknowledged), what
the node's callbacks received (the node writes its counts at shutdown), and for (b) what is in
the node's MCAP log and whether the recorded publication sequence numbers run 1..N without a
gap or repeat; and the CPU and peak RSS of the node process, and for (b) of the supervisor's
whole process tree too (supervisor with its ring readers, node, warm standby). CPU is measured
from the first message published until the node has taken the last one; the load starts only
once the warm standby has started and gone idle, so its one-off start is not counted.

It prints a Markdown report and writes it to ``<out>/recording.md``; exit status 0 when
nothing was dropped anywhere, 1 otherwise.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rory_eval.harness.process_usage import peak_rss_mb, tree_cpu_ticks, tree_pids
from rory_eval.harness.scenario import scenario_env
from rory_runtime.log import SegmentStore

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / 'examples' / 'sensor_sink'
NODE_ID = 'sensor_sink'

STREAMS: tuple[tuple[str, str, float], ...] = (
    ('/scan', 'LaserScan, 720 beams', 10.0),
    ('/odom', 'Odometry', 50.0),
    ('/points', 'PointCloud2, 10k points', 5.0),
    ('/map', 'OccupancyGrid 2000x2000', 1.0),
)
"""(topic, what, rate in Hz), as sensor_load.py publishes them."""

CHECKPOINT_INTERVAL = 1000.0
"""Seconds: longer than any run, so no checkpoint prunes the log that is counted."""

SETTLE_S = 3.0
"""The node's counts unchanged this long after the publisher is done: it has taken all it will."""

_CLK_TCK = os.sysconf('SC_CLK_TCK')


class BenchError(RuntimeError):
    """A process of the bench failed; the message names it and ends with its log's tail."""


# --------------------------------------------------------------------------- pure helpers


@dataclass(frozen=True)
class SeqCheck:
    """The publication sequence numbers recorded on one topic (one publisher).

    Attributes:
        count: Entries recorded.
        first: Lowest sequence number, None if nothing was recorded.
        last: Highest sequence number, None if nothing was recorded.
        gaps: Missing runs between first and last, as inclusive (low, high) pairs.
        duplicates: Entries whose sequence number was recorded before.

    """

    count: int
    first: int | None
    last: int | None
    gaps: tuple[tuple[int, int], ...]
    duplicates: int

    def complete(self, published: int) -> bool:
        """True if exactly 1..published were recorded, each once.

        A DDS writer numbers its samples from 1, so a fresh publisher's ``published`` messages
        carry 1..published.
        """
        if published == 0:
            return self.count == 0
        return (self.first == 1 and self.last == published and not self.gaps
                and not self.duplicates)

    def describe(self) -> str:
        """Short text for the report, e.g. ``1-300`` or ``1-300, missing 17-19``."""
        if self.first is None:
            return 'none'
        text = f'{self.first}-{self.last}'
        if self.gaps:
            shown = ', '.join(f'{lo}' if lo == hi else f'{lo}-{hi}' for lo, hi in self.gaps[:3])
            more = f' (+{len(self.gaps) - 3} more)' if len(self.gaps) > 3 else ''
            text += f', missing {shown}{more}'
        if self.duplicates:
            text += f', {self.duplicates} repeated'
        return text


def check_sequence(seqs: Iterable[int]) -> SeqCheck:
    """Find gaps and repeats in the sequence numbers of one publisher's messages.

    Args:
        seqs: Publication sequence numbers, in any order.

    Returns:
        What was recorded, with the missing runs between the lowest and highest number.

    """
    ordered = sorted(seqs)
    gaps: list[tuple[int, int]] = []
    duplicates = 0
    for before, after in itertools.pairwise(ordered):
        if after == before:
            duplicates += 1
        elif after > before + 1:
            gaps.append((before + 1, after - 1))
    return SeqCheck(
        count=len(ordered),
        first=ordered[0] if ordered else None,
        last=ordered[-1] if ordered else None,
        gaps=tuple(gaps),
        duplicates=duplicates,
    )


@dataclass(frozen=True)
class Usage:
    """CPU and memory of some processes over the measured window."""

    cpu_seconds: float  # user + system
    wall_seconds: float
    peak_rss_mb: float  # sum of the VmHWM of the processes (an upper bound of the peak)
    parts: tuple[tuple[str, float], ...] = ()  # (process, its VmHWM in MB)

    @property
    def cpu_percent(self) -> float:
        """CPU seconds per wall second, in percent of one core."""
        return 100.0 * self.cpu_seconds / max(self.wall_seconds, 1e-9)


@dataclass
class RunResult:
    """What one run (bare or RORY) produced.

    Attributes:
        label: ``bare`` or ``rory``.
        load: sensor_load.py's summary (per topic: published, acked, publish times).
        received: Per topic, the messages the node's callbacks took (its own report).
        node: Usage of the node process.
        tree: Usage of the supervisor's process tree (RORY run only).
        recorded: Per topic, the entries in the node's MCAP log (RORY run only).
        sizes: Per topic, bytes of the largest recorded message (RORY run only).
        sequences: Per topic, the recorded sequence numbers checked (RORY run only).
        log_mb: Size of the node's log on disk (RORY run only).
        problems: Everything that went wrong, each naming the topic or file.

    """

    label: str
    load: dict[str, Any]
    received: dict[str, int]
    node: Usage
    tree: Usage | None = None
    recorded: dict[str, int] | None = None
    sizes: dict[str, int] = field(default_factory=dict)
    sequences: dict[str, SeqCheck] = field(default_factory=dict)
    log_mb: float | None = None
    problems: list[str] = field(default_factory=list)

    def published(self, topic: str) -> int:
        """Messages the load published on topic."""
        return int(self.load['topics'][topic]['published'])


def judge(run: RunResult) -> list[str]:
    """Every drop in a run: unacknowledged, not received, not recorded, a sequence gap."""
    problems = []
    for topic, _, _ in STREAMS:
        info = run.load['topics'].get(topic)
        if info is None:
            problems.append(f'{run.label}: {topic}: the publisher has no summary for it')
            continue
        published = int(info['published'])
        if not info['acked']:
            problems.append(f'{run.label}: {topic}: the publisher\'s messages were not all '
                            'acknowledged')
        received = run.received.get(topic, 0)
        if received != published:
            problems.append(f'{run.label}: {topic}: the node received {received} of {published}')
        if run.recorded is not None:
            recorded = run.recorded.get(topic, 0)
            if recorded != published:
                problems.append(f'{run.label}: {topic}: {recorded} of {published} recorded')
            seq = run.sequences.get(topic, check_sequence(()))
            if not seq.complete(published):
                problems.append(f'{run.label}: {topic}: recorded sequence numbers '
                                f'{seq.describe()}, expected 1-{published}')
    return problems


def count_recorded(store: Path, node: str) -> tuple[dict[str, int], dict[str, int],
                                                       dict[str, SeqCheck]]:
    """Read a node's log segments: entries, largest message and sequence check per topic.

    Raises:
        LogError: A segment is not a readable log (the error names its file).

    """
    seqs: dict[str, list[int]] = {}
    sizes: dict[str, int] = {}
    for entry in SegmentStore(store, node).read_after(None):
        seqs.setdefault(entry.topic, []).append(entry.seq)
        sizes[entry.topic] = max(sizes.get(entry.topic, 0), len(entry.data))
    counts = {topic: len(s) for topic, s in seqs.items()}
    return counts, sizes, {topic: check_sequence(s) for topic, s in seqs.items()}


def _fmt_ms(value: Any) -> str:
    return '-' if value is None else f'{float(value):.1f}'


def report(bare: RunResult, rory: RunResult, seconds: float) -> str:
    """The Markdown report of both runs."""
    lines = [
        f'## Recording under load: {seconds:g} s of sensor data, bare node vs node under RORY',
        '',
        '| topic | message | rate (Hz) | bytes | bare: published | bare: received | '
        'RORY: published | RORY: received | RORY: recorded | recorded sequence numbers |',
        '|---|---|---:|---:|---:|---:|---:|---:|---:|---|',
    ]
    for topic, what, rate in STREAMS:
        recorded = '-' if rory.recorded is None else str(rory.recorded.get(topic, 0))
        seq = rory.sequences.get(topic)
        lines.append(
            f'| {topic} | {what} | {rate:g} | {rory.sizes.get(topic, "-")} | '
            f'{bare.published(topic)} | {bare.received.get(topic, 0)} | '
            f'{rory.published(topic)} | {rory.received.get(topic, 0)} | {recorded} | '
            f'{seq.describe() if seq else "none"} |'
        )
    log = f'{rory.log_mb:.0f}' if rory.log_mb is not None else '-'
    lines += [
        '',
        '| run | node CPU % | node peak RSS (MB) | all processes CPU % | '
        'all processes peak RSS (MB) | log written (MB) |',
        '|---|---:|---:|---:|---:|---:|',
        f'| bare | {bare.node.cpu_percent:.1f} | {bare.node.peak_rss_mb:.0f} | '
        f'{bare.node.cpu_percent:.1f} | {bare.node.peak_rss_mb:.0f} | - |',
    ]
    tree = rory.tree or rory.node
    lines += [
        f'| RORY | {rory.node.cpu_percent:.1f} | {rory.node.peak_rss_mb:.0f} | '
        f'{tree.cpu_percent:.1f} | {tree.peak_rss_mb:.0f} | {log} |',
        '',
        'CPU in % of one core from the first message published until the node had taken the '
        'last; RSS the sum of the peak RSS (VmHWM) of the processes. For RORY, "all processes" '
        'is the supervisor (with its ring readers, which receive every message too), the node '
        'and its warm standby'
        + (': ' + ', '.join(f'{name} {mb:.0f} MB' for name, mb in tree.parts) if tree.parts
           else '')
        + '.',
        '',
        '| topic | bare: publish() median / max (ms) | bare: latest send (ms) | '
        'RORY: publish() median / max (ms) | RORY: latest send (ms) |',
        '|---|---:|---:|---:|---:|',
    ]
    for topic, _, _ in STREAMS:
        b, r = bare.load['topics'][topic], rory.load['topics'][topic]
        lines.append(
            f'| {topic} | {_fmt_ms(b["publish_ms_median"])} / {_fmt_ms(b["publish_ms_max"])} | '
            f'{_fmt_ms(b["max_late_ms"])} | {_fmt_ms(r["publish_ms_median"])} / '
            f'{_fmt_ms(r["publish_ms_max"])} | {_fmt_ms(r["max_late_ms"])} |'
        )
    lines += ['', 'Latest send: how far behind its schedule the publisher sent a message.', '']
    problems = bare.problems + rory.problems
    if problems:
        lines += ['**Dropped or missing:**', '', *[f'- {p}' for p in problems]]
    else:
        lines.append('**Nothing dropped**: every message published was acknowledged, received '
                     'by the node in both runs and, under RORY, recorded once, in sequence.')
    return '\n'.join(lines) + '\n'


# --------------------------------------------------------------------------- processes


@contextlib.contextmanager
def _running(args: list[str], env: dict[str, str], cwd: Path, log: Path,
             stop_timeout: float = 15.0) -> Iterator[subprocess.Popen[bytes]]:
    """A process in its own session; stopped on exit (SIGINT, then SIGKILL) and reaped."""
    with log.open('wb') as out:
        proc = subprocess.Popen(args, env=env, cwd=cwd, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            yield proc
        finally:
            _stop(proc, stop_timeout)


def _stop(proc: subprocess.Popen[bytes], timeout: float) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    # Anything the process left in its session (a node whose supervisor was killed) goes too.
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)


def _tail(path: Path, chars: int = 3000) -> str:
    try:
        return path.read_text(errors='replace')[-chars:]
    except OSError:
        return f'({path} unreadable)'


class _Meter:
    """CPU ticks of a process tree between two moments, and its peak RSS at the second."""

    def __init__(self, root: int, names: dict[int, str] | None = None) -> None:
        self.root = root
        self.names = names or {}
        self.ticks = tree_cpu_ticks(root)
        self.began = time.monotonic()

    def read(self) -> Usage:
        parts = tuple((self.names.get(pid, f'pid {pid}'), peak_rss_mb(pid))
                      for pid in tree_pids(self.root))
        return Usage(
            cpu_seconds=(tree_cpu_ticks(self.root) - self.ticks) / _CLK_TCK,
            wall_seconds=time.monotonic() - self.began,
            peak_rss_mb=sum(mb for _, mb in parts),
            parts=parts,
        )


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _wait_for(path: Path, proc: subprocess.Popen[bytes], what: str, log: Path,
              timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        if proc.poll() is not None:
            raise BenchError(f'{what} exited with {proc.returncode} before {path.name} '
                             f'appeared; {log}:\n{_tail(log)}')
        if time.monotonic() > deadline:
            raise BenchError(f'{path} did not appear within {timeout:g} s; {log}:\n{_tail(log)}')
        time.sleep(0.02)


def _settle(report_path: Path, published: dict[str, int], timeout: float) -> None:
    """Wait until the node's report shows every published message, or stops changing."""
    deadline = time.monotonic() + timeout
    last: Any = None
    changed = time.monotonic()
    while time.monotonic() < deadline:
        data = _read_json(report_path)
        counts = data.get('counts') if data else None
        if counts == published:
            return
        if counts != last:
            last, changed = counts, time.monotonic()
        elif time.monotonic() - changed > SETTLE_S:
            return
        time.sleep(0.1)


def _load_args(seconds: float, summary: Path, subscribers: int) -> list[str]:
    return [sys.executable, str(EXAMPLE / 'sensor_load.py'), '--seconds', f'{seconds:g}',
            '--summary', str(summary), '--subscribers', str(subscribers)]


def _drive_load(workdir: Path, label: str, env: dict[str, str], seconds: float,
                subscribers: int, node_pid: int, tree_pid: int | None,
                report_path: Path, names: dict[int, str] | None = None,
                ) -> tuple[dict[str, Any], Usage, Usage | None]:
    """Run the publisher to its end and let the node settle; the summary and usage."""
    summary = workdir / f'load-{label}.json'
    log = workdir / f'load-{label}.log'
    started = Path(f'{summary}.started')
    with _running(_load_args(seconds, summary, subscribers), env, workdir, log) as load:
        _wait_for(started, load, 'sensor_load.py', log, timeout=30.0)
        node_meter = _Meter(node_pid)
        tree_meter = _Meter(tree_pid, names) if tree_pid is not None else None
        try:
            load.wait(timeout=seconds + 60.0)
        except subprocess.TimeoutExpired:
            raise BenchError(f'sensor_load.py did not finish; {log}:\n{_tail(log)}') from None
        data = _read_json(summary)
        if load.returncode == 2 or data is None:
            raise BenchError(f'sensor_load.py exited with {load.returncode} without a summary; '
                             f'{log}:\n{_tail(log)}')
        published = {t: int(v['published']) for t, v in data['topics'].items()}
        _settle(report_path, published, timeout=15.0)
        node_usage = node_meter.read()
        tree_usage = tree_meter.read() if tree_meter is not None else None
    return data, node_usage, tree_usage


def _received(report_path: Path, who: str) -> dict[str, int]:
    data = _read_json(report_path)
    if data is None or not isinstance(data.get('counts'), dict):
        raise BenchError(f'{report_path}: the node ({who}) left no report of what it received')
    return {str(k): int(v) for k, v in data['counts'].items()}


def run_bare(workdir: Path, seconds: float, domain: int) -> RunResult:
    """The load against the bare sink."""
    env = scenario_env(domain)
    report_path = workdir / 'received-bare.json'
    report_path.unlink(missing_ok=True)
    node_log = workdir / 'node-bare.log'
    argv = [sys.executable, str(EXAMPLE / 'sensor_sink.py'),
            '--ros-args', '-p', f'report:={report_path}']
    with _running(argv, env, workdir, node_log) as node:
        load, usage, _ = _drive_load(workdir, 'bare', env, seconds, 1, node.pid, None,
                                     report_path)
        _stop(node, 15.0)
        if node.returncode != 0:
            raise BenchError(f'the bare sink exited with {node.returncode}; '
                             f'{node_log}:\n{_tail(node_log)}')
    run = RunResult('bare', load, _received(report_path, 'bare'), usage)
    run.problems = judge(run)
    return run


def _instrument(workdir: Path) -> Path:
    out = workdir / 'out'
    if out.exists():
        shutil.rmtree(out)
    done = subprocess.run(
        [sys.executable, '-m', 'rory_instrument', str(EXAMPLE),
         '--vars', str(EXAMPLE / 'keyvars.yaml'), '-o', str(out)],
        capture_output=True, text=True, check=False,
    )
    if done.returncode != 0:
        raise BenchError(f'rory-instrument {EXAMPLE} failed ({done.returncode}):\n'
                         f'{done.stdout}{done.stderr}')
    return out


def _events(store: Path) -> list[dict[str, Any]]:
    try:
        text = (store / 'events.jsonl').read_text()
    except OSError:
        return []
    events = []
    for line in text.splitlines():
        with contextlib.suppress(ValueError):
            events.append(json.loads(line))
    return events


def _wait_running(store: Path, sup: subprocess.Popen[bytes], log: Path,
                  timeout: float) -> int:
    """The node's pid once the supervisor reports it RUNNING."""
    deadline = time.monotonic() + timeout
    while True:
        events = _events(store)
        pids = [int(e['pid']) for e in events if e.get('kind') == 'spawn']
        if pids and any(e.get('kind') == 'state' and e.get('new') == 'RUNNING'
                        for e in events):
            return pids[-1]
        if sup.poll() is not None:
            raise BenchError(f'rory supervise exited with {sup.returncode}; {log}:\n{_tail(log)}')
        if time.monotonic() > deadline:
            raise BenchError(f'{NODE_ID} was not RUNNING after {timeout:g} s; '
                             f'{log}:\n{_tail(log)}')
        time.sleep(0.05)


def _wait_standby_idle(store: Path, timeout: float) -> None:
    """Wait until the warm standby has started and gone idle.

    The supervisor starts it a second after the node runs, and its start (imports,
    ``rclpy.init``, ~2 s of CPU) would otherwise land in the measured window: a one-off cost
    that is not recording. Idle: under 5 % of a core over half a second.
    """
    deadline = time.monotonic() + timeout
    pid = None
    while pid is None and time.monotonic() < deadline:
        pids = [int(e['pid']) for e in _events(store) if e.get('kind') == 'standby']
        pid = pids[-1] if pids else None
        time.sleep(0.05)
    if pid is None:
        return
    before = tree_cpu_ticks(pid)
    while time.monotonic() < deadline:
        time.sleep(0.5)
        now = tree_cpu_ticks(pid)
        if (now - before) / _CLK_TCK < 0.025:
            return
        before = now


def run_rory(workdir: Path, seconds: float, domain: int) -> RunResult:
    """The load against the instrumented sink under ``rory supervise``."""
    env = scenario_env(domain)
    _instrument(workdir)
    store = workdir / 'store'
    if store.exists():
        shutil.rmtree(store)
    report_path = workdir / 'received-rory.json'
    report_path.unlink(missing_ok=True)
    config = {
        'nodes': [{
            'name': NODE_ID,
            'command': ['python', f'out/{NODE_ID}.py', '--ros-args', '-p',
                        f'report:={report_path}'],
            'method': 'rory',
            'checkpoint_interval': CHECKPOINT_INTERVAL,
        }],
        'store': 'store',
    }
    config_path = workdir / 'supervise.yaml'
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    sup_log = workdir / 'supervisor.log'
    argv = [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config_path)]
    with _running(argv, env, workdir, sup_log, stop_timeout=30.0) as sup:
        node_pid = _wait_running(store, sup, sup_log, timeout=60.0)
        _wait_standby_idle(store, timeout=15.0)
        # The node's reader and the supervisor's ring reader on every topic.
        names = {sup.pid: 'supervisor', node_pid: 'node'}
        names.update({int(e['pid']): 'warm standby' for e in _events(store)
                      if e.get('kind') == 'standby'})
        load, usage, tree = _drive_load(workdir, 'rory', env, seconds, 2, node_pid, sup.pid,
                                        report_path, names)
        _stop(sup, 30.0)
    if sup.returncode != 0:
        raise BenchError(f'rory supervise exited with {sup.returncode}; '
                         f'{sup_log}:\n{_tail(sup_log)}')
    recorded, sizes, sequences = count_recorded(store, NODE_ID)
    log_dir = SegmentStore(store, NODE_ID).dir
    log_bytes = sum(p.stat().st_size for p in log_dir.rglob('*') if p.is_file())
    run = RunResult('rory', load, _received(report_path, 'rory'), usage, tree=tree,
                    recorded=recorded, sizes=sizes, sequences=sequences,
                    log_mb=log_bytes / 1e6)
    crashes = [e for e in _events(store) if e.get('kind') in ('crash', 'hang', 'recovered')]
    run.problems = judge(run) + [f'rory: {NODE_ID}: {e["kind"]} during the run ({e})'
                                 for e in crashes]
    return run


def main(argv: list[str] | None = None) -> int:
    """Run both, print and write the report; 0 when nothing was dropped."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, default=30.0, help='load duration per run')
    parser.add_argument('--out', type=Path, default=Path('recording-out'))
    parser.add_argument('--domain', type=int, default=60, help='ROS_DOMAIN_ID for both runs')
    args = parser.parse_args(argv)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    try:
        bare = run_bare(out, args.seconds, args.domain)
        rory = run_rory(out, args.seconds, args.domain)
    except BenchError as err:
        print(f'recording_bench: {err}', file=sys.stderr)
        return 2
    text = report(bare, rory, args.seconds)
    (out / 'recording.md').write_text(text)
    (out / 'recording.json').write_text(json.dumps(_as_json(bare, rory), indent=1))
    print(text)
    return 1 if bare.problems or rory.problems else 0


def _as_json(*runs: RunResult) -> dict[str, Any]:
    def usage(u: Usage | None) -> dict[str, Any] | None:
        if u is None:
            return None
        return {'cpu_percent': u.cpu_percent, 'peak_rss_mb': u.peak_rss_mb,
                'wall_seconds': u.wall_seconds, 'peak_rss_mb_by_process': dict(u.parts)}

    return {
        run.label: {
            'load': run.load,
            'received': run.received,
            'recorded': run.recorded,
            'sequences': {t: s.describe() for t, s in run.sequences.items()},
            'node': usage(run.node),
            'all_processes': usage(run.tree),
            'log_mb': run.log_mb,
            'problems': run.problems,
        }
        for run in runs
    }


if __name__ == '__main__':
    sys.exit(main())
