"""``rory kill STORE NODE``: signal one supervised node's current process, and nothing else.

``pkill -f`` matches every process whose command line looks like the node's (its warm standby,
another robot's copy, an editor) and, with ``--ros-args`` in the command, none. The supervisor
knows exactly which process is the node: its last ``spawn`` event in ``<store>/events.jsonl``.
Before signalling, that process must still be alive and a child of the supervisor that holds
the store (``supervisor.lock``), so a pid the kernel has since given to another process is
never signalled.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from .supervisor.run_marker import LOCK_NAME

EVENTS_NAME = 'events.jsonl'


class KillError(Exception):
    """Why the node was not signalled (one line for the user)."""


def _parent_of(pid: int) -> int | None:
    try:
        stat = Path(f'/proc/{pid}/stat').read_text()
    except OSError:
        return None
    # The command name may hold spaces and parentheses: fields start after the last ')'.
    return int(stat[stat.rindex(')') + 2:].split()[1])


def _supervisor_pid(store: Path) -> int:
    try:
        text = (store / LOCK_NAME).read_text().strip()
    except OSError as err:
        raise KillError(f'{store}: no supervisor has run here ({err.strerror})') from None
    if not text.isdigit() or not Path(f'/proc/{text}').exists():
        raise KillError(f'{store}: no supervisor runs on this store now')
    return int(text)


def current_process(store: Path, node: str) -> tuple[int, int]:
    """The node's live process: (pid, incarnation).

    Raises:
        KillError: No such node, it is not running, or its pid is no longer its process.
    """
    supervisor = _supervisor_pid(store)
    try:
        lines = (store / EVENTS_NAME).read_text().splitlines()
    except OSError as err:
        raise KillError(f'{store / EVENTS_NAME}: cannot read: {err.strerror}') from None
    spawned: tuple[int, int] | None = None
    exited: set[int] = set()
    for line in lines:
        try:
            event = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut short by a crash of the writer
        if not isinstance(event, dict) or event.get('node') != node:
            continue
        if event.get('kind') == 'spawn':
            spawned = (int(event['pid']), int(event['incarnation']))
        elif event.get('kind') == 'exit':
            exited.add(int(event['incarnation']))
    if spawned is None:
        raise KillError(f'{store}: no node {node!r} was started here')
    pid, incarnation = spawned
    if incarnation in exited or _parent_of(pid) != supervisor:
        raise KillError(f'{node} is not running (its last process, pid {pid}, has ended)')
    return pid, incarnation


def main(argv: Sequence[str] | None = None) -> int:
    """``rory kill``; 0, or 2 with one line saying why nothing was signalled."""
    parser = argparse.ArgumentParser(
        prog='rory kill', description="Signal one supervised node's current process (the one "
        'the supervisor last started for it), and nothing else.')
    parser.add_argument('store', type=Path, help='the store folder (.rory by default)')
    parser.add_argument('node', help="the node's name in the supervisor config")
    parser.add_argument('--signal', default='KILL',
                        help='KILL (default), SEGV, TERM, INT, ABRT, ... or a number')
    args = parser.parse_args(argv)
    name = args.signal.upper().removeprefix('SIG')
    try:
        signum = signal.Signals(int(name) if name.isdigit() else getattr(signal, f'SIG{name}'))
    except (AttributeError, ValueError):
        print(f'rory kill: error: --signal: no signal {args.signal!r}', file=sys.stderr)
        return 2
    try:
        pid, incarnation = current_process(args.store, args.node)
        os.kill(pid, signum)
    except KillError as err:
        print(f'rory kill: error: {err}', file=sys.stderr)
        return 2
    except ProcessLookupError:
        print(f'rory kill: error: {args.node} ended just now (pid {pid})', file=sys.stderr)
        return 2
    print(f'sent {signum.name} to {args.node} '
          f'(pid {pid}, incarnation {incarnation})')
    return 0
