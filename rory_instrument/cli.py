"""``rory-instrument SRC --vars keyvars.yaml -o OUT``: copy SRC, instrumenting the listed nodes.

Everything is validated and rewritten in memory first; OUT is then built in a temporary
directory next to it and renamed into place, so an error never leaves a partial OUT.
"""

from __future__ import annotations

import argparse
import os
import posixpath
import shutil
import stat
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path, PurePosixPath

from libcst.metadata import MetadataWrapper

from rory_instrument.checks import ModuleFacts, collect_module
from rory_instrument.config import KeyVars, NodeSpec, load_keyvars
from rory_instrument.errors import InstrumentError, PathError
from rory_instrument.manifest import MANIFEST_NAME, ManifestEntry, render_manifest
from rory_instrument.packaging import DISTRIBUTION, declare_runtime
from rory_instrument.transform import instrument_source, parse_source

EXIT_OK = 0
EXIT_INPUT_ERROR = 2


def _check_out(out: str, src: Path) -> Path:
    """Returns OUT resolved, or raises if it may not be (re)placed.

    Args:
        out: OUT as given on the command line.
        src: SRC, resolved.

    Raises:
        PathError: OUT is SRC or inside it, contains SRC, or exists and is not a previous
            output (an empty directory is accepted too).
    """
    path = Path(out).resolve()
    if path == src or path.is_relative_to(src):
        raise PathError(out, 0, 0, f'OUT must not be SRC or inside it (SRC is {src})')
    if path.exists():
        if not path.is_dir():
            raise PathError(out, 0, 0, 'OUT exists and is not a directory')
        if src.is_relative_to(path):
            raise PathError(out, 0, 0, 'OUT contains SRC; refusing to replace it')
        if not (path / MANIFEST_NAME).is_file() and any(path.iterdir()):
            raise PathError(
                out, 0, 0,
                f'OUT exists and is not a rory-instrument output (no {MANIFEST_NAME}); '
                'refusing to replace it',
            )
    return path


def _source_file(keyvars: KeyVars, spec: NodeSpec, src: Path, src_shown: str) -> str:
    """Returns the POSIX path of ``spec.file`` relative to SRC, symlinks resolved.

    Raises:
        ConfigError: The file is absolute, outside SRC, or not a regular file.
    """
    if PurePosixPath(spec.file).is_absolute() or Path(spec.file).is_absolute():
        raise keyvars.error(spec, 'file', f'file {spec.file!r} must be relative to SRC')
    path = (src / spec.file).resolve()
    if not path.is_relative_to(src):
        raise keyvars.error(spec, 'file', f'file {spec.file!r} is outside SRC ({src_shown})')
    if not path.exists():
        raise keyvars.error(spec, 'file', f'file {spec.file!r} not found in SRC ({src_shown})')
    if not path.is_file():
        raise keyvars.error(spec, 'file', f'file {spec.file!r} is not a regular file')
    rel = path.relative_to(src).as_posix()
    if rel == MANIFEST_NAME:
        raise keyvars.error(spec, 'file', f'file {spec.file!r} is reserved for the manifest')
    return rel


def base_candidates(file: str, qualified: str) -> Iterator[tuple[str, str]]:
    """Yields the (module file, class name) pairs an imported class name may denote in SRC.

    ``.base.BaseNode`` (``from .base import BaseNode``) is looked for relative to ``file``'s
    folder; ``pkg.base.BaseNode`` relative to ``file``'s folder and each folder above it up
    to SRC, as Python would find it from the script's folder or an installed package. The
    longest module path comes first (``pkg/base.py`` for ``BaseNode`` before ``pkg.py`` for
    ``base.BaseNode``).

    Args:
        file: The importing file, relative to SRC.
        qualified: The qualified name libcst gives the base.

    Yields:
        A file relative to SRC (which may not exist) and a dotted class name.
    """
    name = qualified.lstrip('.')
    dots = len(qualified) - len(name)
    parts = name.split('.')
    here = posixpath.dirname(file) or '.'
    if dots:
        roots = [posixpath.normpath(posixpath.join(here, *['..'] * (dots - 1)))]
    else:
        roots = [here]
        while roots[-1] != '.':
            roots.append(posixpath.dirname(roots[-1]) or '.')
    for root in roots:
        if root == '..' or root.startswith('../'):
            continue
        for k in range(len(parts) - 1, 0, -1):
            module = posixpath.normpath(posixpath.join(root, *parts[:k]))
            for candidate in (f'{module}.py', f'{module}/__init__.py'):
                yield candidate, '.'.join(parts[k:])


class SourceTree:
    """Finds base classes of node classes in the other files of SRC.

    Used as the ``resolve`` of ``instrument_source``: a node class deriving from a Node
    subclass defined in another module of SRC is then a node too, and the attributes that
    class assigns count. Each file is parsed once.

    Args:
        src: SRC, resolved.
        src_shown: SRC as given on the command line, to name files in messages.
    """

    def __init__(self, src: Path, src_shown: str) -> None:
        self.src = src
        self.src_shown = src_shown
        self.modules: dict[str, ModuleFacts | None] = {}

    def __call__(self, module: ModuleFacts, qualified: str) -> tuple[ModuleFacts, str] | None:
        for file, class_name in base_candidates(module.file, qualified):
            found = self.module(file)
            if found is not None and class_name in found.classes:
                return found, class_name
        return None

    def module(self, file: str) -> ModuleFacts | None:
        """Returns the facts of a file of SRC, or None if there is no such regular file.

        Raises:
            SourceError: The file is not valid Python.
        """
        if file not in self.modules:
            path = (self.src / file).resolve()
            facts = None
            if path.is_relative_to(self.src) and path.is_file():
                display = str(Path(self.src_shown) / file)
                try:
                    source = path.read_bytes()
                except OSError:
                    source = None
                if source is not None:
                    wrapper = MetadataWrapper(parse_source(source, display))
                    facts = collect_module(wrapper, file, display)
            self.modules[file] = facts
        return self.modules[file]


def _ignore_manifest(src: Path) -> Callable[[str, list[str]], list[str]]:
    """Returns a copytree filter that skips SRC's own rory_manifest.json (a previous OUT)."""

    def ignore(directory: str, names: list[str]) -> list[str]:
        return [MANIFEST_NAME] if Path(directory) == src and MANIFEST_NAME in names else []

    return ignore


def _copy_tree(src: Path, tree: Path) -> None:
    """Copies SRC to ``tree``, symlinks as symlinks, except relative links to files outside SRC.

    A copied link keeps its text, so a relative one that leads out of SRC (``../shared/x.py``,
    a module several programs link in) would point at nothing in OUT, or at something else: it
    is copied as the file it points to. Links inside SRC, absolute links, links to directories
    and dangling links stay links.
    """
    shutil.copytree(src, tree, symlinks=True, ignore=_ignore_manifest(src))
    root = src.resolve()  # SRC may be given relative, or through a link
    for directory, _subdirs, names in os.walk(tree):
        for name in names:
            copied = Path(directory) / name
            if not copied.is_symlink() or Path(os.readlink(copied)).is_absolute():
                continue
            pointed = (root / copied.relative_to(tree)).resolve()
            if pointed.is_relative_to(root) or not pointed.is_file():
                continue
            copied.unlink()
            shutil.copy2(pointed, copied)


def _write_file(path: Path, data: bytes) -> None:
    """Overwrites a copied file, keeping its mode even if that mode is read-only."""
    mode = stat.S_IMODE(path.stat().st_mode)
    if not mode & stat.S_IWUSR:
        path.chmod(mode | stat.S_IWUSR)
    path.write_bytes(data)
    path.chmod(mode)


def _write_tree(src: Path, out: Path, files: dict[str, bytes],
                manifest: str) -> tuple[list[str], list[str]]:
    """Builds OUT next to itself and renames it into place, replacing a previous OUT.

    Returns:
        The package files that now declare RORY's runtime, and warnings about those left
        alone (``rory_instrument.packaging``).
    """
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f'.{out.name}.rory-', dir=out.parent))
    try:
        tree = staging / 'tree'
        _copy_tree(src, tree)
        for rel, code in files.items():
            _write_file(tree / rel, code)
        declared = declare_runtime(tree)
        (tree / MANIFEST_NAME).write_text(manifest, encoding='utf-8')
        old = staging / 'old'
        if out.exists():
            out.rename(old)
        try:
            tree.rename(out)
        except OSError:
            if old.exists():
                old.rename(out)
            raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return declared


def instrument_tree(
    src: str, keyvars_path: str, out: str | None, *, check: bool = False,
    warn: Callable[[str], None] | None = None,
    inform: Callable[[str], None] | None = None,
) -> list[ManifestEntry]:
    """Validates keyvars.yaml against SRC and, unless checking, writes OUT.

    Args:
        src: The source directory; relative paths resolve against the current directory.
        keyvars_path: keyvars.yaml.
        out: The output directory, or None to validate only.
        check: Validate only; write nothing even if ``out`` is given.
        warn: Gets each warning line (``file:line:col: warning: ...``).
        inform: Gets a line naming the package files that now declare RORY's runtime.

    Returns:
        One entry per instrumented node, in keyvars.yaml order.

    Raises:
        InstrumentError: Any problem with the inputs; nothing has been written.
    """
    src_dir = Path(src).resolve()
    if not src_dir.is_dir():
        raise PathError(src, 0, 0, 'SRC is not a directory')
    out_dir = None if out is None else _check_out(out, src_dir)
    keyvars = load_keyvars(keyvars_path, keyvars_path)

    tree = SourceTree(src_dir, src)
    by_file: dict[str, list[NodeSpec]] = {}
    for spec in keyvars.nodes:
        by_file.setdefault(_source_file(keyvars, spec, src_dir, src), []).append(spec)
    files: dict[str, bytes] = {}
    entries: list[tuple[int, ManifestEntry]] = []
    for rel, specs in by_file.items():
        display = str(Path(src) / rel)
        try:
            source = (src_dir / rel).read_bytes()
        except OSError as e:
            raise keyvars.error(specs[0], 'file', f'cannot read {rel}: {e.strerror}') from e
        result = instrument_source(source, keyvars, rel, display=display, specs=specs,
                                   resolve=tree)
        files[rel] = result.code
        if warn is not None:
            for line in result.warnings:
                warn(line)
        for done in result.classes:
            spec = done.spec
            entry = ManifestEntry(rel, spec.class_name, spec.vars, done.source_sha256,
                                  done.manifest, spec.checkpoint_interval, spec.replay,
                                  spec.module_vars)
            entries.append((spec.index, entry))
    ordered = [entry for _index, entry in sorted(entries, key=lambda pair: pair[0])]

    if out_dir is not None and not check:
        try:
            declared, warnings = _write_tree(src_dir, out_dir, files, render_manifest(ordered))
        except OSError as e:
            raise PathError(str(out), 0, 0, f'cannot write OUT: {e.strerror or e}') from e
        if declared and inform is not None:
            inform(f'declared {DISTRIBUTION} in {", ".join(declared)}')
        for line in warnings:
            if warn is not None:
                warn(f'{out_dir / line}'.replace(': ', ': warning: ', 1))
    return ordered


def _describe(entry: ManifestEntry) -> str:
    """Returns how the command line reports an entry: ``file:Class vars=a,b module_vars=c``."""
    parts = [entry.file if entry.class_name is None else f'{entry.file}:{entry.class_name}']
    if entry.class_name is not None:
        parts.append(f'vars={",".join(entry.vars)}')
    if entry.module_vars:
        parts.append(f'module_vars={",".join(entry.module_vars)}')
    return ' '.join(parts)


def build_parser() -> argparse.ArgumentParser:
    """Returns the command-line parser."""
    parser = argparse.ArgumentParser(
        prog='rory-instrument',
        description='Copy SRC to OUT, instrumenting the ROS 2 nodes listed in keyvars.yaml '
        '(node classes and the module globals of nodes written as functions) so that '
        'rory_runtime checkpoints and restores their state.',
    )
    parser.add_argument('src', metavar='SRC', help='directory with the node sources')
    parser.add_argument('--vars', required=True, metavar='KEYVARS',
                        help='keyvars.yaml: nodes to instrument and the variables they keep')
    parser.add_argument('-o', '--out', metavar='OUT',
                        help='output directory (required unless --check); replaced if it '
                        'is a previous output')
    parser.add_argument('--check', action='store_true',
                        help='validate only; write nothing')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Runs the command line.

    Args:
        argv: Arguments without the program name; defaults to ``sys.argv[1:]``.

    Returns:
        0 on success, 2 when the inputs are wrong (the message is on stderr).
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.out is None and not args.check:
        parser.error('the following arguments are required: -o/--out')
    try:
        entries = instrument_tree(args.src, args.vars, args.out, check=args.check,
                                  warn=lambda line: print(line, file=sys.stderr),
                                  inform=print)
    except InstrumentError as e:
        print(e, file=sys.stderr)
        return EXIT_INPUT_ERROR
    verb = 'checked' if args.check else 'instrumented'
    for entry in entries:
        print(f'{verb} {_describe(entry)}')
    return EXIT_OK
