"""Safe outputs: soft_rom never replaces what it did not write, and what it writes appears whole.

Every folder soft_rom creates as an output (a training set, a bag of predictions, a study
folder) carries a small marker file, :data:`MARKER`, naming what it is. ``--overwrite``
replaces an existing output only when that marker says soft_rom wrote it (a file output,
such as a model file, is recognised by a check the caller passes). A recording — a bag
that soft_rom did not write — is never replaced.

Outputs are built in a hidden staging folder next to their destination (same file system)
and moved into place at the end:

* a folder is swapped in with one atomic ``renameat2(RENAME_EXCHANGE)`` where the kernel
  and file system support it, so that at every instant either the old or the new output
  exists; elsewhere with two renames, and :func:`recover` (called before every write)
  restores the old one if a crash came between them;
* several files (:func:`atomic_files`, e.g. one model file per method and r) are staged
  together and moved in only when all were written; if moving one fails, the files
  already moved are put back.

The checks run before the output is built; what appears at the destination meanwhile
(another run writing the same path) is checked again when the output is moved in: without
``--overwrite`` it is never replaced (``renameat2(RENAME_NOREPLACE)`` / a hard link, atomic
where supported), with it only if soft_rom wrote it.

Staging folders left by a killed run are removed by the next run in the same folder
(:func:`clean_stale`); they are hidden and never read as outputs.

An output that records its own path while it is built (a study folder) is built in place
instead, the previous one parked aside: :mod:`soft_rom.outputs_inplace`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
import contextlib
import ctypes
import ctypes.util
import errno
import functools
import gzip
import json
import os
from pathlib import Path
import shutil
import uuid

from soft_rom.errors import ConfigError, OutputExistsError, ResourceError

__all__ = [
    'MARKER',
    'atomic_dir',
    'atomic_files',
    'atomic_new_dir',
    'check_free_space',
    'check_output',
    'clean_stale',
    'foreign_files',
    'is_marked',
    'make_parent',
    'mark',
    'recover',
    'refuse_foreign',
]

MARKER = '.soft_rom_output.json'
#: The files soft_rom wrote in a marked folder (relative paths, gzip'd text, one per line).
MANIFEST = '.soft_rom_output.files.gz'
_STAGE = '.soft_rom-stage-'
_OLD = '.soft_rom-old-'

Checker = Callable[[Path], bool]


def mark(folder: str | os.PathLike[str], kind: str, *, manifest: bool = True) -> None:
    """Write the marker that says soft_rom wrote ``folder`` as an output of ``kind``.

    With ``manifest`` (the default, for a folder soft_rom has just written whole) it also
    lists the files in it, so that ``--overwrite`` can refuse to delete files added to it
    later (:func:`foreign_files`); without (a folder that keeps growing, or one adopted from
    an earlier version), any list left from before is removed.
    """
    folder = Path(folder)
    folder.joinpath(MARKER).write_text(json.dumps({'writer': 'soft_rom', 'kind': kind}) + '\n')
    if manifest:
        with gzip.open(folder / MANIFEST, 'wt', encoding='utf-8') as fh:
            fh.write(''.join(f'{name}\n' for name in _listing(folder)))
    else:
        folder.joinpath(MANIFEST).unlink(missing_ok=True)


def _ours_hidden(name: str) -> bool:
    """A staging, parked or marker name of soft_rom's own (never a user's file)."""
    return name.startswith('.') and 'soft_rom' in name


def _listing(folder: Path) -> list[str]:
    """The files (and links) under ``folder``, relative, without soft_rom's hidden ones."""
    names = []
    for root, dirs, files in os.walk(folder):
        rel = Path(root).relative_to(folder)
        links = [d for d in dirs if os.path.islink(os.path.join(root, d))]
        dirs[:] = [d for d in dirs if not _ours_hidden(d) and d not in links]
        names += [(rel / n).as_posix() for n in files + links if not _ours_hidden(n)]
    return sorted(names)


def foreign_files(folder: str | os.PathLike[str]) -> list[str]:
    """Files in a marked ``folder`` that were not there when soft_rom wrote it.

    Empty for a folder without a list of its files (written by an earlier version, or still
    growing): then there is nothing to compare with.

    Raises
    ------
    OutputExistsError
        The list is there but unreadable.
    """
    folder = Path(folder)
    path = folder / MANIFEST
    if not path.is_file():
        return []
    try:
        with gzip.open(path, 'rt', encoding='utf-8') as fh:
            known = set(fh.read().splitlines())
    except (OSError, ValueError, EOFError) as err:
        raise OutputExistsError(f'{folder}: its list of the files soft_rom wrote ({MANIFEST}) '
                                f'is unreadable ({err}); refusing to replace it') from None
    return [name for name in _listing(folder) if name not in known]


def refuse_foreign(folder: str | os.PathLike[str]) -> None:
    """Refuse to replace a soft_rom folder that holds files added since it was written."""
    extra = foreign_files(folder)
    if extra:
        more = f' and {len(extra) - 3} more' if len(extra) > 3 else ''
        raise OutputExistsError(
            f'{folder} holds files soft_rom did not write there ({", ".join(extra[:3])}{more}); '
            '--overwrite would delete them: move them out, or choose another output')


def is_marked(path: str | os.PathLike[str], kinds: Sequence[str] | None = None) -> bool:
    """Whether ``path`` is a folder soft_rom wrote (of one of ``kinds``, if given)."""
    marker = Path(path, MARKER)
    try:
        if not marker.is_file() or marker.stat().st_size > 4096:
            return False
        info = json.loads(marker.read_text())
    except (OSError, ValueError):
        return False
    if not isinstance(info, dict) or info.get('writer') != 'soft_rom':
        return False
    return kinds is None or info.get('kind') in kinds


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def clean_stale(parent: str | os.PathLike[str]) -> None:
    """Remove staging folders in ``parent`` left by soft_rom runs that no longer exist."""
    try:
        entries = list(Path(parent).iterdir())
    except OSError:
        return
    for entry in entries:
        if not entry.name.startswith('.') or _STAGE not in entry.name:
            continue
        try:
            pid = int(entry.name.split(_STAGE, 1)[1].split('-', 1)[0])
        except ValueError:
            continue
        if not _pid_alive(pid):
            shutil.rmtree(entry, ignore_errors=True) if entry.is_dir() else entry.unlink(
                missing_ok=True)


def _old_copies(dest: Path) -> list[Path]:
    prefix = f'.{dest.name}{_OLD}'
    try:
        return sorted(p for p in dest.parent.iterdir() if p.name.startswith(prefix))
    except OSError:
        return []


def recover(dest: str | os.PathLike[str]) -> None:
    """Finish or undo a folder swap that a crash interrupted.

    If ``dest`` is missing and an old copy of it is parked beside it, the old copy is put
    back; if ``dest`` exists, parked old copies are removed.
    """
    dest = Path(dest)
    olds = _old_copies(dest)
    if not olds:
        return
    if not dest.exists():
        os.rename(olds[-1], dest)
        olds = olds[:-1]
    for old in olds:
        shutil.rmtree(old, ignore_errors=True)


def check_output(dest: str | os.PathLike[str], *, overwrite: bool, what: str,
                 kinds: Sequence[str] | None = None, is_ours: Checker | None = None) -> None:
    """Refuse to write ``dest`` unless it is new, or ours and ``overwrite`` is set.

    Parameters
    ----------
    dest : path
        The output (folder or file).
    overwrite : bool
        Whether the user asked to replace an existing output.
    what : str
        What the output is, for messages (``'training set'``, ``'model file'``).
    kinds : sequence of str, optional
        Marker kinds accepted for a folder.
    is_ours : callable, optional
        For a file output: ``is_ours(path)`` says whether soft_rom wrote it.

    Raises
    ------
    OutputExistsError
        ``dest`` exists and ``overwrite`` is not set, or it exists and soft_rom did not
        write it.
    """
    dest = Path(dest)
    recover(dest)
    if not dest.exists() and not dest.is_symlink():
        return
    if not overwrite:
        raise OutputExistsError(f'{dest} exists already; choose another output or pass '
                                f'--overwrite to replace it')
    if is_ours is not None:
        # A file output never replaces a folder, whoever wrote it (a training set, a bag).
        if dest.is_dir():
            raise OutputExistsError(f'{dest} is a folder, but the {what} is a file; refusing '
                                    'to replace the folder (choose a file name)')
        ours = dest.is_file() and is_ours(dest)
    else:
        ours = dest.is_dir() and not dest.is_symlink() and is_marked(dest, kinds)
    if not ours:
        raise OutputExistsError(f'{dest} was not written by soft_rom as a {what}; refusing to '
                                f'replace it (--overwrite only replaces soft_rom outputs)')
    if is_ours is None:
        refuse_foreign(dest)


def make_parent(folder: Path, what: str) -> None:
    """Create the folder an output goes into, with errors that name it, not a staging path.

    Raises ``NotADirectoryError`` when a file stands where a folder of the path should be,
    the ``OSError`` naming ``folder`` when it cannot be written (no permission, no space),
    and ``ConfigError`` when files cannot be created there at all (``/proc``).
    """
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, 'Not a directory', str(probe))
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe_file = folder / f'.{_STAGE}probe-{os.getpid()}-{uuid.uuid4().hex[:8]}'
        probe_file.mkdir()
        probe_file.rmdir()
    except OSError as err:
        if err.errno in (errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOSPC, errno.EDQUOT):
            raise type(err)(err.errno, err.strerror, str(folder)) from None   # run time: 1
        raise ConfigError(f'cannot write the {what} in {folder} '
                          f'({err.strerror or err})') from None


def _stage_path(dest: Path) -> Path:
    return dest.parent / f'.{dest.name}{_STAGE}{os.getpid()}-{uuid.uuid4().hex[:8]}'


_libc: list[ctypes.CDLL | None] = []


def _renameat2(a: Path, b: Path, flags: int) -> int:
    """``renameat2(a, b, flags)`` (Linux): 0 on success, else the errno.

    -1 where the C library has no ``renameat2``.
    """
    if not _libc:
        name = ctypes.util.find_library('c')
        try:
            _libc.append(ctypes.CDLL(name, use_errno=True) if name else None)
        except OSError:
            _libc.append(None)
    libc = _libc[0]
    if libc is None or not hasattr(libc, 'renameat2'):
        return -1
    at_fdcwd = -100
    rc = libc.renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), flags)
    return 0 if rc == 0 else ctypes.get_errno()


def _exchange(a: Path, b: Path) -> bool:
    """Atomically exchange two paths (Linux ``renameat2``); False where unsupported."""
    return _renameat2(a, b, 2) == 0          # RENAME_EXCHANGE


def _move_new(stage: Path, dest: Path) -> bool:
    """Move ``stage`` to ``dest`` only if ``dest`` does not exist; False if it does.

    One ``renameat2(RENAME_NOREPLACE)`` where the kernel and file system support it, so an
    output that appeared after the checks (another run writing the same path) is never
    replaced; elsewhere a check followed by a rename.
    """
    rc = _renameat2(stage, dest, 1)          # RENAME_NOREPLACE
    if rc == 0:
        return True
    if rc == errno.EEXIST:
        return False
    if dest.exists() or dest.is_symlink():
        return False
    os.rename(stage, dest)
    return True


def _swap_in(stage: Path, dest: Path, *, overwrite: bool, recheck: Callable[[], None],
             what: str) -> None:
    """Put the staged output at ``dest``.

    The checks ran before the output was built, maybe minutes ago: something may have
    appeared at ``dest`` since (another soft_rom run writing the same path, a user's
    folder). Without ``overwrite`` it is never replaced; with it, ``recheck`` (the same
    checks) runs again on what is there now, just before the exchange.
    """
    if _move_new(stage, dest):
        return
    if not overwrite:
        raise OutputExistsError(f'{dest} appeared while the {what} was being written (another '
                                'soft-rom run?); nothing was replaced: choose another output '
                                'or pass --overwrite')
    recheck()
    if _exchange(stage, dest):
        shutil.rmtree(stage, ignore_errors=True)  # stage now holds the old output
        return
    old = dest.parent / f'.{dest.name}{_OLD}{os.getpid()}-{uuid.uuid4().hex[:8]}'
    os.rename(dest, old)
    try:
        os.rename(stage, dest)
    except BaseException:
        os.rename(old, dest)
        raise
    shutil.rmtree(old, ignore_errors=True)


def _new_stage(dest: str | os.PathLike[str], overwrite: bool, kind: str, what: str,
               kinds: Sequence[str] | None) -> tuple[Path, Path]:
    """Check ``dest`` may be written; create and return ``(dest, an empty staging folder)``."""
    dest = Path(dest)
    make_parent(dest.parent, what)
    clean_stale(dest.parent)
    check_output(dest, overwrite=overwrite, what=what, kinds=kinds or (kind,))
    stage = _stage_path(dest)
    stage.mkdir()
    return dest, stage


@contextlib.contextmanager
def atomic_dir(dest: str | os.PathLike[str], *, overwrite: bool, kind: str, what: str,
               kinds: Sequence[str] | None = None) -> Iterator[Path]:
    """Build a folder output in a staging folder and swap it into place on success.

    Yields the staging folder. On an exception (or Ctrl-C) the staging folder is removed
    and ``dest`` is left as it was; on success the marker for ``kind`` is written and the
    folder replaces ``dest`` atomically (see the module docstring).
    """
    dest, stage = _new_stage(dest, overwrite, kind, what, kinds)
    try:
        yield stage
        mark(stage, kind)
        _swap_in(stage, dest, overwrite=overwrite, what=what, recheck=functools.partial(
            check_output, dest, overwrite=True, what=what, kinds=kinds or (kind,)))
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise


@contextlib.contextmanager
def atomic_new_dir(dest: str | os.PathLike[str], *, overwrite: bool, kind: str, what: str,
                   kinds: Sequence[str] | None = None) -> Iterator[Path]:
    """Like :func:`atomic_dir`, for writers that create their folder themselves.

    Yields a staging path that does not exist yet (e.g. for a bag writer, which refuses
    an existing folder); the caller creates the folder there. If it does not, nothing
    changes at ``dest``.
    """
    dest, parent = _new_stage(dest, overwrite, kind, what, kinds)
    stage = parent / dest.name  # same name as the output: writers name their files after it
    try:
        yield stage
        if not stage.is_dir():
            raise OutputExistsError(f'internal: the {what} was not written')
        mark(stage, kind)
        _swap_in(stage, dest, overwrite=overwrite, what=what, recheck=functools.partial(
            check_output, dest, overwrite=True, what=what, kinds=kinds or (kind,)))
    finally:
        shutil.rmtree(parent, ignore_errors=True)


@contextlib.contextmanager
def atomic_files(dests: Sequence[str | os.PathLike[str]], *, overwrite: bool, what: str,
                 is_ours: Checker | None = None) -> Iterator[dict[Path, Path]]:
    """Write several files so that they appear all together or not at all.

    Every destination is checked with :func:`check_output` before anything is written.
    Yields ``{destination: staging path}``; the caller writes each staging path. On
    success every file is moved into place; if one move fails, the ones already moved are
    put back as they were. On an exception nothing at the destinations changes.
    """
    paths = [Path(d) for d in dests]
    if len(set(paths)) != len(paths):
        raise OutputExistsError(f'two {what}s would be written to the same path')
    for parent in {p.parent for p in paths}:
        make_parent(parent, what)
        clean_stale(parent)
    for p in paths:
        check_output(p, overwrite=overwrite, what=what, is_ours=is_ours)
    stages = {p.parent: _stage_path(p.parent / 'files') for p in paths}
    for stage in stages.values():
        stage.mkdir()
    mapping = {p: stages[p.parent] / p.name for p in paths}
    moved: list[tuple[Path, Path | None]] = []
    try:
        yield mapping
        missing = [str(p) for p, s in mapping.items() if not s.is_file()]
        if missing:
            raise OutputExistsError(f'internal: {what}s not written: {", ".join(missing)}')
        for p, s in mapping.items():
            backup = None
            if _link_new(s, p):
                moved.append((p, None))
                continue
            # p appeared since the checks (another run?) or exists: the checks again, now
            if not overwrite:
                raise OutputExistsError(f'{p} appeared while the {what} was being written '
                                        '(another soft-rom run?); nothing was replaced: '
                                        'choose another output or pass --overwrite')
            check_output(p, overwrite=True, what=what, is_ours=is_ours)
            backup = s.with_name(s.name + '.previous')
            os.replace(p, backup)
            moved.append((p, backup))
            os.replace(s, p)
    except BaseException:
        for p, backup in reversed(moved):
            with contextlib.suppress(OSError):
                if backup is not None:
                    os.replace(backup, p)
                else:
                    p.unlink(missing_ok=True)
        raise
    finally:
        for stage in stages.values():
            shutil.rmtree(stage, ignore_errors=True)


def _link_new(staged: Path, dest: Path) -> bool:
    """Put the staged file at ``dest`` only if nothing is there; False if something is.

    A hard link is created atomically or not at all (``dest`` existing), then the staged
    name is removed; where links are not supported, a check followed by a rename.
    """
    try:
        os.link(staged, dest)
    except FileExistsError:
        return False
    except OSError:
        if dest.exists() or dest.is_symlink():
            return False
        os.replace(staged, dest)
        return True
    staged.unlink()
    return True


def check_free_space(folder: str | os.PathLike[str], nbytes: float, what: str) -> None:
    """Refuse work that would need more disk than ``folder``'s file system has free.

    Raises
    ------
    ResourceError
        With the estimate and what is free.
    """
    folder = Path(folder)
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    free = shutil.disk_usage(folder).free
    if nbytes > free:
        raise ResourceError(f'{what} needs about {nbytes / 1e9:.3g} GB on disk, only '
                            f'{free / 1e9:.3g} GB free in {folder}')

