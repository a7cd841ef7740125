"""``make faults`` under load: the campaign's parts with busy processes on every core beside them.

A robot's computer is rarely idle, and a recovery that is exact on a quiet machine may not be
on a busy one: a heartbeat read late looks like a hang, a replacement starts slowly, the ring
falls behind. ``--load N`` starts N busy processes per core before the first run, each a tight
arithmetic loop pinned to its core (``os.sched_setaffinity``) at this campaign's own nice value,
which every process of a run inherits (the supervisor, the node, the publisher): the hogs
compete with the nodes as equals. They are reaped after the last run, also on Ctrl-C and
SIGTERM, and die with the campaign if it is SIGKILLed (``PR_SET_PDEATHSIG``). At the end the
campaign prints their pids, their CPU seconds over their wall seconds, and the load average.

Under that load it runs the parts of docs/faults.md through their own functions, with fewer
runs, and beside each part's runs with a fault, runs without one (``--no-crash``):

* part one (:mod:`.fault_campaign`): the integrator struck by every fault kind, the hang
  among them; without a fault: the integrator, never struck;
* part two (:mod:`.target_faults`): a real target in the simulator, every fault kind and a
  second strike; without a fault: the reference, and more runs compared with it byte for byte;
* part three (:mod:`.storm_campaign`): crash storms on the integrator; without a fault: the
  integrator with the storms' settings, warm and cold;
* part four (:mod:`.corpus_campaign`): every corpus node SIGKILLed; without a fault: each
  node's reference, and more runs judged against it.

What each run must show (:meth:`RunRecord.failures`):

* without a fault: exact, nothing lost, nothing applied twice, the safe state never engaged
  (no ``True`` on ``/e_stop``, no ``safe_state`` held event), no kill by the supervisor (no
  ``hang`` or ``unheard`` event), no crash (``exit``), no recovery, no give-up;
* with a fault: exact, nothing lost, nothing applied twice, no give-up; a hang struck is found
  (a ``hang`` event) with the heartbeat silent no longer than the node's ``hang_timeout`` plus
  :data:`HANG_SLACK`.

It prints one table per part and the totals, and exits 1 if any run fails (its folder kept and
named), 0 otherwise.

    python -m rory_eval.faults.load_campaign --load 2                 # ~25 min on 2 cores
    python -m rory_eval.faults.load_campaign --load 2 --parts one three four --runs 1
"""

from __future__ import annotations

import argparse
import functools
import itertools
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol

from rory_eval.faults import corpus_campaign, fault_campaign, storm_campaign, target_faults
from rory_eval.harness.process_usage import read_process
from rory_eval.harness.scenario import Kill, ScenarioResult
from rory_eval.harness.simrun import exit_on_sigterm, store_events
from rory_eval.targets import EXACT_TARGETS
from rory_runtime.supervisor.config import NodeConfig

PARTS = ('one', 'two', 'three', 'four')
"""The parts of docs/faults.md, by the numbers it gives them."""

MODULES = {'one': 'fault_campaign', 'two': 'target_faults', 'three': 'storm_campaign',
           'four': 'corpus_campaign'}

HANG_SLACK = 0.5
"""Seconds a hang may be found after its node's ``hang_timeout``: the supervisor looks at the
heartbeat on each tick (0.02-0.25 s apart) and the node beats every 0.2 s."""

NO_CRASH = 'no fault'
_CLK_TCK = float(os.sysconf('SC_CLK_TCK'))

HOG_PROGRAM = '''
import ctypes, os, signal, sys
ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
if os.getppid() != int(sys.argv[1]):
    sys.exit(0)  # the campaign is already gone
x = 1
while True:
    x = (x * 7 + 3) % 1000003
'''
"""A hog: pure CPU, no memory, no I/O; SIGKILLed by the kernel when the campaign ends however
it ends (argv[1]: the campaign's pid)."""


class _Process(Protocol):
    """What the load needs of a hog's process (subprocess.Popen; a fake in the tests)."""

    @property
    def pid(self) -> int: ...

    def poll(self) -> int | None: ...

    def kill(self) -> None: ...

    def wait(self, timeout: float | None = None) -> int: ...


def spawn_hog() -> subprocess.Popen[bytes]:
    """One busy process, in a session of its own (a Ctrl-C at the terminal is the campaign's
    to handle: it reaps the hogs)."""
    return subprocess.Popen([sys.executable, '-c', HOG_PROGRAM, str(os.getpid())],
                            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)


def cpu_seconds(pid: int) -> float | None:
    """pid's CPU seconds (user + system) so far; None if it is gone."""
    reading = read_process(pid)
    return None if reading is None else reading.own_ticks / _CLK_TCK


def nice_of(pid: int) -> int:
    """pid's nice value."""
    return os.getpriority(os.PRIO_PROCESS, pid)


@dataclass
class Hog:
    """One busy process and what it used."""

    process: _Process
    core: int
    started: float  # the load's clock
    nice: int | None = None
    cpu_s: float | None = None  # measured just before it was killed
    wall_s: float | None = None
    died_early: bool = False  # it had ended before the load was taken off

    @property
    def pid(self) -> int:
        """Its pid."""
        return self.process.pid

    @property
    def share(self) -> float | None:
        """CPU seconds over wall seconds: 1.0 is a whole core."""
        if self.cpu_s is None or not self.wall_s:
            return None
        return self.cpu_s / self.wall_s


class Load:
    """``per_core`` hogs on each of ``cores`` (default: the cores this process may run on),
    each pinned to its core at this process's nice value; a context manager that takes them
    all off (SIGKILL, reaped) on the way out, however it is left.

    ``spawn``, ``pin``, ``nice``, ``cpu``, ``clock`` and ``loadavg`` are the operating
    system's unless a test gives fakes. The 1-minute load average is sampled every
    ``sample_every`` seconds while the hogs run.
    """

    def __init__(self, per_core: int, cores: Iterable[int] | None = None, *,
                 spawn: Callable[[], _Process] = spawn_hog,
                 pin: Callable[[int, set[int]], None] = os.sched_setaffinity,
                 nice: Callable[[int], int] = nice_of,
                 cpu: Callable[[int], float | None] = cpu_seconds,
                 clock: Callable[[], float] = time.monotonic,
                 loadavg: Callable[[], tuple[float, float, float]] = os.getloadavg,
                 sample_every: float = 5.0) -> None:
        self.per_core = per_core
        self.cores = sorted(os.sched_getaffinity(0) if cores is None else cores)
        self.own_nice = nice(os.getpid())
        self.hogs: list[Hog] = []
        self.load_samples: list[float] = []  # 1-minute load averages while the hogs ran
        self.load_at_end: tuple[float, float, float] | None = None
        self.started = 0.0
        self.ended: float | None = None
        self._spawn, self._pin, self._nice, self._cpu = spawn, pin, nice, cpu
        self._clock, self._loadavg, self._sample_every = clock, loadavg, sample_every
        self._sampling = threading.Event()
        self._sampler: threading.Thread | None = None

    def __enter__(self) -> Load:
        self.started = self._clock()
        try:
            for core in self.cores:
                for _ in range(self.per_core):
                    hog = Hog(self._spawn(), core, self._clock())
                    self.hogs.append(hog)  # before anything else can fail: it is reaped
                    self._pin(hog.pid, {core})
                    hog.nice = self._nice(hog.pid)
        except BaseException:
            self.stop()
            raise
        self._sampler = threading.Thread(target=self._sample, name='loadavg', daemon=True)
        self._sampler.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    def _sample(self) -> None:
        while not self._sampling.wait(self._sample_every):
            self.load_samples.append(self._loadavg()[0])

    def stop(self) -> None:
        """Take every hog off: its CPU seconds read, then SIGKILL, then reaped (idempotent)."""
        self._sampling.set()
        if self._sampler is not None:
            self._sampler.join(timeout=2.0)
        if self.ended is None:
            self.load_at_end = self._loadavg()
        for hog in self.hogs:
            if hog.wall_s is not None:
                continue
            hog.died_early = hog.process.poll() is not None
            hog.cpu_s = self._cpu(hog.pid)
            hog.wall_s = self._clock() - hog.started
            if not hog.died_early:
                hog.process.kill()
            hog.process.wait()
        if self.ended is None:
            self.ended = self._clock()

    def describe(self) -> str:
        """One line: how many hogs, where, at which nice value, their pids."""
        cores = ', '.join(str(c) for c in self.cores)
        nices = sorted({h.nice for h in self.hogs if h.nice is not None})
        return (f'load: {len(self.hogs)} busy processes, {self.per_core} per core on cores '
                f'{cores}, each pinned to its core, nice {", ".join(map(str, nices)) or "-"} '
                f'(this campaign: {self.own_nice}); pids '
                f'{" ".join(str(h.pid) for h in self.hogs) or "-"}')

    def report(self) -> str:
        """Per hog its pid, core, nice value, CPU and wall seconds; in all, the share of the
        machine they took, and the load average."""
        lines = ['| hog pid | core | nice | CPU s | wall s | CPU share |',
                 '|---:|---:|---:|---:|---:|---:|']
        for h in self.hogs:
            share = '-' if h.share is None else f'{h.share:.0%}'
            lines.append(f'| {h.pid} | {h.core} | {h.nice} | {_num(h.cpu_s, 1)} '
                         f'| {_num(h.wall_s, 1)} | {share}'
                         f'{" (had died)" if h.died_early else ""} |')
        cpu = sum(h.cpu_s or 0.0 for h in self.hogs)
        wall = (self.ended or self._clock()) - self.started
        lines.append('')
        if self.hogs and wall > 0:
            lines.append(f'The {len(self.hogs)} hogs used {cpu:.0f} CPU s in {wall:.0f} s on '
                         f'{len(self.cores)} cores: {cpu / wall:.2f} cores, '
                         f'{cpu / (wall * len(self.cores)):.0%} of the machine.')
        if self.load_samples:
            mean = sum(self.load_samples) / len(self.load_samples)
            lines.append(f'Load average (1 min) while they ran: mean {mean:.2f}, max '
                         f'{max(self.load_samples):.2f} ({len(self.load_samples)} samples).')
        if self.load_at_end is not None:
            one, five, fifteen = self.load_at_end
            lines.append(f'Load average at the end (1, 5, 15 min): {one:.2f}, {five:.2f}, '
                         f'{fifteen:.2f}.')
        return '\n'.join(lines)


def _num(value: float | None, digits: int) -> str:
    return '-' if value is None else f'{value:.{digits}f}'


@dataclass
class RunRecord:
    """What one run under load showed."""

    part: str
    kind: str  # its row: NO_CRASH, a fault kind, a group of strikes
    label: str
    folder: Path
    struck: bool
    exact: bool = False
    lost: int | None = None  # None: the part cannot count them
    twice: int | None = None
    differing: int | None = None  # outputs differing from the reference (part two)
    safe_state: int | None = 0  # engagements; None: no safe state in the run (part two)
    kills: int = 0  # the supervisor's kills: hang and unheard events
    exits: int = 0  # processes that ended during the run (crashes, kills)
    recoveries: int = 0
    give_ups: int = 0
    hang_strikes: int = 0  # hangs delivered
    hang_stalls: list[float] = field(default_factory=list)  # silence before each hang found
    hang_limit: float | None = None  # the node's hang_timeout
    problems: list[str] = field(default_factory=list)  # the part's judge
    error: str = ''  # the run did not run

    def failures(self) -> list[str]:
        """Why the run fails its acceptance (nothing: it passes)."""
        why = [self.error] if self.error else []
        if not self.exact and not self.error:
            why.append('not exact' + (f' ({"; ".join(self.problems)})' if self.problems else ''))
        for count, what in ((self.lost, 'lost'), (self.twice, 'applied twice'),
                            (self.differing, 'outputs differing'), (self.give_ups, 'give-ups')):
            if count:
                why.append(f'{count} {what}')
        if self.hang_strikes and not self.hang_stalls and not self.error:
            why.append(f'{self.hang_strikes} hang struck, none found')
        if self.hang_limit is not None:
            late = [s for s in self.hang_stalls if s > self.hang_limit + HANG_SLACK]
            if late:
                why.append(f'a hang found after {max(late):.2f} s of silence '
                           f'(hang_timeout {self.hang_limit:g} s)')
        if not self.struck:
            for count, what in ((self.safe_state, 'safe-state engagements'),
                                (self.kills, 'kills'), (self.exits, 'crashes'),
                                (self.recoveries, 'recoveries')):
                if count:
                    why.append(f'{count} {what} without a fault')
        return why


@dataclass(frozen=True)
class EventCounts:
    """What a supervisor's events.jsonl says happened in a run."""

    kills: int
    exits: int
    recoveries: int
    held: int  # safe state held
    give_ups: int
    hang_stalls: tuple[float, ...]  # stalled_s of each hang found on the heartbeat


def count_events(events: Sequence[dict[str, Any]]) -> EventCounts:
    """Count the kinds that matter here in a run's supervisor events."""
    def n(kind: str, **fields: Any) -> int:
        return sum(1 for e in events
                   if e['kind'] == kind and all(e.get(k) == v for k, v in fields.items()))

    return EventCounts(
        kills=n('hang') + n('unheard'), exits=n('exit'), recoveries=n('recovered'),
        held=n('safe_state', what='held'), give_ups=n('state', new='FATAL'),
        hang_stalls=tuple(float(e['stalled_s']) for e in events
                          if e['kind'] == 'hang' and e.get('waiting_for') == 'heartbeat'))


def with_events(record: RunRecord, events: Sequence[dict[str, Any]],
                e_stop: Sequence[tuple[float, bool]] | None = None) -> RunRecord:
    """``record`` with its events counted; ``e_stop``: what an observer heard on /e_stop
    (None: the run has no safe state)."""
    counts = count_events(events)
    record.kills, record.exits, record.recoveries = counts.kills, counts.exits, counts.recoveries
    record.give_ups = counts.give_ups
    record.hang_stalls = list(counts.hang_stalls)
    if e_stop is None:
        record.safe_state = counts.held or None
    else:
        record.safe_state = max(sum(1 for _, on in e_stop if on), counts.held)
    return record


def from_scenario(record: RunRecord, result: ScenarioResult) -> RunRecord:
    """``record`` (parts one, three, four) with what the scenario saw: events, /e_stop, the
    hangs it struck."""
    record.hang_strikes = sum(1 for what, _ in result.kills if what.startswith('hang '))
    return with_events(record, result.events, result.e_stop)


@dataclass(frozen=True)
class Options:
    """How much of each part to run."""

    no_crash: int = 2  # runs without a fault per program
    runs: int = 2  # part one: runs per fault kind (every second one struck twice)
    storms: int = 4  # part three: schedules
    kills: int = 1  # part four: kills per corpus node
    nodes: tuple[str, ...] = ()  # part four: only these (all if empty)
    targets: tuple[str, ...] = ('amcl',)  # part two
    worlds: tuple[str, ...] = ('office_small',)
    seed: int = 35


Part = Callable[[Options, Path, int], Iterator[RunRecord]]
"""A part: its options, its folder and ROS domain -> its runs, one by one."""


def attempt(record: RunRecord, body: Callable[[RunRecord], RunRecord]) -> RunRecord:
    """``body(record)``; a run that failed to run (the harness timed out, the node never
    started) is a failed run, with the first line of why."""
    try:
        return body(record)
    except Exception as err:
        text = str(err).strip().splitlines()
        record.error = f'did not run: {type(err).__name__}: {text[0] if text else ""}'
        return record


def part_one(options: Options, root: Path, domain: int) -> Iterator[RunRecord]:
    """The integrator, never struck, then struck by every fault kind (fault_campaign.plan)."""
    limit = dict(fault_campaign.FLAKY.settings)['hang_timeout']

    def no_crash(record: RunRecord) -> RunRecord:
        result = fault_campaign.scenario((), record.folder, domain)
        record.exact, record.lost, record.twice = result.correct, result.lost, result.duplicated
        return from_scenario(record, result)

    for i in range(options.no_crash):
        yield attempt(RunRecord('one', NO_CRASH, 'integrator, no fault', root / f'no-fault{i}',
                                False, hang_limit=limit), no_crash)

    for i, case in enumerate(fault_campaign.plan(options.runs, options.seed)):
        def struck(record: RunRecord, case: fault_campaign.Case = case) -> RunRecord:
            result = fault_campaign.scenario(case.kills(), record.folder, domain)
            outcome = fault_campaign.judge(case, result)
            record.exact, record.lost = outcome.correct, outcome.lost
            record.twice = outcome.duplicated
            if outcome.missing:
                record.problems.append(f'missing {outcome.missing}')
            return from_scenario(record, result)

        yield attempt(RunRecord('one', case.fault, case.label(), root / f'run{i:03d}', True,
                                hang_limit=limit), struck)


def compare_no_crash(reference: dict[int, bytes], again: dict[int, bytes]) -> tuple[int, int]:
    """A run without a fault against the reference: (missing, differing) - the reference's
    outputs up to the run's last one that it lacks, and its outputs up to the reference's last
    one that the reference lacks or has otherwise (the stop may cut the two ends apart)."""
    if not again:
        return len(reference), 0
    end, ref_end = max(again), max(reference, default=0)
    missing = sum(1 for s in reference if s <= end and s not in again)
    differing = sum(1 for s, data in again.items() if s <= ref_end and reference.get(s) != data)
    return missing, differing


def part_two(options: Options, root: Path, domain: int) -> Iterator[RunRecord]:
    """Per target x world: the reference and more runs without a fault compared with it, then
    target_faults.plan's cases (every fault kind and a second strike) judged against it."""
    cases = target_faults.plan(options.targets, options.worlds, options.seed)
    for name, world in itertools.product(options.targets, options.worlds):
        yield from _target_runs(options, name, world, root, domain,
                                [c for c in cases if (c.target, c.world) == (name, world)])


def _target_runs(options: Options, name: str, world: str, root: Path, domain: int,
                 cases: Sequence[target_faults.Case]) -> Iterator[RunRecord]:
    target = EXACT_TARGETS[name]
    base = root / name / world
    inst = (root / name / 'inst').resolve()
    limit = target_faults.HANG_TIMEOUT
    reference: dict[int, bytes] = {}

    def first(record: RunRecord) -> RunRecord:
        outputs, events, _ = target_faults.run_target(target, world, record.folder,
                                                      domain_id=domain, instrumented=inst)
        reference.update(outputs)
        record.exact = bool(outputs)
        if not outputs:
            record.problems.append('no outputs')
        return with_events(record, events)

    def again(record: RunRecord) -> RunRecord:
        outputs, events, _ = target_faults.run_target(target, world, record.folder,
                                                      domain_id=domain, instrumented=inst)
        missing, differing = compare_no_crash(reference, outputs)
        record.lost, record.differing = missing, differing
        record.exact = bool(outputs) and not missing and not differing
        return with_events(record, events)

    def struck(record: RunRecord, case: target_faults.Case) -> RunRecord:
        outcome = target_faults.run_case(case, reference, record.folder, domain_id=domain,
                                         instrumented=inst)
        record.exact = outcome.correct
        c = outcome.comparison
        record.lost = (0 if c is None else c.missing_after_release) + outcome.input_gaps
        record.differing = outcome.differing
        if not outcome.correct:
            record.problems.append(outcome.error or str(c))
        faults = [case.fault] + ([case.second[0]] if case.second else [])
        record.hang_strikes = faults[:outcome.strikes].count('hang')
        return with_events(record, store_events(record.folder / 'store'))

    yield attempt(RunRecord('two', NO_CRASH, f'{name}/{world}: reference', base / 'ref', False,
                            hang_limit=limit), first)
    if not reference:
        return  # nothing to judge the others against: the reference's failure says why
    for i in range(1, options.no_crash):
        yield attempt(RunRecord('two', NO_CRASH, f'{name}/{world}: no fault',
                                base / f'no-fault{i}', False, hang_limit=limit), again)
    for k, case in enumerate(cases):
        kind = case.fault if case.second is None else 'second strike during recovery'
        yield attempt(RunRecord('two', kind, case.label(), base / f'case{k}', True,
                                hang_limit=limit), functools.partial(struck, case=case))


def part_three(options: Options, root: Path, domain: int) -> Iterator[RunRecord]:
    """The integrator with the storms' settings, never struck (warm and cold), then
    storm_campaign.campaign's schedules."""
    limit = dict(fault_campaign.FLAKY.settings)['hang_timeout']
    for i in range(options.no_crash):
        schedule = storm_campaign.Schedule((), 'fast', warm=i % 2 == 0)

        def no_crash(record: RunRecord,
                     schedule: storm_campaign.Schedule = schedule) -> RunRecord:
            result = storm_campaign.scenario(schedule, record.folder, domain)
            record.exact, record.lost = result.correct, result.lost
            record.twice = result.duplicated
            return from_scenario(record, result)

        yield attempt(RunRecord('three', NO_CRASH, f'integrator, no fault, {schedule.label()}',
                                root / f'no-fault{i}', False, hang_limit=limit), no_crash)

    for i, schedule in enumerate(storm_campaign.campaign(options.storms, options.seed)):
        def struck(record: RunRecord,
                   schedule: storm_campaign.Schedule = schedule) -> RunRecord:
            result = storm_campaign.scenario(schedule, record.folder, domain)
            outcome = storm_campaign.judge(schedule, result)
            record.exact, record.lost = outcome.correct, outcome.lost
            record.twice = outcome.duplicated
            if outcome.quarantined:
                record.label += f' ({len(outcome.quarantined)} quarantined as poison)'
            if not outcome.correct:
                record.problems.append(storm_campaign.describe(outcome))
            return from_scenario(record, result)

        n = len(schedule.strikes)
        yield attempt(RunRecord('three', f'{n} strike{"s" if n > 1 else ""}', schedule.label(),
                                root / f'run{i:03d}', True, hang_limit=limit), struck)


def part_four(options: Options, root: Path, domain: int) -> Iterator[RunRecord]:
    """Per corpus node: its reference and more runs without a fault judged against it, then
    SIGKILLs at corpus_campaign.kill_times."""
    for node in corpus_campaign.NODES:
        if not options.nodes or node.name in options.nodes:
            times = iter(corpus_campaign.kill_times(options.seed, node.name, options.kills))
            yield from _corpus_runs(options, node, root / node.name, domain, times)


def _corpus_runs(options: Options, node: corpus_campaign.CorpusNode, folder: Path, domain: int,
                 times: Iterator[float]) -> Iterator[RunRecord]:
    limit = NodeConfig.hang_timeout  # the corpus runs with the default
    reference: list[Any] = []  # the reference's final state, once it has run

    def judged(record: RunRecord, kills: tuple[Kill, ...]) -> RunRecord:
        result = corpus_campaign.run_node(node, kills, record.folder, domain)
        record.problems = corpus_campaign.judge_run(
            node, reference[0] if reference else None, result)
        record.exact = not record.problems
        if not reference and not kills:
            reference.append(result.state)
        return from_scenario(record, result)

    for i in range(options.no_crash):
        what = 'reference' if i == 0 else 'no fault'
        yield attempt(RunRecord('four', NO_CRASH, f'{node.name}: {what}', folder / f'no-fault{i}',
                                False, hang_limit=limit), functools.partial(judged, kills=()))
    for k in range(options.kills):
        at = next(times)
        yield attempt(RunRecord('four', 'SIGKILL', f'{node.name}: SIGKILL at {at:.2f} s',
                                folder / f'kill{k}', True, hang_limit=limit),
                      functools.partial(judged, kills=(Kill(after=at),)))


PART_RUNNERS: dict[str, Part] = {'one': part_one, 'two': part_two, 'three': part_three,
                                 'four': part_four}


COLUMNS = ('runs', 'accepted', 'exact', 'lost', 'applied twice', 'outputs differing',
           'safe state engaged', 'hangs struck', 'hangs found (longest silence)',
           'kills (hang, unheard)', 'crashes (exit)', 'recoveries', 'give-ups')


def _sum(values: Iterable[int | None]) -> str:
    known = [v for v in values if v is not None]
    return str(sum(known)) if known else '-'


def row(name: str, records: Sequence[RunRecord]) -> str:
    """One Markdown row over ``records``."""
    stalls = [s for r in records for s in r.hang_stalls]
    limits = sorted({r.hang_limit for r in records if r.hang_limit is not None and r.hang_stalls})
    found = str(len(stalls)) if not stalls else (
        f'{len(stalls)} ({max(stalls):.2f} s; limit '
        f'{", ".join(f"{x:g}" for x in limits)} s)')
    cells = [len(records), sum(not r.failures() for r in records),
             sum(r.exact and not r.error for r in records), _sum(r.lost for r in records),
             _sum(r.twice for r in records), _sum(r.differing for r in records),
             _sum(r.safe_state for r in records), sum(r.hang_strikes for r in records), found,
             sum(r.kills for r in records), sum(r.exits for r in records),
             sum(r.recoveries for r in records), sum(r.give_ups for r in records)]
    return f'| {name} | ' + ' | '.join(str(c) for c in cells) + ' |'


def header(first: str) -> list[str]:
    """The table's header, its first column named ``first``."""
    return [f'| {first} | ' + ' | '.join(COLUMNS) + ' |',
            '|---|' + '---:|' * len(COLUMNS)]


def table(records: Sequence[RunRecord], part: str = '') -> str:
    """One part's table: runs without a fault first, then each kind of run with one, then
    all."""
    kinds = list(dict.fromkeys(r.kind for r in records if r.struck))
    lines = header(f'part {part}' if part else 'runs')
    plain = [r for r in records if not r.struck]
    if plain:
        lines.append(row('without a fault', plain))
    lines += [row(kind, [r for r in records if r.struck and r.kind == kind]) for kind in kinds]
    struck = [r for r in records if r.struck]
    if struck and len(kinds) > 1:
        lines.append(row('with a fault, all', struck))
    lines.append(row('**all**', records))
    return '\n'.join(lines)


def totals(records: Sequence[RunRecord]) -> str:
    """Every part together: without a fault, with one, all."""
    lines = header('all parts')
    lines.append(row('without a fault', [r for r in records if not r.struck]))
    lines.append(row('with a fault', [r for r in records if r.struck]))
    lines.append(row('**all**', records))
    return '\n'.join(lines)


def _positive(minimum: int) -> Callable[[str], int]:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not a whole number') from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f'{value} is less than {minimum}')
        return value

    return parse


def parser() -> argparse.ArgumentParser:
    """The command line."""
    p = argparse.ArgumentParser(prog='python -m rory_eval.faults.load_campaign',
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--load', type=_positive(0), required=True, metavar='N',
                   help='busy processes per core (0: none, a control run)')
    p.add_argument('--parts', nargs='+', choices=PARTS, default=list(PARTS),
                   help='parts of docs/faults.md to run: one (fault_campaign), two '
                        '(target_faults), three (storm_campaign), four (corpus_campaign); '
                        'default: all')
    p.add_argument('--no-crash', type=_positive(1), default=Options.no_crash, metavar='N',
                   help='runs without a fault per program (part two and four: the reference '
                        'and N-1 more)')
    p.add_argument('--runs', type=_positive(1), default=Options.runs, metavar='N',
                   help='part one: runs per fault kind, every second one struck twice')
    p.add_argument('--storms', type=_positive(1), default=Options.storms, metavar='N',
                   help='part three: storm schedules')
    p.add_argument('--kills', type=_positive(1), default=Options.kills, metavar='N',
                   help='part four: kills per corpus node')
    p.add_argument('--nodes', nargs='+', choices=[n.name for n in corpus_campaign.NODES],
                   help='part four: only these corpus nodes')
    p.add_argument('--targets', nargs='+', choices=sorted(EXACT_TARGETS),
                   default=list(Options.targets), help='part two: targets')
    p.add_argument('--worlds', nargs='+', choices=target_faults.WORLDS,
                   default=list(Options.worlds), help='part two: worlds')
    p.add_argument('--seed', type=int, default=Options.seed)
    p.add_argument('--domain', type=int, default=5,
                   help='ROS domain of part one; parts two to four take the next three')
    p.add_argument('--out', type=Path,
                   help='keep every run here (default: a temporary folder, where only the '
                        'runs that fail are kept)')
    return p


def main(argv: Sequence[str] | None = None, *, parts: Mapping[str, Part] | None = None,
         load: Callable[[int], Load] = Load) -> int:
    """Run the campaign under load; exit 1 unless every run passed (2: bad arguments)."""
    exit_on_sigterm()
    args = parser().parse_args(argv)
    runners = PART_RUNNERS if parts is None else parts
    options = Options(no_crash=args.no_crash, runs=args.runs, storms=args.storms,
                      kills=args.kills, nodes=tuple(args.nodes or ()),
                      targets=tuple(args.targets), worlds=tuple(args.worlds), seed=args.seed)
    root = args.out if args.out else Path(tempfile.mkdtemp(prefix='rory-load-'))
    chosen = [p for p in PARTS if p in args.parts]
    records: dict[str, list[RunRecord]] = {p: [] for p in chosen}
    broken: list[str] = []
    started = time.monotonic()
    with load(args.load) as hogs:
        print(hogs.describe(), flush=True)
        for name in chosen:
            print(f'\npart {name} ({MODULES[name]}), under load:', flush=True)
            try:
                for record in runners[name](options, root / name, args.domain +
                                            PARTS.index(name)):
                    records[name].append(record)
                    why = record.failures()
                    print(f'  [{len(records[name])}] {record.label}: '
                          f'{"; ".join(why) + f" -> {record.folder}" if why else "ok"}',
                          flush=True)
                    if not why and not args.out:
                        shutil.rmtree(record.folder, ignore_errors=True)
            except Exception as err:
                traceback.print_exc()
                broken.append(f'part {name} stopped: {type(err).__name__}: {err}')
    minutes = (time.monotonic() - started) / 60
    every = [r for p in chosen for r in records[p]]
    for name in chosen:
        print(f'\nPart {name} ({MODULES[name]}), {len(records[name])} runs:\n')
        print(table(records[name], name))
    print(f'\nAll parts, {len(every)} runs in {minutes:.1f} min:\n')
    print(totals(every))
    failed = [r for r in every if r.failures()]
    if failed or broken:
        print('\nFailed:')
        for r in failed:
            print(f'- part {r.part}, {r.label}: {"; ".join(r.failures())} -> {r.folder}')
        for line in broken:
            print(f'- {line}')
    print(f'\n{hogs.describe()}\n')
    print(hogs.report())
    early = [h.pid for h in hogs.hogs if h.died_early]
    if early:
        print(f'\nThe load was not held: hogs {early} had ended before the last run.')
    ok = not failed and not broken and not early
    if ok and not args.out:
        shutil.rmtree(root, ignore_errors=True)
    elif not ok:
        print(f'\nRuns kept in {root}')
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
