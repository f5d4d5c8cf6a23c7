"""Writing a training set: :class:`TrainingSetWriter` and its :class:`EpisodeWriter`."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
import contextlib
import json
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom import data as signals
from soft_rom import outputs
from soft_rom.data import all_finite, as_signal
from soft_rom.dataset._format import (
    _check_name,
    _create_array,
    _jsonable,
    _open_group,
    ALL_CHUNKS,
    FORMAT,
    FORMAT_VERSION,
    KIND,
    Q_CHUNK_COLS,
    Q_CHUNK_ROWS,
)
from soft_rom.dataset.checksum import CODEC_ID
from soft_rom.dataset.chunks import ChunkFileWriter
from soft_rom.errors import DatasetError, DimensionError

__all__ = ['EpisodeWriter', 'TrainingSetWriter', 'adopt_legacy']

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
        self._qfiles: ChunkFileWriter | None = None
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

        Every column goes to the chunk-file writer (:class:`ChunkFileWriter`), the one write
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

    def _direct_writer(self, n: int, chunks: tuple[int, int]) -> ChunkFileWriter:
        """The chunk-file writer of ``Q`` (an uncompressed zarr v2 array in a directory)."""
        directory = self._owner.store_path / 'episodes' / self.name / 'Q'
        try:
            meta = json.loads((directory / '.zarray').read_text())
        except (OSError, ValueError) as err:
            raise DatasetError(f'episode {self.name!r}: Q array metadata unreadable in '
                               f'{directory} ({err}).') from err
        if (meta.get('zarr_format') != 2 or meta.get('compressor') is not None
                or meta.get('filters') != [{'id': CODEC_ID}] or meta.get('order') != 'F'
                or meta.get('dtype') != '<f8' or list(meta.get('chunks', [])) != list(chunks)):
            raise DatasetError(f'episode {self.name!r}: zarr created Q with an unexpected '
                               f'layout {meta}; the chunk writer needs uncompressed, Fortran '
                               'order, float64 zarr v2 chunks with the crc32c filter.')
        return ChunkFileWriter(directory, n, chunks, meta.get('dimension_separator') or '.')

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
        def listed(values: Sequence[str] | str, like: Sequence[str] | str) -> list[str]:
            """A string is one name, or (``like`` given) the unit of every channel."""
            if isinstance(values, str):
                return [values] * (1 if isinstance(like, str) else len(like))
            return [str(s) for s in values]

        names = (listed(input_names, ''), listed(input_units, input_names),
                 listed(output_names, ''), listed(output_units, output_names))
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
                'episode_names': list(self._episodes), ALL_CHUNKS: True,
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
    from soft_rom.bags.reader import is_bag
    if is_bag(path):
        return
    try:
        attrs = json.loads((path / '.zattrs').read_text())
    except (OSError, ValueError):
        return
    if isinstance(attrs, dict) and attrs.get('format') == FORMAT:
        outputs.mark(path, KIND, manifest=False)     # what else it holds: not known


