"""Folder outputs built in place: the previous one comes back if the build stops.

An output that records its own path while it is built (a study folder: its training set
names its bags, its model files name their training set) cannot be built under another
name and swapped in (:func:`soft_rom.outputs.atomic_dir`). :func:`rebuilt_dir` builds it
in place instead: the previous one is parked under a hidden name first and comes back if
the build stops (an exception, Ctrl-C, SIGTERM), so the folder is never a mix of old and
new; a build killed outright leaves a folder marked incomplete, which the next run at that
path replaces by the parked one (:func:`restore_interrupted`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
import contextlib
import json
import os
from pathlib import Path
import shutil
import signal
import threading
import uuid

from soft_rom.errors import OutputExistsError
from soft_rom.outputs import (
    _pid_alive,
    check_output,
    clean_stale,
    make_parent,
    mark,
    MARKER,
)

__all__ = ['rebuilt_dir', 'restore_interrupted']

_PARKED = '.soft_rom-previous-'
_INCOMPLETE = 'incomplete'


def _marker_info(folder: Path) -> dict[str, object]:
    marker = folder / MARKER
    try:
        if not marker.is_file() or marker.stat().st_size > 4096:
            return {}
        info = json.loads(marker.read_text())
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) and info.get('writer') == 'soft_rom' else {}


def restore_interrupted(dest: str | os.PathLike[str]) -> None:
    """Undo a :func:`rebuilt_dir` build that was killed before it could clean up.

    ``dest`` marked incomplete by a process that no longer runs is removed and the
    folder it parked (if any) put back. A build still running is refused.

    Raises
    ------
    OutputExistsError
        Another soft_rom run is building ``dest`` now.
    """
    dest = Path(dest)
    if dest.is_symlink() or not dest.is_dir():
        return
    info = _marker_info(dest)
    if info.get('kind') != _INCOMPLETE:
        return
    pid = info.get('pid')
    if isinstance(pid, int) and pid != os.getpid() and _pid_alive(pid):
        raise OutputExistsError(f'{dest} is being written by another soft-rom run (process '
                                f'{pid}); wait for it to finish or choose another output')
    parked = info.get('previous')
    shutil.rmtree(dest, ignore_errors=True)
    if isinstance(parked, str) and parked.startswith(f'.{dest.name}{_PARKED}'):
        old = dest.parent / parked
        if old.is_dir() and not dest.exists():
            os.rename(old, dest)


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Ctrl-C and SIGTERM wait until the block is done (main thread; elsewhere no change)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    old = {sig: signal.signal(sig, lambda n, _f: caught.append(n))
           for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    if caught:
        signal.raise_signal(caught[0])


@contextlib.contextmanager
def _terminate_raises() -> Iterator[None]:
    """SIGTERM raises ``SystemExit`` (so cleanup runs as for Ctrl-C), main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    old = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


@contextlib.contextmanager
def rebuilt_dir(dest: str | os.PathLike[str], *, overwrite: bool, kind: str, what: str,
                kinds: Sequence[str] | None = None,
                carry_over: Callable[[Path, Path], None] | None = None) -> Iterator[Path]:
    """Build a folder output at its own path; the previous one comes back if the build stops.

    ``dest`` is checked like :func:`check_output` (new, or ours and ``overwrite``). An
    existing one is parked under a hidden name beside it, and ``dest`` is created empty,
    marked incomplete (with this process and the parked name), and yielded. On success the
    marker for ``kind`` is written and the parked folder removed. On an exception, Ctrl-C or
    SIGTERM the new folder is removed and the parked one put back (signals wait until that
    is done). If the process is killed outright, :func:`restore_interrupted` -- called
    here, before the checks -- does the same at the next run.

    Parameters
    ----------
    carry_over : callable, optional
        ``carry_over(parked, dest)`` before the build, to reuse parts of the previous
        output (e.g. hard links to its recorded episodes); it must not change ``parked``.
    """
    dest = Path(dest)
    make_parent(dest.parent, what)
    clean_stale(dest.parent)
    restore_interrupted(dest)
    check_output(dest, overwrite=overwrite, what=what, kinds=kinds or (kind,))
    parked: Path | None = None
    created = False
    with _terminate_raises():
        try:
            with _signals_held():          # a Ctrl-C here is raised when the block ends
                if dest.exists():
                    parked = dest.parent / (f'.{dest.name}{_PARKED}{os.getpid()}-'
                                            f'{uuid.uuid4().hex[:8]}')
                    os.rename(dest, parked)
                dest.mkdir()
                created = True
                Path(dest, MARKER).write_text(json.dumps(
                    {'writer': 'soft_rom', 'kind': _INCOMPLETE, 'of': kind,
                     'pid': os.getpid(), 'previous': parked.name if parked else None}) + '\n')
            if carry_over is not None and parked is not None:
                carry_over(parked, dest)
            yield dest
            mark(dest, kind)
        except BaseException:
            with _signals_held():
                if created:
                    shutil.rmtree(dest, ignore_errors=True)
                if parked is not None and not dest.exists():
                    os.rename(parked, dest)
            raise
    if parked is not None:
        shutil.rmtree(parked, ignore_errors=True)
