"""The chunked on-disk training set (zarr), written by ``soft-rom convert`` and read by the fits.

Layout (zarr format 2 on disk, so zarr 2.16+ and zarr 3.x both read and write it, and
:func:`dask.array.from_zarr` reads it on a cluster)::

    OUT.zarr/                      attrs: format='soft_rom.trainingset', format_version=2,
                                          input_names, input_units, output_names,
                                          output_units, episode_names, provenance, ...
        q_ref      (n,)            reference configuration (absent without states)
        y_ref      (p,)            reference output
        episodes/<name>/           attrs: metadata (t0_ns, source bag, topics, report)
            t      (k,)            seconds from the episode's start: t[0] = 0, increasing
            U      (m, k)          inputs, absolute
            Y      (p, k)          outputs, absolute
            Q      (n, k)          optional full states, absolute, float64

Arrays follow the package convention ``(n_channels, n_samples)``, float64. ``Q`` is chunked in
blocks of ``(min(n, 32768), 32)`` (8 MiB), uncompressed, Fortran order inside a chunk: a column
block of 32 snapshots reads ``ceil(n / 32768)`` whole chunks (the streaming POD's randomized
range finder) and a row block reads whole chunks too (its Gram pass), so both access patterns
of :mod:`soft_rom.scale` read every stored byte once per pass. Fortran order makes each
snapshot contiguous inside a chunk file, so the writer appends each snapshot to the open
chunk files of its chunk column straight from the buffer it arrived in
(:class:`_ChunkFileWriter`); compression is off because it would cost a CPU pass per snapshot
on a 2-core machine for data (float64 positions) that compresses poorly. The writer holds at
most 16 snapshots waiting to be written.

Time: ``t`` is float seconds from the episode's own start (``t[0] = 0``); the absolute start
is the integer ``metadata['t0_ns']`` (nanoseconds, e.g. the epoch stamp of the first sample),
so a recording stamped at 1.7e9 s keeps its sample times exact. Format version 1 stored
absolute seconds; such a set is read with its times shifted to ``t[0] = 0`` when its stamps
are small enough to be exact (below 1e4 s), and refused with the command that converts its
bags again otherwise.

A training set is written atomically through :func:`soft_rom.outputs.atomic_dir`: into a
hidden staging folder next to the target, marked as a soft_rom output and swapped into place
only when :class:`TrainingSetWriter` closes without an exception. ``overwrite`` replaces only
a folder soft_rom wrote as a training set; a training set written before the marker existed
is recognised by its ``format`` attribute (a bag or any other folder is refused).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator, Mapping, Sequence
import contextlib
import json
import os
from pathlib import Path
import queue
import shlex
import threading
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom import data as signals
from soft_rom import outputs
from soft_rom.data import all_finite, as_signal, Episode
from soft_rom.errors import DatasetError, DimensionError

__all__ = ['FORMAT', 'FORMAT_VERSION', 'KIND', 'EpisodeWriter', 'TrainingSet',
           'TrainingSetWriter']

FORMAT = 'soft_rom.trainingset'
FORMAT_VERSION = 2
#: Marker kind of a training-set folder (:mod:`soft_rom.outputs`).
KIND = 'trainingset'
#: Format version 1 (absolute times) is read when every episode starts before this (s).
V1_MAX_START_S = 1e4
#: Default ``Q`` chunk: rows (at most) and columns.
Q_CHUNK_ROWS = 32768
Q_CHUNK_COLS = 32


def _zarr() -> Any:
    try:
        import zarr
    except ImportError as err:  # pragma: no cover - zarr is a hard dependency
        raise DatasetError('the training-set format needs the zarr package: '
                           'pip install zarr') from err
    return zarr


def _open_group(path: Path, mode: str) -> Any:
    zarr = _zarr()
    major = int(str(zarr.__version__).split('.')[0])
    if mode == 'w' and major >= 3:
        return zarr.open_group(str(path), mode=mode, zarr_format=2)
    return zarr.open_group(str(path), mode=mode)


def _create_array(group: Any, name: str, shape: tuple[int, ...], chunks: tuple[int, ...],
                  data: NDArray[Any] | None = None, compress: bool = True,
                  order: str = 'C') -> Any:
    """Create a float64 array under ``group`` with the zarr 3 or the zarr 2 API."""
    chunks = tuple(max(int(c), 1) for c in chunks)
    if hasattr(group, 'create_array'):  # zarr 3
        kw: dict[str, Any] = {} if compress else {'compressors': None}
        arr = group.create_array(name, shape=shape, chunks=chunks, dtype='f8',
                                 fill_value=0.0, order=order, **kw)
    else:  # zarr 2
        kw = {} if compress else {'compressor': None}
        arr = group.create_dataset(name, shape=shape, chunks=chunks, dtype='f8',
                                   fill_value=0.0, order=order, **kw)
    if data is not None and data.size:
        arr[...] = data
    return arr


def _jsonable(obj: Any, what: str) -> Any:
    """``obj`` converted to plain JSON types (numpy scalars and arrays become lists)."""
    def default(o: Any) -> Any:
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f'{type(o).__name__} is not JSON-serialisable')
    try:
        return json.loads(json.dumps(obj, default=default, allow_nan=True))
    except (TypeError, ValueError) as err:
        raise DatasetError(f'{what} must be JSON-serialisable: {err}') from err


def _check_name(name: str) -> str:
    name = str(name)
    if not name or '/' in name or '\\' in name or name.startswith('.') or name != name.strip():
        raise DatasetError(f'episode name {name!r} is not valid: use a non-empty name without '
                           "'/' that does not start with '.'.")
    return name


class _ChunkFileWriter:
    """Writes the uncompressed zarr (format 2) chunk files of ``Q`` from a background thread.

    ``Q`` is stored in Fortran order: an uncompressed zarr v2 chunk is then the raw bytes of
    its columns one after the other (edge chunks padded with the fill value), in a file named
    ``'<i>.<j>'``. The files of the chunk column being filled stay open and each snapshot is
    appended to them (its row block ``i`` to file ``i``) as it arrives, straight from the
    array it arrived in: no copy, and the message buffer is released a few snapshots later
    (holding whole chunk columns of message buffers made every new message land in fresh
    pages, whose page faults cost more than a copy). Writes are at most 1 MiB (larger ones
    were several times slower on Linux). A background thread overlaps the writes with
    reading the bag; at most ``queue_size`` snapshots wait for it. With ``drop_cache`` the
    written files are evicted from the page cache ``drop_lag`` files behind the writer
    (``POSIX_FADV_DONTNEED``: the first call starts their write-back, a later one drops the
    clean pages), so that gigabytes of ``Q`` recycle the same pages instead of filling the
    page cache (measured 3-4x faster to write). The array's shape is updated through zarr
    when the episode is finished.
    """

    queue_size = 16
    drop_lag = 16       # chunk files (8 MiB each) left in the page cache behind the writer

    def __init__(self, directory: Path, n: int, chunks: tuple[int, int], separator: str,
                 drop_cache: bool = True) -> None:
        self.directory = directory
        self.n = n
        self.rows, self.cols = chunks
        self.separator = separator
        self.drop_cache = drop_cache and hasattr(os, 'posix_fadvise')
        self.n_blocks = -(-n // self.rows)
        self._zeros = np.zeros(self.rows, dtype=np.float64)
        self._queue: queue.Queue[Any] = queue.Queue(self.queue_size)
        self._count = 0                                  # snapshots queued
        self._fds: list[int] = []                        # files of the open chunk column
        self._paths: list[Path] = []
        self._open_j = -1
        self._filled = 0                                 # columns in the open chunk column
        self._written: deque[Path] = deque()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name='soft_rom-q-writer',
                                        daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    self._close_files(pad=False)
                    return
                if self._error is not None:
                    continue
                if item == 'flush':
                    self._close_files(pad=True)
                else:
                    self._write_column(*item)
            except BaseException as err:  # noqa: BLE001 - re-raised in the caller's thread
                self._error = err
                try:
                    self._close_files(pad=False)
                except OSError:
                    pass

    def _write_column(self, index: int, col: NDArray[np.float64]) -> None:
        j = index // self.cols
        if j != self._open_j:
            self._close_files(pad=True)
            for i in range(self.n_blocks):
                path = self.directory / f'{i}{self.separator}{j}'
                self._fds.append(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644))
                self._paths.append(path)
            self._open_j, self._filled = j, 0
        for i, fd in enumerate(self._fds):
            r0 = i * self.rows
            h = min(self.rows, self.n - r0)
            _write_all(fd, [col[r0:r0 + h]] if h == self.rows else
                       [col[r0:r0 + h], self._zeros[:self.rows - h]])
        self._filled += 1

    def _close_files(self, pad: bool) -> None:
        """Close the open chunk column (``pad``: fill its missing columns with zeros)."""
        fds, paths, self._fds, self._paths = self._fds, self._paths, [], []
        self._open_j = -1
        try:
            if pad:
                for fd in fds:
                    _write_all(fd, [self._zeros] * (self.cols - self._filled))
                    if self.drop_cache:      # starts writing it back now
                        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            for fd in fds:
                os.close(fd)
        if pad and self.drop_cache:
            # drop-behind: evict chunk files written a while ago, by now written back, so
            # that their pages are reused instead of the page cache growing by all of Q
            self._written.extend(paths)
            while len(self._written) > self.drop_lag:
                _drop_pages(self._written.popleft())

    def _check(self) -> None:
        if self._error is not None:
            raise DatasetError(f'writing Q chunks to {self.directory} failed: '
                               f'{self._error}') from self._error

    def append(self, column: NDArray[Any], copy: bool = True) -> None:
        """Queue one snapshot ``(n,)`` (any real dtype).

        Without ``copy`` a contiguous float64 ``column`` is written from as it is: the
        caller must not modify it afterwards.
        """
        self._check()
        if copy:
            col = np.array(column, dtype=np.float64)
        else:
            col = np.ascontiguousarray(column, dtype=np.float64)
        self._queue.put((self._count, col))
        self._count += 1

    def flush(self) -> None:
        """Complete the chunk column being filled (a partial one is padded with zeros)."""
        self._check()
        self._queue.put('flush')

    def close(self) -> None:
        """Wait for every queued snapshot; raise if one failed (an open column is dropped)."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        self._check()


def _drop_pages(path: Path) -> None:
    """Ask the kernel to evict the (written back) pages of ``path`` from the page cache."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


#: Largest single ``write``: measured on Linux/ext4, writing 8 MiB chunk files in one call
#: (or one ``writev``) was 4-10x slower (kernel time copying into fresh page-cache folios)
#: than writing them in 1 MiB pieces, which run at memory-copy speed.
_WRITE_PIECE = 1 << 20


def _write_all(fd: int, parts: list[Any]) -> None:
    """Write every buffer of ``parts`` to ``fd`` in pieces of ``_WRITE_PIECE`` bytes."""
    for part in parts:
        view = memoryview(part).cast('B')
        while view.nbytes:
            view = view[os.write(fd, view[:_WRITE_PIECE]):]


class EpisodeWriter:
    """Appends samples of one episode; obtained from :meth:`TrainingSetWriter.begin_episode`.

    Small arrays (``t``, ``U``, ``Y``) are kept in memory until the episode is finished;
    ``Q`` goes to disk one chunk column at a time. Times are seconds; they are stored from
    the first one (``t[0] = 0``) and that first time is added to ``t0_ns``.
    """

    def __init__(self, owner: TrainingSetWriter, group: Any, name: str, n_states: int | None,
                 metadata: Mapping[str, Any] | None, q_chunks: tuple[int, int],
                 t0_ns: int = 0) -> None:
        self._owner = owner
        self.t0_ns = int(t0_ns)
        self._group = group
        self.name = name
        self.n_states = None if n_states is None else int(n_states)
        self.metadata = _jsonable(dict(metadata or {}), f'metadata of episode {name!r}')
        self._q_chunks = q_chunks
        self._t: list[NDArray[np.float64]] = []
        self._U: list[NDArray[np.float64]] = []
        self._Y: list[NDArray[np.float64]] = []
        self._Q: Any = None
        self._qfiles: _ChunkFileWriter | None = None
        self._qwritten = 0
        self._has_q: bool | None = None
        self._last_t = -np.inf
        self.n_samples = 0
        self.first_q: NDArray[np.float64] | None = None
        self.first_y: NDArray[np.float64] | None = None
        self.closed = False
        self.discarded = False

    def append(self, t: ArrayLike, U: ArrayLike, Y: ArrayLike, Q: ArrayLike | None = None) -> None:
        """Append ``k`` samples.

        Parameters
        ----------
        t : array_like, shape (k,)
            Times in seconds, strictly increasing, continuing the previous appends.
        U : array_like, shape (m, k)
        Y : array_like, shape (p, k)
        Q : array_like, shape (n, k), optional
            Given on every append of the episode or on none.
        """
        k = np.asarray(t).size
        has_q = Q is not None
        if self._has_q is not None and self._has_q != has_q:
            raise DimensionError(f'episode {self.name!r}: Q must be given on every append or on '
                                 'none.')
        if has_q:
            shape: tuple[int, ...] = tuple(getattr(Q, 'shape', None) or np.shape(np.asarray(Q)))
            if len(shape) != 2 or shape[1] != k:
                raise DimensionError(f'episode {self.name!r}: Q must have shape (n, {k}); '
                                     f'got {tuple(shape)}.')
            if self.n_states is not None and shape[0] != self.n_states:
                raise DimensionError(f'episode {self.name!r}: Q must have {self.n_states} '
                                     f'rows; got {shape[0]}.')
            if not all_finite(np.asarray(Q)):
                raise DimensionError(f'episode {self.name!r}: Q contains NaN or Inf.')
        self.append_signals(t, U, Y)
        self._has_q = has_q
        if has_q and k:
            self.append_states(Q, check_finite=False)

    def append_signals(self, t: ArrayLike, U: ArrayLike, Y: ArrayLike) -> None:
        """Append ``t`` (k,), ``U`` (m, k), ``Y`` (p, k) without states.

        With :meth:`append_states` this lets a streaming producer (the bag converter) send
        state columns as they arrive and the signals later; the number of state columns must
        equal the number of samples when the episode is finished.
        """
        if self.closed:
            raise DatasetError(f'episode {self.name!r} is finished; begin a new one.')
        tt = np.asarray(t, dtype=np.float64).reshape(-1)
        k = tt.size
        if k == 0:
            return
        U = as_signal('U', U, rows=len(self._owner.input_names), cols=k)
        Y = as_signal('Y', Y, rows=len(self._owner.output_names), cols=k)
        for label, arr in (('t', tt), ('U', U), ('Y', Y)):
            if not all_finite(arr):
                raise DimensionError(f'episode {self.name!r}: {label} contains NaN or Inf.')
        if tt[0] <= self._last_t or (k > 1 and np.any(np.diff(tt) <= 0)):
            raise DimensionError(f'episode {self.name!r}: times must be strictly increasing '
                                 f'(near t = {tt[0]:.9f} s).')
        if self.first_y is None:
            self.first_y = Y[:, 0].copy()
        self._t.append(tt.copy())
        self._U.append(U.copy())
        self._Y.append(Y.copy())
        self._last_t = float(tt[-1])
        self.n_samples += k

    def append_states(self, Q: Any, check_finite: bool = True, copy: bool = True) -> None:
        """Append state columns ``Q`` (n, k) (any array with ``shape`` and column slicing).

        Every column goes to the chunk-file writer (:class:`_ChunkFileWriter`), the one write
        path of ``Q``. ``copy=False`` lets it keep a contiguous float64 ``(n,)`` / ``(n, 1)``
        input without copying it (the caller must not modify it afterwards); the converter
        uses it to write snapshots straight from the message buffers.
        """
        if self.closed:
            raise DatasetError(f'episode {self.name!r} is finished; begin a new one.')
        shape = getattr(Q, 'shape', None)
        if shape is None:
            Q = np.asarray(Q, dtype=np.float64)
            shape = Q.shape
        if len(shape) == 1:
            Q = np.asarray(Q).reshape(-1, 1)
            shape = Q.shape
        if len(shape) != 2:
            raise DimensionError(f'episode {self.name!r}: Q must be 2-D (n, k); got '
                                 f'{tuple(shape)}.')
        k = int(shape[1])
        n = int(shape[0])
        if self.n_states is None:
            self.n_states = n
        if n != self.n_states:
            raise DimensionError(f'episode {self.name!r}: Q must have {self.n_states} rows; '
                                 f'got {n}.')
        if self._qfiles is None:
            rows = min(n, self._q_chunks[0])
            cols = self._q_chunks[1]
            self._Q = _create_array(self._group, 'Q', (n, 0), (rows, cols), compress=False,
                                    order='F')
            self._qfiles = self._direct_writer(n, (rows, cols))
        step = self._q_chunks[1]
        for j in range(0, k, step):
            block = np.asarray(Q[:, j:j + step])
            if check_finite:
                signals.check_finite(f'episode {self.name!r}: Q (from sample {self.n_q})', block)
            if self.first_q is None:
                self.first_q = np.array(block[:, 0], dtype=np.float64)
            for c in range(block.shape[1]):
                self._qfiles.append(block[:, c], copy=copy)
            self._qwritten += block.shape[1]

    @property
    def n_q(self) -> int:
        """Number of state columns appended so far."""
        return self._qwritten

    def _direct_writer(self, n: int, chunks: tuple[int, int]) -> _ChunkFileWriter:
        """The chunk-file writer of ``Q`` (an uncompressed zarr v2 array in a directory)."""
        directory = self._owner.store_path / 'episodes' / self.name / 'Q'
        try:
            meta = json.loads((directory / '.zarray').read_text())
        except (OSError, ValueError) as err:
            raise DatasetError(f'episode {self.name!r}: Q array metadata unreadable in '
                               f'{directory} ({err}).') from err
        if (meta.get('zarr_format') != 2 or meta.get('compressor') is not None
                or meta.get('filters') or meta.get('order') != 'F'
                or meta.get('dtype') != '<f8' or list(meta.get('chunks', [])) != list(chunks)):
            raise DatasetError(f'episode {self.name!r}: zarr created Q with an unexpected '
                               f'layout {meta}; the chunk writer needs uncompressed, Fortran '
                               'order, float64 zarr v2 chunks.')
        return _ChunkFileWriter(directory, n, chunks, meta.get('dimension_separator') or '.')

    def discard(self) -> None:
        """Stop the background chunk writer (the training set is being aborted)."""
        self.closed = True
        self.discarded = True
        files, self._qfiles = self._qfiles, None
        if files is not None:
            try:
                files.close()
            except DatasetError:
                pass

    def finish(self) -> None:
        """Write ``t``, ``U``, ``Y`` and the last ``Q`` columns; called by the writer."""
        if self.closed:
            return
        self.closed = True
        if self.n_samples == 0:
            raise DatasetError(f'episode {self.name!r} has no samples; nothing to store.')
        if self._Q is not None and self.n_q != self.n_samples:
            raise DimensionError(f'episode {self.name!r}: {self.n_q} state columns for '
                                 f'{self.n_samples} samples.')
        if self._qfiles is not None:
            files, self._qfiles = self._qfiles, None
            files.flush()
            files.close()
            self._Q.resize((self._Q.shape[0], self._qwritten))
        t = np.concatenate(self._t)
        start = float(t[0])
        if start != 0.0:             # stored from the episode's own start
            t = t - start
            self.t0_ns += int(round(start * 1e9))
        U = np.concatenate(self._U, axis=1)
        Y = np.concatenate(self._Y, axis=1)
        k = t.size
        _create_array(self._group, 't', (k,), (k,), data=t)
        _create_array(self._group, 'U', U.shape, U.shape, data=U)
        _create_array(self._group, 'Y', Y.shape, Y.shape, data=Y)
        meta = dict(self.metadata)
        meta['t0_ns'] = int(self.t0_ns)
        meta['duration_s'] = float(t[-1])
        meta['n_samples'] = int(k)
        meta['has_state'] = self._Q is not None
        self._group.attrs.update({'metadata': _jsonable(meta, 'episode metadata')})
        self._t, self._U, self._Y = [], [], []


class TrainingSetWriter:
    """Write a training set atomically, episode by episode; use as a context manager.

    Parameters
    ----------
    path : str or Path
        Target directory (conventionally ``*.zarr``).
    input_names, input_units : sequence of str, length m
    output_names, output_units : sequence of str, length p
    attrs : dict, optional
        Extra JSON root attributes; ``attrs['provenance']`` is stored as the provenance.
    overwrite : bool
        Replace an existing training set (only once the new one is complete).
    q_chunks : (int, int)
        Chunk shape ``(rows, cols)`` of ``Q`` (rows capped at ``n``).

    Examples
    --------
    >>> with TrainingSetWriter('train.zarr', input_names=['p1'], input_units=['Pa'],
    ...                        output_names=['x1'], output_units=['m']) as w:
    ...     ep = w.begin_episode('ep1')
    ...     ep.append(t, U, Y)
    """

    def __init__(self, path: str | Path, *, input_names: Sequence[str],
                 input_units: Sequence[str], output_names: Sequence[str],
                 output_units: Sequence[str], attrs: Mapping[str, Any] | None = None,
                 overwrite: bool = False,
                 q_chunks: tuple[int, int] = (Q_CHUNK_ROWS, Q_CHUNK_COLS)) -> None:
        self.path = Path(path)
        self.input_names: list[str] = []
        self.input_units: list[str] = []
        self.output_names: list[str] = []
        self.output_units: list[str] = []
        self.set_names(input_names, input_units, output_names, output_units)
        self.attrs = _jsonable(dict(attrs or {}), 'attrs')
        self.overwrite = bool(overwrite)
        self.q_chunks = (int(q_chunks[0]), int(q_chunks[1]))
        if self.overwrite:
            adopt_legacy(self.path)
        outputs.check_output(self.path, overwrite=self.overwrite, what='training set',
                             kinds=(KIND,))
        self._stack: contextlib.ExitStack | None = None
        self._stage: Path | None = None
        self._root: Any = None
        self._episodes: dict[str, EpisodeWriter] = {}
        self._current: EpisodeWriter | None = None
        self._q_ref: NDArray[np.float64] | None = None
        self._y_ref: NDArray[np.float64] | None = None

    def set_names(self, input_names: Sequence[str], input_units: Sequence[str],
                  output_names: Sequence[str], output_units: Sequence[str]) -> None:
        """Set the channel names and units; allowed until the first sample is appended."""
        if any(ep.n_samples or ep.n_q for ep in getattr(self, '_episodes', {}).values()):
            raise DatasetError('names and units are fixed once samples were appended.')
        names = ([str(s) for s in input_names], [str(s) for s in input_units],
                 [str(s) for s in output_names], [str(s) for s in output_units])
        if len(names[1]) != len(names[0]) or not names[0]:
            raise DatasetError('input_names and input_units must be non-empty and of equal '
                               f'length; got {len(names[0])} and {len(names[1])}.')
        if len(names[3]) != len(names[2]) or not names[2]:
            raise DatasetError('output_names and output_units must be non-empty and of equal '
                               f'length; got {len(names[2])} and {len(names[3])}.')
        self.input_names, self.input_units, self.output_names, self.output_units = names

    @property
    def store_path(self) -> Path:
        """The staging folder the set is written into (until :meth:`close`)."""
        if self._stage is None:
            raise DatasetError('TrainingSetWriter is not open: use it as a context manager.')
        return self._stage

    def open(self) -> TrainingSetWriter:
        """Create the staging folder; called by ``__enter__``."""
        if self._root is not None:
            return self
        stack = contextlib.ExitStack()
        self._stage = stack.enter_context(outputs.atomic_dir(
            self.path, overwrite=self.overwrite, kind=KIND, what='training set'))
        self._stack = stack
        self._root = _open_group(self._stage, 'w')
        self._root.require_group('episodes')
        return self

    def __enter__(self) -> TrainingSetWriter:
        return self.open()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def begin_episode(self, name: str, n_states: int | None = None,
                      metadata: Mapping[str, Any] | None = None,
                      t0_ns: int = 0) -> EpisodeWriter:
        """Start episode ``name`` (the previous one is finished); returns its writer.

        ``t0_ns`` is the absolute time of the episode's first sample in integer
        nanoseconds (for a recording, its first stamp).
        """
        if self._root is None:
            raise DatasetError('TrainingSetWriter is not open: use it as a context manager.')
        name = _check_name(name)
        if name in self._episodes:
            raise DatasetError(f'episode {name!r} was written already; names must be unique.')
        if self._current is not None:
            self._current.finish()
        group = self._root['episodes'].require_group(name)
        ep = EpisodeWriter(self, group, name, n_states, metadata, self.q_chunks, t0_ns)
        self._episodes[name] = ep
        self._current = ep
        return ep

    def update_metadata(self, name: str, extra: Mapping[str, Any]) -> None:
        """Add ``extra`` to the metadata of episode ``name`` (also once it is finished)."""
        ep = self._episodes.get(name)
        if ep is None:
            raise DatasetError(f'no episode {name!r} is being written.')
        extra = _jsonable(dict(extra), f'metadata of episode {name!r}')
        ep.metadata.update(extra)
        if ep.closed and not ep.discarded:
            meta = dict(ep._group.attrs.get('metadata') or {})
            meta.update(extra)
            ep._group.attrs['metadata'] = meta

    def set_reference(self, q_ref: ArrayLike | None = None,
                      y_ref: ArrayLike | None = None) -> None:
        """Set ``q_ref`` (n,) and/or ``y_ref`` (p,); default: first sample of the first episode."""
        if q_ref is not None:
            self._q_ref = np.asarray(q_ref, dtype=np.float64).reshape(-1).copy()
        if y_ref is not None:
            y = np.asarray(y_ref, dtype=np.float64).reshape(-1)
            if y.size != len(self.output_names):
                raise DimensionError(f'y_ref must have {len(self.output_names)} values; '
                                     f'got {y.size}.')
            self._y_ref = y.copy()

    def close(self) -> None:
        """Finish the last episode, write references and attributes, swap into place."""
        if self._root is None or self._stack is None:
            return
        try:
            if self._current is not None:
                self._current.finish()
            if not self._episodes:
                raise DatasetError(f'no episode was written to {self.path}; nothing to store.')
            first = next(iter(self._episodes.values()))
            y_ref = self._y_ref if self._y_ref is not None else first.first_y
            q_ref = self._q_ref
            if q_ref is None:
                q_ref = next((e.first_q for e in self._episodes.values()
                              if e.first_q is not None), None)
            ns = {e.n_states for e in self._episodes.values() if e.n_states is not None}
            if len(ns) > 1:
                raise DimensionError(f'episodes have different state sizes {sorted(ns)}.')
            if q_ref is not None and ns and q_ref.size != ns.pop():
                raise DimensionError(f'q_ref has {q_ref.size} values; the states have '
                                     f'{self._episodes[first.name].n_states} rows.')
            if y_ref is None:
                raise DatasetError('no output sample was written; cannot set y_ref.')
            _create_array(self._root, 'y_ref', y_ref.shape, y_ref.shape, data=y_ref)
            if q_ref is not None:
                _create_array(self._root, 'q_ref', q_ref.shape,
                              (min(q_ref.size, 1 << 20),), data=q_ref, compress=False)
            attrs = dict(self.attrs)
            attrs.update({
                'format': FORMAT, 'format_version': FORMAT_VERSION,
                'input_names': self.input_names, 'input_units': self.input_units,
                'output_names': self.output_names, 'output_units': self.output_units,
                'episode_names': list(self._episodes),
                'provenance': attrs.get('provenance', {}),
            })
            self._root.attrs.update(attrs)   # written last: a partial set has no format
        except BaseException:
            self.abort()
            raise
        self._root = None
        stack, self._stack = self._stack, None
        self._stage = None
        stack.close()                        # marker, then the atomic swap

    def abort(self) -> None:
        """Delete the staging folder; ``path`` is left untouched."""
        self._root = None
        for ep in self._episodes.values():
            ep.discard()
        self._current = None
        stack, self._stack = self._stack, None
        self._stage = None
        if stack is not None:
            with contextlib.suppress(_Aborted):
                stack.__exit__(_Aborted, _Aborted(), None)


class _Aborted(Exception):
    """Passed to the staging context so that it removes the staging folder."""


def adopt_legacy(path: Path) -> None:
    """Mark a training set written before the output marker existed as soft_rom's.

    Only a folder whose zarr attributes say ``format = soft_rom.trainingset`` and that holds
    no bag file is adopted; anything else is left alone (and then refused by ``--overwrite``).
    """
    if not path.is_dir() or path.is_symlink() or outputs.is_marked(path):
        return
    if (path / 'metadata.yaml').exists() or any(
            f.suffix in ('.mcap', '.db3') for f in path.iterdir()):
        return
    try:
        attrs = json.loads((path / '.zattrs').read_text())
    except (OSError, ValueError):
        return
    if isinstance(attrs, dict) and attrs.get('format') == FORMAT:
        outputs.mark(path, KIND)


class TrainingSet:
    """A training set on disk, read lazily (``Q`` stays a zarr array).

    Use :meth:`open`; ``ts[name]`` is an :class:`~soft_rom.data.Episode` whose ``Q`` is the
    zarr array (slice it in column blocks, or hand it to :func:`dask.array.from_zarr`).
    """

    def __init__(self, path: Path, root: Any) -> None:
        self.path = path
        self._root = root
        self.attrs: dict[str, Any] = dict(root.attrs)
        self._v1 = False

    @classmethod
    def open(cls, path: str | Path) -> TrainingSet:
        """Open the training set at ``path``.

        Raises
        ------
        DatasetError
            Missing directory, not a soft_rom training set, unknown format version, or
            inconsistent array shapes.
        """
        p = Path(path)
        if not p.exists():
            outputs.recover(p)          # a swap interrupted by a crash: put the old set back
            outputs.clean_stale(p.parent)
        if not p.exists():
            raise DatasetError(f'training set {p} does not exist; create it with '
                               '`soft-rom convert BAG... -o OUT.zarr`.')
        try:
            root = _open_group(p, 'r')
            attrs = dict(root.attrs)
        except Exception as err:  # noqa: BLE001 - zarr raises many kinds on corrupt stores
            raise DatasetError(f'{p} is not a readable zarr training set '
                               f'({type(err).__name__}: {err}).') from err
        if attrs.get('format') != FORMAT:
            raise DatasetError(f'{p} is not a soft_rom training set (format attribute is '
                               f'{attrs.get("format")!r}, expected {FORMAT!r}).')
        version = attrs.get('format_version')
        if version not in (1, FORMAT_VERSION):
            raise DatasetError(f'{p} has training-set format version {version!r}; this soft_rom '
                               f'reads versions 1 and {FORMAT_VERSION}. Upgrade soft_rom or '
                               f'convert the bags again: {_reconvert(p, attrs)}')
        for key in ('input_names', 'input_units', 'output_names', 'output_units',
                    'episode_names'):
            if not isinstance(attrs.get(key), list):
                raise DatasetError(f'{p}: attribute {key!r} is missing or not a list.')
        ts = cls(p, root)
        ts._validate()
        if version == 1:
            ts._check_v1()
        return ts

    def _check_v1(self) -> None:
        """Version 1 stored absolute seconds: readable only when those were exact."""
        for name in self.episode_names:
            t = self._group(name)['t']
            start = float(t[0]) if t.shape[0] else 0.0
            if not abs(start) < V1_MAX_START_S:
                raise DatasetError(
                    f'{self.path} was written by an older soft_rom (format version 1) with '
                    f'absolute times (episode {name!r} starts at t = {start:.6f} s), whose '
                    'float64 seconds cannot hold the sample steps exactly. Convert the bags '
                    f'again: {_reconvert(self.path, self.attrs)}')
        self._v1 = True

    def _validate(self) -> None:
        m, p = len(self.input_names), len(self.output_names)
        n = None if self.q_ref is None else self.q_ref.size
        if self.y_ref.shape != (p,):
            raise DatasetError(f'{self.path}: y_ref has shape {self.y_ref.shape}; expected '
                               f'({p},).')
        for name in self.episode_names:
            g = self._group(name)
            try:
                k = g['t'].shape[0]
                shapes = {'U': (m, k), 'Y': (p, k)}
                if 'Q' in g:
                    shapes['Q'] = (n if n is not None else g['Q'].shape[0], k)
                for key, want in shapes.items():
                    if tuple(g[key].shape) != want:
                        raise DatasetError(f'{self.path}: episode {name!r} array {key} has '
                                           f'shape {tuple(g[key].shape)}; expected {want}.')
            except KeyError as err:
                raise DatasetError(f'{self.path}: episode {name!r} is incomplete '
                                   f'(missing {err}).') from err

    def _group(self, name: str) -> Any:
        if name not in self.episode_names:
            raise DatasetError(f'no episode {name!r} in {self.path}; episodes are '
                               f'{self.episode_names}.')
        try:
            return self._root['episodes'][name]
        except KeyError as err:
            raise DatasetError(f'{self.path}: episode group {name!r} is missing.') from err

    @classmethod
    def from_episodes(cls, path: str | Path, episodes: Sequence[Episode], *,
                      input_names: Sequence[str] | None = None,
                      input_units: Sequence[str] | None = None,
                      output_names: Sequence[str] | None = None,
                      output_units: Sequence[str] | None = None,
                      q_ref: ArrayLike | None = None, y_ref: ArrayLike | None = None,
                      attrs: Mapping[str, Any] | None = None, overwrite: bool = False,
                      q_chunks: tuple[int, int] = (Q_CHUNK_ROWS, Q_CHUNK_COLS)) -> TrainingSet:
        """Write in-memory episodes to ``path`` and open the result (tests, small data).

        Names default to ``u1..um`` / ``y1..yp`` and units to ``''``; an episode's
        ``metadata['t0_ns']`` (default 0) is its absolute start.
        """
        if not episodes:
            raise DatasetError('from_episodes needs at least one episode.')
        m, p = episodes[0].U.shape[0], episodes[0].Y.shape[0]
        in_names = list(input_names) if input_names is not None else [
            f'u{i + 1}' for i in range(m)]
        out_names = list(output_names) if output_names is not None else [
            f'y{i + 1}' for i in range(p)]
        with TrainingSetWriter(
                path, input_names=in_names,
                input_units=list(input_units) if input_units is not None else [''] * m,
                output_names=out_names,
                output_units=list(output_units) if output_units is not None else [''] * p,
                attrs=attrs, overwrite=overwrite, q_chunks=q_chunks) as w:
            for i, ep in enumerate(episodes):
                writer = w.begin_episode(ep.name or f'ep{i + 1}', metadata=ep.metadata,
                                         t0_ns=int(ep.metadata.get('t0_ns', 0)))
                if ep.Q is None:
                    writer.append(ep.t, ep.U, ep.Y)
                else:
                    step = max(q_chunks[1], 1)
                    for a in range(0, ep.n_samples, step):
                        b = min(a + step, ep.n_samples)
                        writer.append(ep.t[a:b], ep.U[:, a:b], ep.Y[:, a:b], ep.Q[:, a:b])
            w.set_reference(q_ref=q_ref, y_ref=y_ref)
        return cls.open(path)

    # -- accessors ----------------------------------------------------------------------
    @property
    def episode_names(self) -> list[str]:
        """Episode names in the order they were written."""
        return list(self.attrs['episode_names'])

    @property
    def input_names(self) -> list[str]:
        """Input names, length m."""
        return list(self.attrs['input_names'])

    @property
    def input_units(self) -> list[str]:
        """Input units, length m."""
        return list(self.attrs['input_units'])

    @property
    def output_names(self) -> list[str]:
        """Output names, length p."""
        return list(self.attrs['output_names'])

    @property
    def output_units(self) -> list[str]:
        """Output units, length p."""
        return list(self.attrs['output_units'])

    @property
    def provenance(self) -> dict[str, Any]:
        """Provenance attributes (bags, topics, conversion options)."""
        return dict(self.attrs.get('provenance') or {})

    @property
    def q_ref(self) -> NDArray[np.float64] | None:
        """Reference configuration ``(n,)``, or ``None`` without states."""
        if 'q_ref' not in self._root:
            return None
        return np.asarray(self._root['q_ref'][...], dtype=np.float64)

    @property
    def y_ref(self) -> NDArray[np.float64]:
        """Reference output ``(p,)``."""
        return np.asarray(self._root['y_ref'][...], dtype=np.float64)

    @property
    def n_states(self) -> int | None:
        """State dimension ``n`` or ``None``."""
        q = self.q_ref
        return None if q is None else int(q.size)

    def has_state(self, name: str) -> bool:
        """True if episode ``name`` stores ``Q``."""
        return 'Q' in self._group(name)

    def q_array(self, name: str) -> Any:
        """The zarr array ``Q`` (n, k) of episode ``name``."""
        g = self._group(name)
        if 'Q' not in g:
            raise DatasetError(f'episode {name!r} of {self.path} has no states (Q); convert '
                               'the bags without --no-state.')
        return g['Q']

    def metadata(self, name: str) -> dict[str, Any]:
        """Episode attributes (``t0_ns``, source bag, topics, conversion report)."""
        meta = dict(self._group(name).attrs.get('metadata') or {})
        if self._v1 and 't0_ns' not in meta:
            t = self._group(name)['t']
            meta['t0_ns'] = int(round(float(t[0]) * 1e9)) if t.shape[0] else 0
        meta.setdefault('t0_ns', 0)
        return meta

    def times(self, name: str) -> NDArray[np.float64]:
        """Sample times of episode ``name`` in seconds from its start (``t[0] = 0``)."""
        t = np.asarray(self._group(name)['t'][...], dtype=np.float64)
        return t - t[0] if self._v1 and t.size else t

    def t0_ns(self, name: str) -> int:
        """Absolute start of episode ``name`` in integer nanoseconds."""
        return int(self.metadata(name)['t0_ns'])

    def __getitem__(self, name: str) -> Episode:
        g = self._group(name)
        return Episode(t=self.times(name),
                       U=np.asarray(g['U'][...], dtype=np.float64),
                       Y=np.asarray(g['Y'][...], dtype=np.float64),
                       Q=g['Q'] if 'Q' in g else None, name=name,
                       metadata=self.metadata(name))

    def episodes(self, names: Sequence[str] | None = None) -> list[Episode]:
        """Episodes ``names`` (default all, in order); ``Q`` is lazy (zarr) or ``None``."""
        return [self[n] for n in (self.episode_names if names is None else names)]

    def __iter__(self) -> Iterator[Episode]:
        return iter(self.episodes())

    def __len__(self) -> int:
        return len(self.episode_names)

    def describe(self) -> dict[str, Any]:
        """Summary for ``soft-rom info``: per episode ``t0_ns`` and times from its start."""
        eps = {}
        for name in self.episode_names:
            g = self._group(name)
            t = self.times(name)
            eps[name] = {
                'n_samples': int(t.size), 't0_ns': self.t0_ns(name),
                'duration_s': float(t[-1]) if t.size else 0.0,
                'dt_mean': float(np.mean(np.diff(t))) if t.size > 1 else float('nan'),
                'Q': list(g['Q'].shape) if 'Q' in g else None,
                'Q_chunks': list(g['Q'].chunks) if 'Q' in g else None,
                'source': self.metadata(name).get('source_bag'),
            }
        return {'path': str(self.path), 'format_version': self.attrs.get('format_version'),
                'input_names': self.input_names, 'input_units': self.input_units,
                'output_names': self.output_names, 'output_units': self.output_units,
                'n_states': self.n_states, 'episodes': eps, 'provenance': self.provenance}


def _reconvert(path: Path, attrs: Mapping[str, Any]) -> str:
    """The command that converts the bags of a training set again."""
    prov = attrs.get('provenance') or {}
    bags = prov.get('bags') if isinstance(prov, Mapping) else None
    args = ' '.join(shlex.quote(str(b)) for b in bags) if isinstance(bags, list) and bags \
        else 'BAG...'
    return f'soft-rom convert {args} -o {shlex.quote(str(path))} --overwrite'
