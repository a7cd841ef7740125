"""What RORY adds to taking one LaserScan, in instructions: the same on a busy machine.

    python -m rory_eval.bench.instructions_bench [--configs bare,restart,checkpoint]
        [--counts 50,250] [--rate 10] [--domain 88] [--out DIR]

``message_cost_bench`` measures the node process's CPU time per message; it needs a quiet
machine and moves by tens of microseconds from run to run. This bench counts instructions
instead, with valgrind's callgrind, and those do not depend on what else the machine does.
``examples/scan_sink``'s node runs under ``valgrind --tool=callgrind`` (``--trace-children``:
the venv's python re-executes itself) until it has taken N LaserScans, sent at ``--rate`` Hz (a
low rate: under valgrind the node is ~50x slower and must take each scan on its own wake-up),
then shuts down cleanly (callgrind writes its counts at a clean exit). Twice, N1 and N2 scans
(``--counts``): instructions per message = (total(N2) - total(N1)) / (N2 - N1), so start-up
and shut-down cancel out. What is left includes what the process does per second (DDS's
announcements, RORY's heartbeat thread, checkpoints), amortised over ``--rate`` messages.

Configurations: ``bare`` (the node as written) and the runtime standalone, with the
environment the supervisor would give it and no supervisor: ``restart`` and ``checkpoint``
release themselves; ``rory`` (the log written ahead, checkpoints; not in the default set) is
sent the RELEASE a supervisor sends at a fresh start by a helper process on its shadow topic.
Without the supervisor's socket statuses are dropped; its ring and standby are other processes.
bare, restart and checkpoint repeat within 1 %; rory did not (1.80 and 1.97 M in two runs):
how often its executor wakes per message depends on how its threads are scheduled, so the
table gives the executor's waits per message (calls of ``rcl_wait``) beside the counts.

Each thread is counted on its own (``--separate-threads``), and two whose counts follow wall
time, not the work, are left out (``IDLE_THREADS``): numpy's OpenBLAS idle thread
(``blas_thread_server``) and Fast DDS's flow controller thread. Prints a Markdown table, then
per configuration the ten functions (self cost, ``callgrind_annotate``) that add the most
instructions per message against bare, recursion levels merged.
"""

from __future__ import annotations

import argparse
import json
import re
import secrets
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from rory_eval.bench.light_node_bench import plain_env
from rory_eval.bench.message_cost_bench import PUBLISHER, SINK
from rory_eval.harness.scenario import stop_process
from rory_eval.harness.simrun import exit_on_sigterm
from rory_runtime import protocol

CONFIGS = ('bare', 'restart', 'checkpoint', 'rory')
DEFAULT_CONFIGS = ('bare', 'restart', 'checkpoint')
# Threads whose counts follow wall time, not the messages, known by the function they run:
# numpy's OpenBLAS idle thread spins for as long as the process lives; Fast DDS's flow
# controller's thread sends what a writer could not send at once (a sink sends nothing per
# message), and its locking loop ran 14 M instructions more in one run of 250 scans than in
# another (2026-11-28).
IDLE_THREADS = re.compile(
    r'blas_thread_server|eprosima::fastdds::rtps::FlowControllerImpl<.*>::run\(\)')
TOP = 10

# The node under callgrind: scan_sink's ScanSink, under the runtime when RORY_NODE is set (as
# the instrumenter's decorator would put it), spun until it has taken argv[1] scans, then shut
# down cleanly. Argument: the number of scans.
NODE = r'''
import os, sys
sys.path.insert(0, os.environ['SCAN_SINK_DIR'])
import rclpy
from rclpy.executors import SingleThreadedExecutor
import scan_sink
count = int(sys.argv[1])
cls = scan_sink.ScanSink
if os.environ.get('RORY_NODE'):
    from rory_runtime.node import patching
    cls = patching.checkpointed(vars=('count', 'last_stamp'), manifest='sha256:0')(cls)
rclpy.init()
node = cls()
executor = SingleThreadedExecutor()
executor.add_node(node)
while node.count < count:
    executor.spin_once()
print('done', node.count, flush=True)
executor.shutdown()
node.destroy_node()
rclpy.shutdown()
'''

# For ``rory``: what a supervisor sends a node at a fresh start once its ring is armed, RELEASE
# (incarnation 1, log from segment 1), signed, on the node's shadow topic. Says 'released' once
# the node's reader has it (the scans start after that: none wait for the release), then waits
# to be stopped.
RELEASER = r'''
import os, signal, sys, time, rclpy
signal.signal(signal.SIGINT, signal.SIG_DFL)
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import UInt8MultiArray
from rory_runtime import protocol
rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
node = rclpy.create_node('rory_releaser')
writer = node.create_publisher(
    UInt8MultiArray, protocol.replay_topic(os.environ[protocol.ENV_NODE], 1), protocol.REPLAY_QOS)
while writer.get_subscription_count() < 1:
    time.sleep(0.05)
shadow = protocol.SignedPublisher(writer, bytes.fromhex(os.environ[protocol.ENV_SECRET]))
shadow.publish(protocol.pack_release(1, 1, 0))
if not writer.wait_for_all_acked(rclpy.duration.Duration(seconds=60.0)):
    sys.exit('the node never took RELEASE')
print('released', flush=True)
signal.pause()
'''

# A line of ``callgrind_annotate`` output: count, percentage, file:function, [object].
_LINE = re.compile(r'^\s*([\d,]+)\s+(?:\(\s*[\d.]+%\)\s+)?(.+?)(?:\s+\[([^\[\]]*)\])?\s*$')
_RECURSION = re.compile(r"'\d+$")  # callgrind's recursion level: f'2


@dataclass(frozen=True)
class Profile:
    """One run's instructions: in all, and each function's own (self cost)."""

    total: float
    functions: dict[str, float]  # function -> its self cost
    where: dict[str, str]  # function -> its source file's name, else its object's
    waits: float = 0.0  # the executor's waits for work (calls of rcl_wait)


def parse_annotate(text: str) -> Profile:
    """Read ``callgrind_annotate --inclusive=no --threshold=100`` output: the program's total and
    each function's self cost. A function's recursion levels (``f'2``) and the files it was
    inlined from are added into one (its name); where it is, is taken from its largest line."""
    total: float | None = None
    functions: dict[str, float] = {}
    where: dict[str, str] = {}
    for line in text.splitlines():
        match = _LINE.match(line)
        if match is None:
            continue
        count = float(match.group(1).replace(',', ''))
        if match.group(2) == 'PROGRAM TOTALS':
            total = count
            continue
        if total is None:
            continue  # (nothing before the totals is a function)
        # file:function; a file has no ':', a C++ function may.
        file, _, function = match.group(2).partition(':')
        function = _RECURSION.sub('', function)
        if function not in where:
            where[function] = Path(file if file != '???' else match.group(3) or '?').name
        functions[function] = functions.get(function, 0.0) + count
    if total is None:
        raise ValueError('no PROGRAM TOTALS line: not callgrind_annotate output')
    return Profile(total, functions, where)


def calls_to(text: str, function: str) -> int:
    """How many times ``function`` was called, from a callgrind output file's text (its
    ``cfn=`` and ``calls=`` lines; names compressed to ``(id)`` after their first use)."""
    names: dict[str, str] = {}
    callee = ''
    calls = 0
    for line in text.splitlines():
        if line.startswith(('fn=', 'cfn=')):
            ident, _, name = line.split('=', 1)[1].partition(' ')
            if not ident.startswith('('):  # (not compressed)
                ident, name = '', line.split('=', 1)[1]
            elif name:
                names[ident] = name
            else:
                name = names.get(ident, '')
            if line.startswith('cfn='):
                callee = _RECURSION.sub('', name)
        elif line.startswith('calls=') and callee == function:
            calls += int(line[len('calls='):].split()[0])
    return calls


def idle_thread(profile: Profile) -> bool:
    """Whether a thread's profile is one of an idle loop (:data:`IDLE_THREADS`)."""
    return any(IDLE_THREADS.fullmatch(function) for function in profile.functions)


def combined(profiles: Iterable[Profile]) -> Profile:
    """The threads and processes of one run added up (a child such as ``ldconfig -p``)."""
    total = waits = 0.0
    functions: dict[str, float] = {}
    where: dict[str, str] = {}
    for profile in profiles:
        total += profile.total
        waits += profile.waits
        for function, count in profile.functions.items():
            functions[function] = functions.get(function, 0.0) + count
        where = {**profile.where, **where}
    return Profile(total, functions, where, waits)


def per_message(small: Profile, large: Profile, n_small: int, n_large: int) -> Profile:
    """Instructions per message: (large - small) / (n_large - n_small), per function too."""
    if n_large <= n_small:
        raise ValueError('the second run must take more messages than the first')
    span = n_large - n_small
    names = small.functions.keys() | large.functions.keys()
    return Profile((large.total - small.total) / span,
                   {f: (large.functions.get(f, 0.0) - small.functions.get(f, 0.0)) / span
                    for f in names},
                   {**small.where, **large.where}, (large.waits - small.waits) / span)


def top_added(config: Profile, bare: Profile, top: int = TOP) -> list[tuple[str, float]]:
    """The functions that add the most per message against bare, most first."""
    names = config.functions.keys() | bare.functions.keys()
    added = {f: config.functions.get(f, 0.0) - bare.functions.get(f, 0.0) for f in names}
    return sorted(added.items(), key=lambda item: (-item[1], item[0]))[:top]


def _annotate(out_file: Path) -> Profile:
    """A thread's profile: callgrind_annotate's self costs, and the executor's waits."""
    result = subprocess.run(['callgrind_annotate', '--inclusive=no', '--threshold=100',
                             '--auto=no', str(out_file)], capture_output=True, text=True,
                            check=True, cwd='/')  # (annotate drops the cwd from file names)
    waits = calls_to(out_file.read_text(errors='replace'), 'rcl_wait')
    return replace(parse_annotate(result.stdout), waits=waits)


def _node_env(config: str, domain: int, workdir: Path) -> dict[str, str]:
    """A user's shell on this run's domain; for a RORY method, what the supervisor would set."""
    env = plain_env(domain)
    env['SCAN_SINK_DIR'] = str(SINK)
    if config != 'bare':
        env.update({protocol.ENV_NODE: 'scan_sink', protocol.ENV_STORE: str(workdir / 'store'),
                    protocol.ENV_INCARNATION: '1', protocol.ENV_METHOD: config,
                    protocol.ENV_MODE: protocol.Mode.FRESH.value,
                    protocol.ENV_SECRET: secrets.token_hex(32)})
    return env


def run_once(config: str, count: int, workdir: Path, domain: int, rate: float) -> Profile:
    """The node under callgrind until it took ``count`` scans: its threads and processes added
    up, the idle threads left out."""
    workdir.mkdir(parents=True, exist_ok=True)
    command = ['valgrind', '--tool=callgrind', '--trace-children=yes', '--separate-threads=yes',
               f'--callgrind-out-file={workdir}/callgrind.%p.out',
               sys.executable, '-c', NODE, str(count)]
    timeout = 300.0 + 3 * count / rate  # start-up under valgrind takes ~30 s
    env = _node_env(config, domain, workdir)
    helpers: list[subprocess.Popen[bytes]] = []
    with (workdir / 'node.log').open('wb') as log:
        node = subprocess.Popen(command, env=env, cwd=workdir, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
        try:
            deadline = time.monotonic() + timeout
            if config == 'rory':
                released = workdir / 'releaser.log'
                with released.open('wb') as out:
                    helpers.append(subprocess.Popen(
                        [sys.executable, '-c', RELEASER], env=env, cwd=workdir, stdout=out,
                        stderr=subprocess.STDOUT, start_new_session=True))
                while 'released' not in released.read_text(errors='replace'):
                    if (helpers[0].poll() is not None or node.poll() is not None
                            or time.monotonic() > deadline):
                        raise RuntimeError(f'rory {count}: the node was not released; '
                                           f'see {released} and {workdir / "node.log"}')
                    time.sleep(0.2)
            helpers.append(subprocess.Popen(
                [sys.executable, '-c', PUBLISHER, str(count), str(rate), '1'],
                env=plain_env(domain), cwd=workdir, stdout=subprocess.DEVNULL,
                start_new_session=True))
            while node.poll() is None and time.monotonic() < deadline:
                time.sleep(0.5)
            if node.poll() is None:
                raise RuntimeError(f'{config} {count}: the node did not finish in {timeout:.0f} s')
        finally:
            for helper in helpers:
                stop_process(helper)
            stop_process(node)
    done = f'done {count}'
    if node.returncode != 0 or done not in (workdir / 'node.log').read_text(errors='replace'):
        raise RuntimeError(f'{config} {count}: the node failed (exit {node.returncode}); '
                           f'see {workdir / "node.log"}')
    # One file a thread (callgrind.PID.out-NN); the venv's python before it re-executed itself
    # leaves an empty callgrind.PID.out.
    threads = [_annotate(f) for f in sorted(workdir.glob('callgrind.*.out*'))
               if f.stat().st_size > 0]
    return combined(thread for thread in threads if not idle_thread(thread))


def _counts(text: str) -> tuple[int, int]:
    try:
        small, large = (int(part) for part in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError('two message counts, e.g. 50,250') from None
    if not 0 < small < large:
        raise argparse.ArgumentTypeError('two counts, the first positive and smaller')
    return small, large


def _configs(text: str) -> list[str]:
    configs = [part.strip() for part in text.split(',') if part.strip()]
    unknown = [c for c in configs if c not in CONFIGS]
    if unknown or not configs:
        raise argparse.ArgumentTypeError(f'configurations among {", ".join(CONFIGS)}')
    return configs


def report(results: dict[str, Profile], counts: tuple[int, int], rate: float) -> str:
    """The Markdown tables: per message against bare, and where each addition goes."""
    lines = ['| configuration | instructions per LaserScan | added to bare | added (%) '
             '| executor waits per scan |', '|---|---:|---:|---:|---:|']
    results = {c: results[c] for c in sorted(results, key=CONFIGS.index)}
    bare = results.get('bare')
    for config, profile in results.items():
        added = (f'{profile.total - bare.total:+,.0f} | '
                 f'{100 * (profile.total - bare.total) / bare.total:+.1f} %'
                 if bare is not None and config != 'bare' else '- | -')
        lines.append(f'| {config} | {profile.total:,.0f} | {added} | {profile.waits:.2f} |')
    lines.append(f'\nScans at {rate:g} Hz; per scan: (the run of {counts[1]} - the run of '
                 f'{counts[0]}) / {counts[1] - counts[0]}; the idle threads (OpenBLAS, Fast DDS\'s '
                 'flow controller) left out. Executor waits: calls of rcl_wait; a count that moves '
                 'between runs moves the instructions with it.')
    if bare is None:
        return '\n'.join(lines)
    for config, profile in results.items():
        if config == 'bare':
            continue
        lines += [f'\nWhere {config} adds instructions per LaserScan (self cost against bare, '
                  f'top {TOP}):\n', '| function | added |', '|---|---:|']
        where = {**bare.where, **profile.where}
        lines += [f'| `{function}` ({where.get(function, "?")}) | {added:+,.0f} |'
                  for function, added in top_added(profile, bare)]
    return '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the bench; print the tables."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.instructions_bench',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--configs', type=_configs, default=list(DEFAULT_CONFIGS),
                        help=f'comma-separated, among {",".join(CONFIGS)} '
                             f'(default: {",".join(DEFAULT_CONFIGS)})')
    parser.add_argument('--counts', type=_counts, default=(50, 250),
                        help='the two runs\' message counts (default: 50,250)')
    parser.add_argument('--rate', type=float, default=10.0, help='scans per second')
    parser.add_argument('--domain', type=int, default=88)
    parser.add_argument('--out', help='keep the runs (callgrind files) and instructions.json here')
    args = parser.parse_args(argv)
    if args.rate <= 0:
        parser.error('--rate must be positive')
    missing = [tool for tool in ('valgrind', 'callgrind_annotate') if shutil.which(tool) is None]
    if missing:
        print(f'instructions_bench: {" and ".join(missing)} not found (apt install valgrind)',
              file=sys.stderr)
        return 2
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix='rory-instructions-'))
    small, large = args.counts
    results: dict[str, Profile] = {}
    try:
        for config in args.configs:
            runs = [run_once(config, n, root / f'{config}-{n}', args.domain, args.rate)
                    for n in (small, large)]
            results[config] = per_message(runs[0], runs[1], small, large)
            print(f'{config}: {results[config].total:,.0f} instructions a message', flush=True)
        if args.out:
            (root / 'instructions.json').write_text(json.dumps(
                {config: {'per_message': p.total, 'functions': p.functions}
                 for config, p in results.items()}, indent=1))
    finally:
        if not args.out:
            shutil.rmtree(root, ignore_errors=True)
    print()
    print(report(results, args.counts, args.rate))
    return 0


if __name__ == '__main__':
    sys.exit(main())
