"""The ``rory`` command: supervise, sim, eval, inspect, kill, bundle and reproduce."""

from __future__ import annotations

import argparse
import importlib.metadata
import logging
import sys
from collections.abc import Sequence

import setproctitle

from .errors import ConfigError, ParameterError, RoryError

# Before anything else runs: a later first call found no room for a title in this process (ps
# then showed every fork of the supervisor's zygote with the supervisor's command line).
setproctitle.getproctitle()


def _supervise(args: argparse.Namespace) -> int:
    from .supervisor.embed import supervise

    start = 'fresh' if args.fresh else 'resume' if args.resume else 'auto'
    return supervise(args.config, ros_args=args.ros_args, start=start)


EXTRAS = {'sim': ('mujoco',), 'eval': ('mujoco', 'matplotlib')}
"""What ``rory sim`` and ``rory eval`` need beyond the runtime (pyproject.toml's extras)."""


def _missing_extra(command: str) -> str:
    """The modules of ``command``'s extra that cannot be imported here, named; '' if none."""
    import importlib.util

    return ', '.join(m for m in EXTRAS[command] if importlib.util.find_spec(m) is None)


FORWARDED_SIGNALS = ('SIGINT', 'SIGTERM', 'SIGHUP', 'SIGQUIT')
"""The signals ``rory sim`` passes on to the simulator it runs."""

KEYBOARD_SIGNALS = ('SIGINT', 'SIGQUIT')
"""Ctrl-C's and Ctrl-\\'s: a terminal sends them to its foreground process group, child included."""


def _in_the_terminals_foreground() -> bool:
    """Whether this process's group is the foreground group of the terminal it runs in."""
    import os

    for fd in (0, 1, 2):
        try:
            return os.tcgetpgrp(fd) == os.getpgrp()
        except OSError:  # not a terminal, or not ours
            continue
    return False


def _run_program(command: list[str]) -> int:
    """Run ``command`` as a child in the foreground, as if this process were it.

    The signals in :data:`FORWARDED_SIGNALS` that reach this process are passed on to the
    child, each once: a keyboard signal (Ctrl-C, Ctrl-\\) while this process is in its
    terminal's foreground is not, since the terminal sent it to the child too (the same process
    group); `kill -INT` of this process alone there therefore does nothing, while SIGTERM always
    goes on. The child's end is this process's: its exit code, or, killed by a signal, the same
    signal."""
    import contextlib
    import os
    import signal
    import subprocess
    import threading

    child: subprocess.Popen[bytes] | None = None
    early: list[int] = []
    keyboard = {getattr(signal, name) for name in KEYBOARD_SIGNALS}

    def forward(signum: int, _frame: object) -> None:
        if child is None:
            early.append(signum)  # before the child: it has it from no one
        elif child.returncode is None and not (
                signum in keyboard and _in_the_terminals_foreground()):  # from the terminal
            child.send_signal(signum)

    # Only the main thread can set handlers; called from another, the child gets no signals.
    sigs = ([getattr(signal, name) for name in FORWARDED_SIGNALS]
            if threading.current_thread() is threading.main_thread() else [])
    previous = {sig: signal.signal(sig, forward) for sig in sigs}
    try:
        child = subprocess.Popen(command)
        for signum in early:
            child.send_signal(signum)
        code = child.wait()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if code < 0:
        # Killed by a signal: end the same way, so that a shell or a supervisor sees it (a
        # signal whose default is not to end a process ends in its shell code instead).
        with contextlib.suppress(OSError, ValueError):  # SIGKILL's handler is not ours to set
            signal.signal(-code, signal.SIG_DFL)
        os.kill(os.getpid(), -code)
        return 128 - code
    return code


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``rory`` console script."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] in (['sim'], ['eval']) and (missing := _missing_extra(argv[0])):
        print(f'rory: error: rory {argv[0]} needs {missing}, not installed with the runtime: '
              f"pip install 'rory-ros2[{argv[0]}]'", file=sys.stderr)
        return 2
    if argv[:1] == ['sim']:
        # The simulator (sim/, an extra) is a program of its own with its own parser
        # (sim/cli.py): run, not imported, so that the runtime never loads it or MuJoCo. -P:
        # the installed sim, not a folder named sim where the command is typed.
        return _run_program([sys.executable, '-P', '-m', 'sim', *argv[1:]])
    if argv[:1] == ['bundle']:
        from .bundle import bundle_main

        return bundle_main(argv[1:])
    if argv[:1] == ['reproduce']:
        from .bundle import reproduce_main

        return reproduce_main(argv[1:])
    if argv[:1] == ['kill']:
        from .kill import main as kill_main

        return kill_main(argv[1:])
    if argv[:1] == ['inspect']:
        from .inspection import main as inspect_main

        return inspect_main(argv[1:])
    if argv[:1] == ['eval']:
        # The evaluation (rory_eval/evaluation) is a separate program that drives this one;
        # nothing in RORY imports it, so it is run, not imported.
        import subprocess

        return subprocess.call([sys.executable, '-m', 'rory_eval.evaluation', *argv[1:]])
    parser = argparse.ArgumentParser(
        prog='rory', description='Crash recovery with state for ROS 2 nodes.'
    )
    parser.add_argument('-v', '--verbose', action='store_true', help='debug logging')
    parser.add_argument('--version', action='version',
                        version=f'rory {importlib.metadata.version("rory-ros2")}')
    sub = parser.add_subparsers(dest='command', required=True)
    supervise = sub.add_parser('supervise', help='run nodes and recover them when they crash')
    supervise.add_argument('config', help='supervisor configuration (YAML); then optionally '
                           '--ros-args ... for the supervisor and every node')
    start = supervise.add_mutually_exclusive_group()
    start.add_argument('--fresh', action='store_true',
                       help='start every node empty, setting the earlier run aside in '
                            '<store>/.previous (older ones in .previous.1, ...: keep_runs '
                            'in all, 3 by default; the default after a clean stop)')
    start.add_argument('--resume', action='store_true',
                       help="recover every node from the store's checkpoints and logs "
                            '(default after a run that did not stop cleanly)')
    supervise.set_defaults(run=_supervise)
    sub.add_parser('sim', help='the MuJoCo robot worlds bridged to ROS 2 (rory sim --help)',
                   add_help=False)
    sub.add_parser('eval', help="the paper's Tables I-IV and figures from real runs "
                                '(rory eval --help)', add_help=False)
    sub.add_parser('inspect', help="a store's nodes, checkpoints and log segments "
                                   '(rory inspect --help)', add_help=False)
    sub.add_parser('kill', help="signal a supervised node's current process, nothing else "
                                '(rory kill --help)', add_help=False)
    sub.add_parser('bundle', help="a node's last checkpoint, the messages after it and its "
                                  'crash report, as one tar file (rory bundle --help)',
                   add_help=False)
    sub.add_parser('reproduce', help='replay a crash bundle until the node crashes again '
                                     '(rory reproduce --help)', add_help=False)
    # Everything after --ros-args is ROS's (remaps, parameters, log levels), as for any node.
    ros_args: list[str] = []
    if '--ros-args' in argv:
        at = argv.index('--ros-args')
        argv, ros_args = argv[:at], argv[at + 1:]
        if ros_args[-1:] == ['--']:
            ros_args = ros_args[:-1]
    args = parser.parse_args(argv)
    args.ros_args = ros_args

    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format='%(asctime)s.%(msecs)03d %(message)s',
        datefmt='%H:%M:%S',
        stream=sys.stdout,
    )
    try:
        code: int = args.run(args)
    except (ConfigError, ParameterError) as err:
        print(f'rory: error: {err}', file=sys.stderr)
        return 2
    except RoryError as err:
        print(f'rory: error: {err}', file=sys.stderr)
        return 1
    return code


if __name__ == '__main__':
    sys.exit(main())
