"""Crash bundles: take a crash home and make it happen again on a desk.

    rory bundle STORE --node N -o crash.tar [--config supervise.yaml]
    rory reproduce crash.tar [-C DIR] [--timeout 60]

A bundle is a tar file holding what the node would recover from: the newest valid checkpoint
from which a replay reaches the message the node last died on (its newest one; an older one
kept; or, once later checkpoints have gone past a poison message, the copy the supervisor kept
when it quarantined it), every log segment after that checkpoint's cut (the node's own and the
supervisor's recovery logs), and the crash report (the node's events, with its exits, the
messages it died on and any quarantined message). With ``--config`` it also holds the node's
instrumented program (the folder of the script its command runs) and its command, so that
``rory reproduce`` needs nothing else. Quarantined messages are kept apart (``quarantine/``): in the
bundle's store they would be skipped, and the point is to apply them again.

``rory reproduce`` extracts the bundle and runs the node under ``rory supervise --resume`` on
the bundle's store, in a ROS domain of its own: the node restores the checkpoint, the
supervisor replays the messages in their recorded order, and the node dies where it died on
the robot. It reports the exit and the message being applied, and stops at that first crash.
Exit status: 0 reproduced, 1 ran without crashing, 2 bad input.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from .errors import CheckpointError, ConfigError, LogError, RoryError
from .log import SegmentStore, read_segment
from .protocol import NODE_ID_RE
from .store import Checkpoint, CheckpointStore, serialize
from .supervisor.poison import EVIDENCE_SUFFIX

FORMAT = 1
MANIFEST = 'bundle.json'


class BundleError(RoryError):
    """A bundle cannot be made or used; the message names the file, node or field."""


def _events_of(store: Path, node: str) -> list[dict[str, Any]]:
    path = store / 'events.jsonl'
    if not path.exists():
        return []
    records = []
    for line in path.read_text(encoding='utf-8', errors='replace').splitlines():
        try:
            record = json.loads(line)
        except ValueError:
            continue
        if isinstance(record, dict) and record.get('node') == node:
            records.append(record)
    return records


def _report(node: str, events: list[dict[str, Any]]) -> str:
    lines = [f'crash report of node {node}']
    for e in events:
        kind = e.get('kind')
        if kind in ('exit', 'died_on', 'quarantined', 'hang', 'unheard', 'fatal', 'error'):
            fields = {k: v for k, v in e.items() if k not in ('kind', 'node', 't')}
            when = time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(float(e.get('t', 0))))
            lines.append(f'{when} {kind}: {json.dumps(fields, sort_keys=True)}')
    return '\n'.join(lines) + '\n'


def _program(config_path: Path, node: str) -> tuple[list[str], Path, Path]:
    """(command, folder of the program, the program's path inside it) from a config."""
    from .supervisor.config import load_config

    config = load_config(config_path)
    chosen = next((n for n in config.nodes if n.name == node), None)
    if chosen is None:
        names = ', '.join(n.name for n in config.nodes)
        raise BundleError(f'{config_path}: no node {node!r} (nodes: {names})')
    command = list(chosen.command)
    script = next((a for a in command[1:] if a.endswith('.py')), None)
    if script is None:
        raise BundleError(f'{config_path}: the command of {node!r} runs no .py file: {command}')
    path = (config.folder / script).resolve()
    if not path.is_file():
        raise BundleError(f'{config_path}: {node!r} runs {script}, which is not a file')
    return command, path.parent, path


def make_bundle(store: Path, node: str, out: Path, config: Path | None = None) -> dict[str, Any]:
    """Write the bundle; its manifest.

    Raises:
        BundleError: No such store or node, no valid checkpoint, or a bad config.
    """
    if not NODE_ID_RE.fullmatch(node) or not (store / node).is_dir():
        raise BundleError(f'{store}: no node {node!r} in this store')
    events = _events_of(store, node)
    refused: list[str] = []
    source = _source(store, node, _last_death(events), refused)
    if source is None:
        raise BundleError(f'{store}/{node}: no valid checkpoint to start from'
                          + (f' ({"; ".join(refused)})' if refused else ''))
    ckpt_path, ckpt, segment_paths, note = source
    after = sorted(segment_paths)
    manifest: dict[str, Any] = {
        'format': FORMAT, 'node': node, 'made': time.time(), 'store': str(store.resolve()),
        'checkpoint': {'seq': ckpt.seq, 'cut': ckpt.cut, 'manifest': ckpt.manifest,
                       'created_ns': ckpt.created_ns},
        'segments': after, 'refused_checkpoints': refused,
        'command': None, 'program': None, 'note': note,
    }
    program = None
    if config is not None:
        command, folder, script = _program(config, node)
        program = folder
        manifest['program'] = f'code/{script.relative_to(folder)}'
        # The command with the program's path taken out, to be put back where it lands.
        manifest['command'] = ['{program}' if a.endswith('.py') and Path(a).name == script.name
                               else a for a in command[1:]]
    out.parent.mkdir(parents=True, exist_ok=True)
    with tarfile.open(out, 'w') as tar:
        # Written whole (format version 1), whether or not the store keeps its variables in
        # chunks: the bundle's store needs no chunk file.
        _add_bytes(tar, f'store/{node}/checkpoints/{ckpt.seq:010d}.ckpt', serialize(ckpt),
                   int(ckpt_path.stat().st_mtime))
        for n in after:
            tar.add(segment_paths[n], f'store/{node}/log/{n:010d}')
        quarantine = store / node / 'quarantine'
        if quarantine.is_dir():
            # The records; not the copies kept beside them (one of them may be in store/).
            tar.add(quarantine, 'quarantine', filter=lambda info: None if any(
                part.endswith(EVIDENCE_SUFFIX) for part in Path(info.name).parts) else info)
        if program is not None:
            tar.add(program, 'code', filter=lambda info: None if '__pycache__' in info.name
                    else info)
        for name, text in ((MANIFEST, json.dumps(manifest, indent=1)),
                           ('events.jsonl', ''.join(json.dumps(e) + '\n' for e in events)),
                           ('report.txt', _report(node, events))):
            _add_bytes(tar, name, text.encode(), int(time.time()))
    return manifest


def _add_bytes(tar: tarfile.TarFile, name: str, data: bytes, mtime: int) -> None:
    info = tarfile.TarInfo(name)
    info.size, info.mtime, info.mode = len(data), mtime, 0o600
    tar.addfile(info, io.BytesIO(data))


Death = tuple[str, tuple[int, int]]  # (topic, (source_ns, seq)) of the message it died on
Source = tuple[Path, Checkpoint, dict[int, Path], str | None]


def _last_death(events: list[dict[str, Any]]) -> Death | None:
    """The message the node was applying when it last died, if the events say."""
    for event in reversed(events):
        if event.get('kind') in ('died_on', 'quarantined'):
            try:
                return str(event['topic']), (int(event['source_ns']), int(event['seq']))
            except (KeyError, TypeError, ValueError):
                return None
    return None


def _holds(segments: dict[int, Path], death: Death) -> bool:
    topic, ident = death
    for path in segments.values():
        try:
            if any(e.topic == topic and e.ident == ident for e in read_segment(path)):
                return True
        except LogError:
            continue
    return False


def _store_sources(store: Path, node: str, refused: list[str]) -> list[Source]:
    """The store's valid checkpoints, newest first, each with the segments after its cut."""
    checkpoints = CheckpointStore(store, node)
    segments = SegmentStore(store, node)
    found: list[Source] = []
    try:
        paths = checkpoints.paths()
    except CheckpointError as err:
        refused.append(str(err))
        return found
    for path in paths:
        try:
            ckpt = checkpoints.load(path)
        except CheckpointError as err:
            refused.append(str(err))
            continue
        after = {n: segments.path(n) for n in segments.numbers()
                 if ckpt.cut is None or n > ckpt.cut}
        found.append((path, ckpt, after, None))
    return found


def _evidence_sources(store: Path, node: str, death: Death) -> list[Source]:
    """What the supervisor kept beside the quarantine record of the message it died on."""
    found: list[Source] = []
    for folder in sorted((store / node / 'quarantine').glob(f'*{EVIDENCE_SUFFIX}')):
        ckpts = sorted((folder / 'checkpoints').glob('*.ckpt'))
        if not ckpts:
            continue
        try:
            ckpt = CheckpointStore(store, node).load(ckpts[-1])
        except CheckpointError:
            continue
        after = {int(p.name): p for p in (folder / 'log').glob('*') if p.name.isdigit()}
        if _holds(after, death):
            found.append((ckpts[-1], ckpt, after, None))
    return found


def _source(store: Path, node: str, death: Death | None, refused: list[str]) -> Source | None:
    """The checkpoint and segments to bundle: the newest from which a replay reaches the
    message the node last died on (the store's, else the copy kept at its quarantine)."""
    candidates = _store_sources(store, node, refused)
    if death is None:
        return candidates[0] if candidates else None
    for candidate in candidates:
        if _holds(candidate[2], death):
            return candidate
    for candidate in _evidence_sources(store, node, death):
        return candidate
    if not candidates:
        return None
    path, ckpt, after, _ = candidates[0]
    return path, ckpt, after, (f'the checkpoints kept are past the message {node} died on '
                               f'({death[0]}, seq {death[1][1]}): a replay will not reach it')


def _extract(bundle: Path, into: Path) -> dict[str, Any]:
    try:
        with tarfile.open(bundle) as tar:
            tar.extractall(into, filter='data')
    except (OSError, tarfile.TarError) as err:
        raise BundleError(f'{bundle}: not a readable bundle: {err}') from None
    try:
        manifest: dict[str, Any] = json.loads((into / MANIFEST).read_text())
    except (OSError, ValueError) as err:
        raise BundleError(f'{bundle}: no valid {MANIFEST}: {err}') from None
    if manifest.get('format') != FORMAT:
        raise BundleError(f'{bundle}: bundle format {manifest.get("format")!r}, this RORY '
                          f'reads {FORMAT}')
    return manifest


def reproduce(bundle: Path, into: Path, *, timeout: float, domain: int,
              log: Path | None = None) -> int:
    """Run the bundle's node on its store until its first crash; 0 reproduced, 1 not.

    ``log``: where the supervisor's output goes (default: ``into``/supervisor.log); it stays
    after ``into`` is removed when it lies outside it.
    """
    manifest = _extract(bundle, into)
    node = str(manifest['node'])
    if manifest.get('command') is None:
        raise BundleError(f'{bundle}: holds no program; make it with rory bundle --config')
    program = into / str(manifest['program'])
    command = ['python', *(str(program) if a == '{program}' else a
                           for a in manifest['command'])]
    config = into / 'reproduce.yaml'
    config.write_text(yaml.safe_dump({
        'nodes': [{'name': node, 'command': command, 'method': 'rory', 'replay': 'paced',
                   'warm_standby': False, 'backoff': {'max_restarts': 1}}],
        'store': 'store',
    }, sort_keys=False))
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    log = into / 'supervisor.log' if log is None else log
    print(f'rory reproduce: {node} from checkpoint {manifest["checkpoint"]["seq"]}, '
          f'{len(manifest["segments"])} log segment(s) after its cut; log in {log}',
          flush=True)
    events_path = into / 'store' / 'events.jsonl'
    with log.open('wb') as out:
        sup = subprocess.Popen(
            [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config), '--resume'],
            cwd=into, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            return _watch(events_path, node, sup, timeout)
        finally:
            if sup.poll() is None:
                os.killpg(sup.pid, signal.SIGINT)
                try:
                    sup.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    os.killpg(sup.pid, signal.SIGKILL)
                    sup.wait()


# What the watcher says as the run goes, by event kind (the first of each).
_PROGRESS = {
    'spawn': 'started the node',
    'hello': 'restored the checkpoint; replaying what was logged after it',
    'recovered': 'replayed everything; watching 5 s more for a crash',
}


def _watch(events_path: Path, node: str, sup: subprocess.Popen[bytes], timeout: float) -> int:
    deadline = time.monotonic() + timeout
    settled_at: float | None = None
    said: set[str] = set()
    while time.monotonic() < deadline:
        events = _events_of(events_path.parent, node)
        for event in events:
            kind = str(event.get('kind'))
            if kind in _PROGRESS and kind not in said:
                said.add(kind)
                print(f'rory reproduce: {_PROGRESS[kind]}', flush=True)
        exits = [e for e in events if e.get('kind') == 'exit' and e.get('code') != 0]
        if exits:
            time.sleep(0.3)  # the died_on record follows the exit
            events = _events_of(events_path.parent, node)
            died = [e for e in events if e.get('kind') in ('died_on', 'quarantined')]
            code = int(exits[0]['code'])
            how = f'killed by signal {-code}' if code < 0 else f'exit status {code}'
            print(f'REPRODUCED: {node} died ({how})' + (
                f' while applying {died[0]["topic"]} (source_ns {died[0]["source_ns"]}, '
                f'seq {died[0]["seq"]})' if died else ''))
            return 0
        if settled_at is None and any(e.get('kind') == 'recovered' for e in events):
            settled_at = time.monotonic()
        if settled_at is not None and time.monotonic() - settled_at > 5.0:
            print(f'not reproduced: {node} restored, took every recorded message and ran 5 s '
                  'more without crashing')
            return 1
        if sup.poll() is not None:
            print(f'not reproduced: the supervisor ended (exit {sup.returncode}) first')
            return 1
        time.sleep(0.1)
    print(f'not reproduced within {timeout:g} s')
    return 1


def bundle_main(argv: Sequence[str]) -> int:
    """``rory bundle``."""
    parser = argparse.ArgumentParser(prog='rory bundle', description=__doc__.split('\n\n')[0])
    parser.add_argument('store', type=Path)
    parser.add_argument('--node', required=True)
    parser.add_argument('-o', '--out', type=Path, required=True)
    parser.add_argument('--config', type=Path, help="the supervisor config: adds the node's "
                        'program and command, so the bundle reproduces on its own')
    args = parser.parse_args(argv)
    try:
        manifest = make_bundle(args.store, args.node, args.out, args.config)
    except (BundleError, ConfigError, CheckpointError) as err:
        print(f'rory bundle: {err}', file=sys.stderr)
        return 2
    print(f'rory bundle: {args.out}: checkpoint {manifest["checkpoint"]["seq"]}, '
          f'{len(manifest["segments"])} segment(s), '
          f'{"with" if manifest["command"] else "without"} the program')
    if manifest['note']:
        print(f'rory bundle: warning: {manifest["note"]}', file=sys.stderr)
    return 0


def reproduce_main(argv: Sequence[str]) -> int:
    """``rory reproduce``."""
    parser = argparse.ArgumentParser(prog='rory reproduce',
                                     description='Replay a crash bundle until the node crashes.')
    parser.add_argument('bundle', type=Path)
    parser.add_argument('-C', '--directory', type=Path, help='extract here (default: a '
                        'temporary folder, removed afterwards)')
    parser.add_argument('--timeout', type=float, default=60.0)
    parser.add_argument('--domain', type=int, default=int(os.environ.get('ROS_DOMAIN_ID') or 87))
    args = parser.parse_args(argv)
    keep = args.directory is not None
    into = args.directory or Path(tempfile.mkdtemp(prefix='rory-reproduce-'))
    into.mkdir(parents=True, exist_ok=True)
    # The log it names outlives a temporary extraction folder.
    log = None if keep else into.with_name(f'{into.name}.log')
    try:
        return reproduce(args.bundle, into.resolve(), timeout=args.timeout, domain=args.domain,
                         log=log)
    except BundleError as err:
        print(f'rory reproduce: {err}', file=sys.stderr)
        return 2
    finally:
        if not keep:
            shutil.rmtree(into, ignore_errors=True)
