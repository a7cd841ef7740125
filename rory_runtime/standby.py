"""Becoming a node: what a process forked from the supervisor's zygote does to run a node's
program as ``python node.py``, ``python -m package.node`` or its console script (an installed
package's entry point, ``pkg_node = package.node:main``) would have.

The zygote (``supervisor/zygote.py``) imports, before it forks anything, what every node's
program imports from outside its own folder (:func:`warm_imports`: rclpy, numpy, message
packages and their type support); the node's own modules are never imported before the node
starts, because a node class is decorated from the environment when it is defined, and that
environment exists only then. A module of someone else's that decorates at import is abandoned
(its import fails here and is redone by the node).

A *warm standby* is such a fork that has also called ``rclpy.init`` and made a hidden
placeholder node, so that its DDS participant exists and is discovered before any node
crashes: a cold restart of a Python rclpy node costs ~0.25 s of imports and initialisation and
then, in most runs, 1.7-2.6 s before the rest of the graph hears a new participant, while a
process whose participant is already known gets its first message ~10 ms after making its
node. It waits for one :class:`Activation` line: the program, the environment and the folder
of the node it becomes. Then the program runs (``__name__ == '__main__'``); its own
``rclpy.init()`` is absorbed when it asks for what is already done (:func:`absorb_init`); the
placeholder goes as soon as the program's first node exists, so the participant is never
without a node (:func:`drop_placeholder_after_first_node`). End of file instead of a line (the
supervisor dropped it) ends the standby.
"""

from __future__ import annotations

import ast
import builtins
import contextlib
import importlib
import importlib.machinery
import importlib.metadata
import importlib.util
import io
import json
import logging
import os
import pkgutil
import runpy
import shutil
import sys
import types
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

_logger = logging.getLogger('rory.standby')

ACTIVATE_LIMIT = 1 << 20
"""Largest activation line accepted (bytes); the environment is a few hundred."""

PLACEHOLDER_PREFIX = '_rory_standby_'
"""Node name prefix of the placeholder (a leading underscore hides it from node lists)."""


class StandbyError(Exception):
    """The standby was started wrongly or activated with a bad message."""


@dataclass(frozen=True)
class Program:
    """What the standby will run: a script path, a module, or a module's function that a
    console script calls (``entry``, with the script's path as ``argv0``); and its arguments."""

    script: Path | None
    module: str | None
    args: tuple[str, ...]
    entry: str | None = None  # the function (dotted within the module) a console script calls
    argv0: str | None = None  # the console script's path: sys.argv[0] as the node sees it

    @classmethod
    def parse(cls, argv: Sequence[str]) -> Program:
        """``node.py args...`` or ``-m package.node args...``.

        Raises:
            StandbyError: Neither form (interpreter options such as ``-u`` are not taken).
        """
        argv = list(argv)
        if len(argv) >= 2 and argv[0] == '-m':
            return cls(None, argv[1], tuple(argv[2:]))
        if argv and not argv[0].startswith('-'):
            return cls(Path(argv[0]), None, tuple(argv[1:]))
        raise StandbyError(f'not a script or -m module: {argv!r}')

    @classmethod
    def console_script(cls, argv: Sequence[str]) -> Program | None:
        """``script args...`` when ``script`` is a console script that runs with this
        interpreter (its ``#!`` line names it), resolved through ``importlib.metadata`` to the
        module and function it calls; else None."""
        if not argv or argv[0].startswith('-'):
            return None
        found = shutil.which(argv[0])
        if found is None:
            return None
        try:
            with open(found, 'rb') as script:
                shebang = script.readline(4096)
        except OSError:
            return None
        if shebang.strip() != f'#!{sys.executable}'.encode():
            return None
        name = Path(found).name
        entries = importlib.metadata.entry_points(group='console_scripts', name=name)
        entry = next(iter(entries), None)
        if entry is None or not entry.attr:
            return None
        return cls(None, entry.module, tuple(argv[1:]), entry=entry.attr, argv0=found)

    @property
    def argv(self) -> list[str]:
        """sys.argv as the program will see it (for -m, runpy puts the module's path first)."""
        if self.entry is not None:
            return [str(self.argv0), *self.args]
        head = str(self.script) if self.script is not None else str(self.module)
        return [head, *self.args]

    def home(self) -> Path:
        """The directory Python puts first on sys.path for this program."""
        if self.script is not None:
            return self.script.resolve().parent
        return Path.cwd()


# -- warming up ---------------------------------------------------------------------------------


def _imports_of(source: str) -> list[tuple[str, tuple[str, ...]]]:
    """Absolute imports anywhere in a module: (module, names taken from it)."""
    found: list[tuple[str, tuple[str, ...]]] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.extend((alias.name, ()) for alias in node.names)
        elif (isinstance(node, ast.ImportFrom) and node.level == 0 and node.module
              and node.module != '__future__'):
            found.append((node.module, tuple(a.name for a in node.names)))
    return found


def _is_own(name: str, home: Path, own_top: str | None) -> bool:
    """Whether a module belongs to the program (its folder, or its own package)."""
    top = name.partition('.')[0]
    if top == own_top:
        return True
    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        return True  # unknown: leave it to the program
    if spec is None:
        return True
    places = [spec.origin] if spec.origin else []
    places += list(spec.submodule_search_locations or [])
    return any(p and Path(p).resolve().is_relative_to(home) for p in places)


def foreign_imports(program: Program) -> list[tuple[str, tuple[str, ...]]]:
    """What the program (and its own modules, followed) imports from outside itself."""
    home = program.home()
    own_top = program.module.partition('.')[0] if program.module else None
    if program.script is not None:
        first = program.script.resolve()
    else:
        spec = importlib.util.find_spec(str(program.module))
        if spec is None or not spec.origin:
            return []
        first = Path(spec.origin)
    todo: list[Path] = [first]
    seen: set[Path] = set()
    found: list[tuple[str, tuple[str, ...]]] = []
    while todo:
        path = todo.pop()
        if path in seen or len(seen) > 200:
            continue
        seen.add(path)
        try:
            imports = _imports_of(path.read_text(encoding='utf-8'))
        except (OSError, SyntaxError, UnicodeDecodeError, ValueError):
            continue
        for name, names in imports:
            if not _is_own(name, home, own_top):
                found.append((name, names))
                continue
            local = home.joinpath(*name.split('.'))
            for candidate in (local.with_suffix('.py'), local / '__init__.py'):
                if candidate.is_file():
                    todo.append(candidate.resolve())
    return found


class _Deferred(Exception):
    """A module tried to decorate a node class before activation."""


def warm_imports(program: Program) -> list[str]:
    """Import what the program will import from outside itself; the names that failed."""
    from rory_runtime.node import attach

    def refuse(*_args: Any, **_kwargs: Any) -> Any:
        raise _Deferred
    real = attach.RuntimeEnv.from_environ
    attach.RuntimeEnv.from_environ = refuse  # type: ignore[method-assign]
    failed: list[str] = []
    try:
        for name, names in foreign_imports(program):
            try:
                module = importlib.import_module(name)
            except (Exception, _Deferred):  # the program will meet (and report) it again
                failed.append(name)
                continue
            if name.endswith('.msg') or name.endswith('.srv'):
                for attr in names:
                    _load_type_support(getattr(module, attr, None))
    finally:
        attach.RuntimeEnv.from_environ = real  # type: ignore[method-assign]
    return failed


def _load_type_support(msgtype: Any) -> None:
    # rclpy loads a type's C support the first time an entity uses it (~ms each): its
    # libraries, whose relocated pages a process forked before the load would each hold
    # privately (~1-2 MB a type). A service's request, response and event are types too.
    if msgtype is None:
        return
    for part in (msgtype, *(getattr(msgtype, name, None) for name in ('Request', 'Response',
                                                                       'Event'))):
        load = getattr(type(part), '__import_type_support__', None) if part else None
        if load is not None:
            with contextlib.suppress(Exception):  # loaded again, with its real error, when used
                load()


RCLPY_TYPES = (
    ('rcl_interfaces.srv', ('ListParameters', 'GetParameters', 'SetParameters',
                            'SetParametersAtomically', 'DescribeParameters',
                            'GetParameterTypes')),
    ('rcl_interfaces.msg', ('ParameterEvent', 'Log')),
    ('type_description_interfaces.srv', ('GetTypeDescription',)),
    ('rosgraph_msgs.msg', ('Clock',)),
    ('std_msgs.msg', ('String', 'UInt8MultiArray')),
)
"""Types every supervised node uses whatever its program: rclpy's parameter services,
~/get_type_description, /rosout, /parameter_events and /clock; RORY's status and shadow
topics."""


def load_type_supports(types: Sequence[tuple[str, Sequence[str]]] = RCLPY_TYPES) -> None:
    """Load the C type support of ``types`` (module, names) into this process now."""
    for module_name, names in types:
        try:
            module = importlib.import_module(module_name)
        except ImportError:
            continue
        for name in names:
            _load_type_support(getattr(module, name, None))


# -- activation ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Activation:
    """What a standby becomes: a node's command line, environment and folder."""

    argv: tuple[str, ...]
    env: dict[str, str]
    cwd: str

    def encode(self) -> bytes:
        """The line written on the standby's control pipe."""
        return json.dumps({'argv': list(self.argv), 'env': self.env,
                           'cwd': self.cwd}).encode() + b'\n'

    @classmethod
    def decode(cls, data: bytes) -> Activation:
        """Parse one line.

        Raises:
            StandbyError: Not a JSON object with ``argv`` (strings), ``env`` (strings to
                strings) and ``cwd`` (a string).
        """
        try:
            message = json.loads(data)
            argv, env, cwd = message['argv'], message['env'], message['cwd']
        except (ValueError, KeyError, TypeError) as err:
            raise StandbyError(f'bad activation message: {err}') from None
        if not (isinstance(argv, list) and argv and all(isinstance(a, str) for a in argv)):
            raise StandbyError('bad activation message: argv must be a list of strings')
        if not isinstance(env, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in env.items()
        ):
            raise StandbyError('bad activation message: env must map strings to strings')
        if not isinstance(cwd, str):
            raise StandbyError('bad activation message: cwd must be a string')
        return cls(tuple(argv), env, cwd)


def read_activation(fd: int) -> Activation | None:
    """Block until the activation line arrives; None at end of file before one.

    Raises:
        StandbyError: The line is malformed or longer than :data:`ACTIVATE_LIMIT`.
    """
    data = b''
    while not data.endswith(b'\n'):
        chunk = os.read(fd, 65536)
        if not chunk:
            return None if not data else Activation.decode(data)
        data += chunk
        if len(data) > ACTIVATE_LIMIT:
            raise StandbyError(f'activation longer than {ACTIVATE_LIMIT} bytes')
    return Activation.decode(data)


def absorb_init(
    rclpy: Any, used_args: list[str],
    same: Callable[[list[str], list[str]], bool] | None = None,
) -> Callable[[], None]:
    """Make the program's ``rclpy.init()`` a no-op when it asks for what is already done.

    Anything else (other arguments, a context, a domain id) shuts the standby's context down
    and initialises as asked: correct, only no longer warm. Returns the undo.

    Args:
        same: Whether the program's arguments ask for what ``used_args`` did (default: every
            argument after the program's name equal).
    """
    real_init = rclpy.init

    def equal(wanted: list[str], used: list[str]) -> bool:
        return wanted[1:] == used[1:]

    judge = same or equal

    def init(*args: Any, **kwargs: Any) -> None:
        rclpy.init = real_init
        wanted = kwargs.get('args', args[0] if args else None)
        wanted = list(sys.argv if wanted is None else wanted)
        extra = set(kwargs) - {'args'} or len(args) > 1
        if not extra and judge(wanted, used_args) and rclpy.ok():
            return None
        _logger.warning('[rory] standby: the program initialises rclpy differently; '
                        'starting cold')
        rclpy.try_shutdown()
        real_init(*args, **kwargs)

    rclpy.init = init

    def undo() -> None:
        rclpy.init = real_init
    return undo


def give_nodes_arguments(node_class: Any, ros_args: Sequence[str]) -> None:
    """Every node the program makes gets ``ros_args`` (parameters, remaps) as its own
    arguments, as ``rclpy.init(args)`` would have given them to all its nodes: the standby's
    ``rclpy.init`` had none (supervisor/zygote.py, ``node_level``).

    A node's own ``cli_args`` come after them and so win, as node arguments win over global
    ones; a node made with ``use_global_arguments=False`` or in another context gets none.
    """
    original = node_class.__init__
    given = ['--ros-args', *ros_args]

    def __init__(self: Any, *args: Any, **kwargs: Any) -> None:
        if kwargs.get('use_global_arguments', True) and kwargs.get('context') is None:
            kwargs['cli_args'] = [*given, *(kwargs.get('cli_args') or [])]
        original(self, *args, **kwargs)

    node_class.__init__ = __init__


def drop_placeholder_after_first_node(node_class: Any, placeholder: Any) -> None:
    """Destroy the placeholder once the program's first node exists.

    The DDS participant lives as long as the context has a node: the real node must exist
    before the placeholder goes, or the participant (and its discovery) would be lost.
    """
    original = node_class.__init__

    def __init__(self: Any, *args: Any, **kwargs: Any) -> None:
        original(self, *args, **kwargs)
        if node_class.__init__ is __init__:
            node_class.__init__ = original
        nonlocal placeholder
        if placeholder is not None and self is not placeholder:
            done, placeholder = placeholder, None
            done.destroy_node()

    node_class.__init__ = __init__


# What the interpreter itself calls for ``python -m`` and a folder or zip file: it runs the
# code in the ``__main__`` of sys.modules and, unlike run_module, leaves it there.
_run_module_as_main: Callable[..., object] = runpy._run_module_as_main  # type: ignore[attr-defined]


def run_program(program: Program) -> None:
    """Run it as ``python`` (or its console script) would have.

    A script or ``-m`` module runs in a new ``__main__`` module that stays in ``sys.modules``
    after it returns or raises, as in an interpreter (``runpy.run_path`` and ``run_module``
    put the zygote's back): the atexit hooks that run after it, among them the runtime's last
    checkpoint, which names an Enum or dataclass class by its module, must find the
    program's classes there.
    """
    sys.argv = program.argv
    if program.entry is not None:
        sys.path[0] = str(Path(str(program.argv0)).parent)  # a script's folder comes first
        target: Any = importlib.import_module(str(program.module))
        for part in program.entry.split('.'):
            target = getattr(target, part)
        sys.exit(target())  # as the console script's wrapper does
    main = types.ModuleType('__main__')
    main.__builtins__ = builtins  # type: ignore[attr-defined]
    sys.modules['__main__'] = main
    if program.script is None:
        sys.path[0] = str(program.home())  # python -m puts the working directory first
        _run_module_as_main(str(program.module), alter_argv=True)
    elif pkgutil.get_importer(str(program.script)) is not None:
        # A folder or zip file: its __main__.py, found first on sys.path, as python runs it.
        sys.path[0] = str(program.script)
        _run_module_as_main('__main__', alter_argv=False)
    else:
        sys.path[0] = str(program.home())
        _run_file(program.script, main)


def _run_file(script: Path, main: types.ModuleType) -> None:
    """``python FILE``: its source, or the code of a compiled file, run in ``main``."""
    path = os.path.abspath(script)
    with io.open_code(path) as file:
        code = pkgutil.read_code(file)
    if code is None:
        with io.open_code(path) as file:
            # dont_inherit: this module's ``from __future__`` imports are not the program's.
            code = compile(file.read(), path, 'exec', dont_inherit=True)
        loader: Any = importlib.machinery.SourceFileLoader('__main__', path)
    else:
        loader = importlib.machinery.SourcelessFileLoader('__main__', path)
    main.__file__ = path
    main.__cached__ = None  # type: ignore[attr-defined]
    main.__loader__ = loader
    try:
        exec(code, vars(main))
    finally:  # as the interpreter does once a file has run
        vars(main).pop('__file__', None)
        vars(main).pop('__cached__', None)

