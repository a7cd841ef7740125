"""``rory-instrument SRC --vars keyvars.yaml -o OUT``: copy SRC, instrumenting node classes.

Everything is validated and rewritten in memory first; OUT is then built in a temporary
directory next to it and renamed into place, so an error never leaves a partial OUT.
"""

from __future__ import annotations

import argparse
import shutil
import stat
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path, PurePosixPath

from rory_instrument.config import KeyVars, NodeSpec, load_keyvars
from rory_instrument.errors import InstrumentError, PathError
from rory_instrument.manifest import MANIFEST_NAME, ManifestEntry, render_manifest
from rory_instrument.transform import instrument_source

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


def _ignore_manifest(src: Path) -> Callable[[str, list[str]], list[str]]:
    """Returns a copytree filter that skips SRC's own rory_manifest.json (a previous OUT)."""

    def ignore(directory: str, names: list[str]) -> list[str]:
        return [MANIFEST_NAME] if Path(directory) == src and MANIFEST_NAME in names else []

    return ignore


def _write_file(path: Path, data: bytes) -> None:
    """Overwrites a copied file, keeping its mode even if that mode is read-only."""
    mode = stat.S_IMODE(path.stat().st_mode)
    if not mode & stat.S_IWUSR:
        path.chmod(mode | stat.S_IWUSR)
    path.write_bytes(data)
    path.chmod(mode)


def _write_tree(src: Path, out: Path, files: dict[str, bytes], manifest: str) -> None:
    """Builds OUT next to itself and renames it into place, replacing a previous OUT."""
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f'.{out.name}.rory-', dir=out.parent))
    try:
        tree = staging / 'tree'
        shutil.copytree(src, tree, symlinks=True, ignore=_ignore_manifest(src))
        for rel, code in files.items():
            _write_file(tree / rel, code)
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


def instrument_tree(
    src: str, keyvars_path: str, out: str | None, *, check: bool = False
) -> list[ManifestEntry]:
    """Validates keyvars.yaml against SRC and, unless checking, writes OUT.

    Args:
        src: The source directory; relative paths resolve against the current directory.
        keyvars_path: keyvars.yaml.
        out: The output directory, or None to validate only.
        check: Validate only; write nothing even if ``out`` is given.

    Returns:
        One entry per instrumented class, in keyvars.yaml order.

    Raises:
        InstrumentError: Any problem with the inputs; nothing has been written.
    """
    src_dir = Path(src).resolve()
    if not src_dir.is_dir():
        raise PathError(src, 0, 0, 'SRC is not a directory')
    out_dir = None if out is None else _check_out(out, src_dir)
    keyvars = load_keyvars(keyvars_path, keyvars_path)

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
        result = instrument_source(source, keyvars, rel, display=display, specs=specs)
        files[rel] = result.code
        for done in result.classes:
            spec = done.spec
            entry = ManifestEntry(rel, spec.class_name, spec.vars, done.source_sha256,
                                  done.manifest, spec.checkpoint_interval, spec.replay)
            entries.append((spec.index, entry))
    ordered = [entry for _index, entry in sorted(entries, key=lambda pair: pair[0])]

    if out_dir is not None and not check:
        try:
            _write_tree(src_dir, out_dir, files, render_manifest(ordered))
        except OSError as e:
            raise PathError(str(out), 0, 0, f'cannot write OUT: {e.strerror or e}') from e
    return ordered


def build_parser() -> argparse.ArgumentParser:
    """Returns the command-line parser."""
    parser = argparse.ArgumentParser(
        prog='rory-instrument',
        description='Copy SRC to OUT, instrumenting the ROS 2 node classes listed in '
        'keyvars.yaml so that rory_runtime checkpoints and restores their state.',
    )
    parser.add_argument('src', metavar='SRC', help='directory with the node sources')
    parser.add_argument('--vars', required=True, metavar='KEYVARS',
                        help='keyvars.yaml: classes to instrument and attributes to keep')
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
        entries = instrument_tree(args.src, args.vars, args.out, check=args.check)
    except InstrumentError as e:
        print(e, file=sys.stderr)
        return EXIT_INPUT_ERROR
    verb = 'checked' if args.check else 'instrumented'
    for entry in entries:
        print(f'{verb} {entry.file}:{entry.class_name} vars={",".join(entry.vars)}')
    return EXIT_OK
