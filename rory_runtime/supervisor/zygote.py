"""The supervisor's fork server: every node process and standby starts as a fork of one warm
process, so what they all import is in memory once.

An interpreter that imports rclpy, its message packages and numpy, and makes a DDS participant,
holds ~50 MB of PSS on its own; a forked child that shares its parent's pages keeps ~17 MB
private (``python -m rory_eval.bench.fork_memory_bench``, docs/performance.md). So the supervisor,
before its own ``rclpy.init`` and before it starts any thread, imports what its nodes import
from outside their own folders (:func:`~rory_runtime.standby.warm_imports`), freezes those
objects out of the garbage collector's reach (``gc.freeze``: a collection in a child would
otherwise write to every page), and forks the *zygote*. The zygote never makes a participant
and never starts a thread; it waits on a socket and forks on request:

* a **node**: the program runs as ``python node.py`` would (``__main__``), in the node's
  folder and environment; its modules are imported only now, since the decorator reads the
  environment when a node class is defined;
* a **standby**: it calls ``rclpy.init`` and makes a hidden placeholder node, so that its
  participant exists and is discovered before any node crashes, then waits to be told which
  node to become (environment, folder, program). One standby serves every node whose
  ``rclpy.init`` would be the same (:func:`init_signature`);
* a **spare**: a fork held ready without ``rclpy.init``, told at activation which node to
  become, which it then starts as a node fork would (cold). It costs a few private pages
  (docs/performance.md, "Spare forks"), and it takes the zygote's round trip, which a loaded
  machine stretches to a hundred milliseconds, off the supervisor's main loop when more nodes
  are struck together than the pool has standbys.

Each child is forked twice (the zygote's child forks it and exits), so it is re-parented to
the supervisor, which is a child subreaper while it asks for a fork: the supervisor waits for
it, signals it and sees its exit status as for a process it started itself. The child then
asks to be killed if the supervisor dies (``PR_SET_PDEATHSIG``), in a session of its own.

What a fork does not give a child that ``exec`` would: a fresh interpreter. It gets the
zygote's modules (every node's foreign imports, RORY's runtime), its random state (reseeded
here: Python's ``random`` does so itself, numpy's global generator is reseeded below) and no
thread, participant or lock of the supervisor (none existed when the zygote was forked).
"""

from __future__ import annotations

import array
import atexit
import contextlib
import ctypes
import ctypes.util
import gc
import io
import json
import logging
import os
import shlex
import signal
import socket
import struct
import sys
import time
import traceback
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import setproctitle

from ..errors import RoryError
from ..standby import (
    PLACEHOLDER_PREFIX,
    Activation,
    Program,
    StandbyError,
    absorb_init,
    drop_placeholder_after_first_node,
    give_nodes_arguments,
    load_type_supports,
    read_activation,
    run_program,
    warm_imports,
)

_logger = logging.getLogger('rory.supervisor')

ZYGOTE_TITLE = 'rory-zygote'
STANDBY_TITLE = 'rory-standby'
SPARE_TITLE = 'rory-spare'
"""Command lines (``ps``) of the fork server, of a waiting standby and of a waiting spare; a
node shows its own."""

_PR_SET_PDEATHSIG = 1
_PR_SET_CHILD_SUBREAPER = 36
_MAX_MESSAGE = 1 << 20  # a request: an environment and a command line
_MAX_FDS = 4

INIT_ENV_PREFIXES = ('ROS_', 'RMW_', 'FASTRTPS_', 'FASTDDS_', 'CYCLONEDDS_', 'RCUTILS_',
                     'RCL_', 'LD_', 'PYTHON', 'AMENT_', 'OPENBLAS_', 'OMP_', 'MKL_')
"""Environment read before a node's own code runs: by rclpy.init and DDS (domain, discovery,
profiles, rmw), by the dynamic loader and the interpreter. A node whose values differ from the
zygote's (imports) or the standby's (participant) cannot start from them."""


def _libc() -> Any:
    return ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6', use_errno=True)


def init_environment(env: Mapping[str, str]) -> dict[str, str]:
    """The part of an environment that must be equal for two processes to share a start."""
    return {k: v for k, v in env.items() if k.startswith(INIT_ENV_PREFIXES)}


def ros_arguments(argv: Sequence[str]) -> tuple[str, ...]:
    """The ``--ros-args`` sections of a command line (what ``rclpy.init`` takes from it)."""
    taken: list[str] = []
    inside = False
    for arg in argv:
        if arg == '--ros-args':
            inside = True
        elif arg == '--' and inside:
            inside = False
        elif inside:
            taken.append(arg)
    return tuple(taken)


NODE_LEVEL_FLAGS = frozenset({'-p', '--param', '-r', '--remap', '--params-file'})
"""``--ros-args`` flags that a node's own arguments (``Node(cli_args=...)``) carry as well as
``rclpy.init``'s: parameters, remaps, parameter files. Others (``--log-level``, ``--enclave``,
...) configure the process or its participant and must be given to ``rclpy.init``."""


def node_level(args: Sequence[str]) -> bool:
    """Whether every one of these ``--ros-args`` arguments can be given to the nodes instead of
    to ``rclpy.init`` (each a flag of :data:`NODE_LEVEL_FLAGS` and its value)."""
    pairs = list(args)
    return len(pairs) % 2 == 0 and all(flag in NODE_LEVEL_FLAGS for flag in pairs[::2])


def init_signature(program: Program, env: Mapping[str, str]) -> tuple[Any, ...]:
    """What a standby's ``rclpy.init`` and participant depend on: nodes with equal signatures
    can all start from one standby. A node whose ROS arguments are all parameters and remaps
    shares the standby that has none: they are given to its nodes at activation
    (:func:`~rory_runtime.standby.give_nodes_arguments`), so one standby serves a robot's
    nodes however their parameters differ."""
    args = ros_arguments(program.args)
    return (() if node_level(args) else args, tuple(sorted(init_environment(env).items())))


def init_arguments(signature: Hashable) -> tuple[str, ...]:
    """The ``--ros-args`` a standby of this :func:`init_signature` gives ``rclpy.init``."""
    assert isinstance(signature, tuple)
    return tuple(signature[0])


def forkable(argv: Sequence[str]) -> Program | None:
    """The Python program a node command runs, if the zygote can fork it: ``python FILE ...``
    or ``python -m MODULE ...`` with this interpreter (no interpreter options), or a console
    script of this interpreter's packages (``Program.console_script``)."""
    if not argv:
        return None
    head = argv[0]
    if head != sys.executable and Path(head).name not in ('python', 'python3', 'python3.11'):
        return Program.console_script(argv)
    if len(argv) < 2:
        return None
    try:
        return Program.parse(argv[1:])
    except StandbyError:
        return None


# -- the socket: one JSON message and up to _MAX_FDS descriptors per datagram -------------------


def _send(sock: socket.socket, message: dict[str, Any], fds: Sequence[int] = ()) -> None:
    data = json.dumps(message).encode()
    ancillary = [(socket.SOL_SOCKET, socket.SCM_RIGHTS, array.array('i', fds))] if fds else []
    sock.sendmsg([data], ancillary)


def _receive(sock: socket.socket) -> tuple[dict[str, Any] | None, list[int]]:
    fds = array.array('i')
    data, ancdata, _flags, _addr = sock.recvmsg(_MAX_MESSAGE,
                                                socket.CMSG_SPACE(_MAX_FDS * fds.itemsize))
    for level, kind, payload in ancdata:
        if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
            fds.frombytes(payload[: len(payload) - (len(payload) % fds.itemsize)])
    if not data:
        return None, list(fds)
    return json.loads(data), list(fds)


# -- the zygote process -------------------------------------------------------------------------


def _serve(sock: socket.socket, supervisor: int) -> int:
    """The zygote's loop: fork what is asked for until the supervisor closes the socket."""
    title(ZYGOTE_TITLE)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the supervisor's to handle
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _libc().prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != supervisor:
        return 1
    while True:
        try:
            request, _fds = _receive(sock)
        except OSError:
            return 1
        if request is None:
            return 0
        reply: dict[str, Any]
        sent: list[int] = []
        try:
            reply, sent = _handle(request, supervisor, sock, _fds)
        except Exception as err:  # a bad request must not end the zygote
            reply = {'error': f'{type(err).__name__}: {err}'}
        finally:
            for fd in _fds:  # the child has its own copies
                os.close(fd)
        try:
            _send(sock, reply, sent)
        except OSError:
            return 1
        finally:
            for fd in sent:  # the supervisor has its own copies now
                os.close(fd)


def _handle(request: dict[str, Any], supervisor: int, sock: socket.socket,
            output: Sequence[int]) -> tuple[dict[str, Any], list[int]]:
    """Fork what ``request`` asks for.

    Args:
        output: The child's stdout and stderr, when the supervisor sent them (its lines are
            prefixed: supervisor/output.py); else it keeps the zygote's.
    """
    if len(output) not in (0, 2):
        raise RoryError(f'{len(output)} descriptors sent, expected none or two')
    kind = request.get('kind')
    if kind == 'node':
        pid = _fork_child(supervisor, lambda: _become_node(request), close=(sock.fileno(),),
                          output=output)
        return {'pid': pid}, []
    if kind in ('standby', 'spare'):
        become = _become_standby if kind == 'standby' else _become_spare
        control_r, control_w = os.pipe()
        ready_r, ready_w = os.pipe()
        try:
            pid = _fork_child(supervisor, lambda: become(request, control_r, ready_w),
                              close=(sock.fileno(), control_w, ready_r), output=output)
        except BaseException:
            for fd in (control_w, ready_r):
                os.close(fd)
            raise
        finally:
            os.close(control_r)
            os.close(ready_w)
        return {'pid': pid}, [control_w, ready_r]
    raise RoryError(f'unknown request {kind!r}')


def _fork_child(supervisor: int, body: Callable[[], int], close: Sequence[int],
                output: Sequence[int] = ()) -> int:
    """Fork ``body`` twice over, so that the supervisor (a subreaper) becomes its parent.

    Args:
        close: Descriptors of the zygote's that the child must not keep (its socket, the
            supervisor's ends of the child's pipes).
        output: Descriptors to become the child's stdout and stderr, if any.
    """
    report_r, report_w = os.pipe()
    middle = os.fork()
    if middle == 0:  # the zygote's child: fork the real one and go
        os.close(report_r)
        child = os.fork()
        if child == 0:
            os.close(report_w)
            for fd in close:
                os.close(fd)
            for target, fd in zip((1, 2), output, strict=False):
                os.dup2(fd, target)
                os.close(fd)
            os._exit(_child_main(supervisor, body))
        os.write(report_w, struct.pack('i', child))
        os._exit(0)
    os.close(report_w)
    data = b''
    while len(data) < 4:
        chunk = os.read(report_r, 4 - len(data))
        if not chunk:
            break
        data += chunk
    os.close(report_r)
    os.waitpid(middle, 0)  # when it has gone, its child is the supervisor's
    if len(data) < 4:
        raise RoryError('the fork server could not fork')
    return int(struct.unpack('i', data)[0])


def _child_main(supervisor: int, body: Callable[[], int]) -> int:
    """In the child: wait to be the supervisor's, bind its life to the supervisor's, run."""
    deadline = time.monotonic() + 5.0
    while os.getppid() != supervisor:
        if time.monotonic() > deadline:
            return 1
        time.sleep(0.0005)
    _libc().prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != supervisor:  # the supervisor died before prctl took effect
        return 1
    os.setsid()
    # What the zygote set for itself is not the node's; a fresh interpreter has these.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    # The zygote's objects stay frozen: a collection that walked them would write to every
    # page they share with the zygote and the other children.
    _reseed()
    try:
        code = body()
    except SystemExit as end:
        code = _exit_code(end.code)
    except BaseException:
        traceback.print_exc()
        code = 1
    return _finish(code)


def _exit_code(value: Any) -> int:
    if value is None:
        return 0
    if isinstance(value, int):
        return value
    print(value, file=sys.stderr)
    return 1


def _finish(code: int) -> int:
    """What an interpreter does at exit: atexit handlers, then flushed output."""
    try:
        atexit._run_exitfuncs()
    except BaseException:
        traceback.print_exc()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    return code


def _reseed() -> None:
    numpy = sys.modules.get('numpy')
    if numpy is not None:
        with contextlib.suppress(Exception):
            numpy.random.seed()  # the legacy global generator; random reseeds itself


def _enter(env: Mapping[str, str], cwd: str) -> None:
    os.environ.clear()
    os.environ.update(env)
    os.chdir(cwd)
    if env.get('PYTHONUNBUFFERED'):
        _unbuffered_streams()


def _unbuffered_streams() -> None:
    """What ``PYTHONUNBUFFERED`` gives a new interpreter: a forked one has the zygote's
    streams, buffered by a block when they were not a terminal, so a node killed after a
    ``print`` would lose it."""
    for name, fd in (('stdout', 1), ('stderr', 2)):
        old = getattr(sys, name)
        with contextlib.suppress(Exception):
            old.flush()
        setattr(sys, name, io.TextIOWrapper(io.FileIO(fd, 'w', closefd=False),
                                            encoding=getattr(old, 'encoding', None),
                                            errors=getattr(old, 'errors', None),
                                            write_through=True))


def forget_shadowed(home: Path) -> list[str]:
    """Drop from ``sys.modules`` what a program's own modules shadow, so that its ``import``
    finds its own file: the zygote imported every node's foreign imports, and one program's
    foreign ``utils`` may be another's own ``utils.py``. Returns the names dropped."""
    dropped = []
    for name in list(sys.modules):
        top = name.partition('.')[0]
        if (home / f'{top}.py').is_file() or (home / top / '__init__.py').is_file():
            dropped.append(name)
            del sys.modules[name]
    return dropped


def _run(program: Program) -> None:
    forget_shadowed(program.home())
    run_program(program)


def title(text: str) -> None:
    """What ``ps`` and ``pkill -f`` see as this process's command line: a fork keeps the
    supervisor's until it says otherwise."""
    setproctitle.setproctitle(text)


def _become_node(request: dict[str, Any]) -> int:
    title(shlex.join(request['argv']))
    _enter(request['env'], request['cwd'])
    program = forkable(request['argv'])
    if program is None:
        raise StandbyError(f'cannot run {request["argv"]!r} in a fork')
    _run(program)
    return 0


def _ready_then_activation(ready: int, control: int) -> Activation | None:
    """Say ready; wait for the activation line (None: dropped before use)."""
    os.write(ready, b'R')
    os.close(ready)
    try:
        return read_activation(control)
    finally:
        os.close(control)


def _become_standby(request: dict[str, Any], control: int, ready: int) -> int:
    """rclpy.init and a placeholder node; wait; become the node named at activation."""
    title(STANDBY_TITLE)
    _enter(request['env'], request['cwd'])
    import rclpy
    from rclpy.node import Node

    from .hidden import quiet_node

    init_args = list(request['init_args'])
    rclpy.init(args=init_args)
    placeholder = quiet_node(f'{PLACEHOLDER_PREFIX}{os.getpid()}')
    activation = _ready_then_activation(ready, control)
    if activation is None:  # dropped before use
        placeholder.destroy_node()
        rclpy.shutdown()
        return 0
    program = forkable(list(activation.argv))
    if program is None:
        raise StandbyError(f'cannot become {activation.argv!r}')
    title(shlex.join(activation.argv))
    _enter(activation.env, activation.cwd)
    asked, done = ros_arguments(program.args), ros_arguments(init_args)
    if asked != done and not done and node_level(asked):
        # A standby without ROS arguments: the node's parameters and remaps go to its nodes.
        give_nodes_arguments(Node, asked)
        done = asked

    def same_init(wanted: Sequence[str], _used: Sequence[str]) -> bool:
        return ros_arguments(wanted) == done

    absorb_init(rclpy, [program.argv[0], *init_args[1:]], same=same_init)
    drop_placeholder_after_first_node(Node, placeholder)
    _run(program)
    return 0


def _become_spare(request: dict[str, Any], control: int, ready: int) -> int:
    """Wait, without rclpy; become the node named at activation, as a node fork would."""
    title(SPARE_TITLE)
    activation = _ready_then_activation(ready, control)
    if activation is None:  # dropped before use
        return 0
    return _become_node({'argv': list(activation.argv), 'env': activation.env,
                         'cwd': activation.cwd})


# -- the supervisor's side ----------------------------------------------------------------------


@dataclass
class ForkedStandby:
    """A standby the zygote forked: its pid and the supervisor's ends of its two pipes."""

    pid: int
    control: int  # write: the activation line
    ready: int  # read: one byte once rclpy is up


class Zygote:
    """The supervisor's handle on its fork server (:func:`start`)."""

    def __init__(self, sock: socket.socket, pid: int, env: Mapping[str, str]) -> None:
        self._sock = sock
        self.pid = pid
        self.env = dict(env)  # the zygote's own: what it imported under

    @classmethod
    def start(cls, programs: Sequence[Program], preload: Sequence[str] = ()) -> Zygote:
        """Import what ``programs`` import from outside themselves and the modules named in
        ``preload``, freeze it all, and fork the zygote. Call before ``rclpy.init`` and before
        any thread: a fork copies only the calling thread, and the locks as they are.

        """
        import importlib

        for name in preload:
            importlib.import_module(name)
        for program in programs:
            home = str(program.home())
            added = home not in sys.path
            if added:
                sys.path.insert(0, home)
            try:
                warm_imports(program)
            finally:
                if added:
                    sys.path.remove(home)
        from ..log import default_typestore

        default_typestore()
        # Loaded after the fork, rclpy's own types (parameter services, /rosout, ...) cost
        # every node and standby ~20 MB of private pages; loaded here, they share them
        # (measured: a forked node's private memory 33 MB against 11).
        load_type_supports()
        gc.collect()
        gc.freeze()
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        supervisor = os.getpid()
        pid = os.fork()
        if pid == 0:
            parent.close()
            code = 1
            try:
                code = _serve(child, supervisor)
            finally:
                os._exit(code)
        child.close()
        return cls(parent, pid, os.environ)

    def _ask(self, request: dict[str, Any],
             output: Sequence[int] = ()) -> tuple[dict[str, Any], list[int]]:
        # A subreaper only while the zygote forks: the child it forks twice is then re-parented
        # here. Left on, every process a node leaves behind would be re-parented here too, and
        # nobody would reap it.
        libc = _libc()
        libc.prctl(_PR_SET_CHILD_SUBREAPER, 1)
        try:
            _send(self._sock, request, output)
            reply, fds = _receive(self._sock)
        except OSError as err:
            raise RoryError(f'the fork server is gone: {err}') from None
        finally:
            libc.prctl(_PR_SET_CHILD_SUBREAPER, 0)
        if reply is None:
            raise RoryError('the fork server is gone')
        if 'error' in reply:
            for fd in fds:
                os.close(fd)
            raise RoryError(f'the fork server could not start it: {reply["error"]}')
        return reply, fds

    def fork_node(self, argv: Sequence[str], env: Mapping[str, str], cwd: Path,
                  output: Sequence[int] = ()) -> int:
        """Start a node's program as a fork; its pid (a child of this process). ``output``:
        its stdout and stderr, if not the supervisor's."""
        reply, _ = self._ask({'kind': 'node', 'argv': list(argv), 'env': dict(env),
                              'cwd': str(cwd)}, output)
        return int(reply['pid'])

    def fork_standby(self, init_args: Sequence[str], env: Mapping[str, str],
                     cwd: Path, output: Sequence[int] = (), *,
                     spare: bool = False) -> ForkedStandby:
        """Start a standby that calls ``rclpy.init(args=init_args)`` under ``env``; with
        ``spare``, one that waits without it and starts as a node fork once activated."""
        reply, fds = self._ask({'kind': 'spare' if spare else 'standby',
                                'init_args': list(init_args), 'env': dict(env),
                                'cwd': str(cwd)}, output)
        if len(fds) != 2:
            for fd in fds:
                os.close(fd)
            raise RoryError('the fork server sent no pipes for the standby')
        return ForkedStandby(int(reply['pid']), fds[0], fds[1])

    def close(self) -> None:
        """End the zygote (it exits when its socket closes) and reap it."""
        with contextlib.suppress(OSError):
            self._sock.close()
        with contextlib.suppress(ChildProcessError):
            os.waitpid(self.pid, 0)


def activation_line(argv: Sequence[str], env: Mapping[str, str], cwd: Path) -> bytes:
    """What a standby is told at activation."""
    return Activation(tuple(argv), dict(env), str(cwd)).encode()
