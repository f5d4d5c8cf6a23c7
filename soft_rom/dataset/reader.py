"""Reading a training set: :class:`TrainingSet` (lazy ``Q``, format versions 1 and 2).

Every array is read through a :class:`~soft_rom.dataset.stored.StoredArray` (chunks checked
once, errors translated) and every attribute is type-checked, so that a damaged or
incomplete set is refused with one :class:`~soft_rom.errors.DatasetError` naming the set,
the episode and the array, and is never read as zeros.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom import outputs
from soft_rom.data import Episode
from soft_rom.dataset._format import (
    _check_name,
    _open_group,
    _reconvert,
    ALL_CHUNKS,
    CHECKSUM_VERSION,
    FORMAT,
    FORMAT_VERSION,
    Q_CHUNK_COLS,
    Q_CHUNK_ROWS,
    READ_VERSIONS,
    V1_MAX_START_S,
)
from soft_rom.dataset.stored import StoredArray, translated
from soft_rom.dataset.writer import TrainingSetWriter
from soft_rom.errors import DatasetError
from soft_rom.layout import layout_of, OutputLayout

__all__ = ['TrainingSet']

#: Root attributes that must be lists of strings.
_NAME_LISTS = ('input_names', 'input_units', 'output_names', 'output_units', 'episode_names')

class TrainingSet:
    """A training set on disk, read lazily (``Q`` stays on disk until sliced).

    Use :meth:`open`; ``ts[name]`` is an :class:`~soft_rom.data.Episode` whose ``Q`` is a
    :class:`~soft_rom.dataset.stored.StoredArray` over the zarr array (slice it in column
    blocks, or turn it into a dask array with its ``to_dask()``; ``Q.array`` is the zarr
    array itself). Each array is checked for missing or damaged chunks before its first
    read; a damaged set raises :class:`~soft_rom.errors.DatasetError`.
    """

    def __init__(self, path: Path, root: Any, attrs: Mapping[str, Any] | None = None) -> None:
        self.path = path
        self._root = root
        self.attrs: dict[str, Any] = dict(root.attrs if attrs is None else attrs)
        self._v1 = False
        self._arrays: dict[tuple[str, str], StoredArray] = {}
        self._groups: dict[str, Any] = {}

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
        if not p.is_dir():
            raise DatasetError(f'{p} is a file, not a training set (the folder `soft-rom '
                               'convert BAG... -o OUT.zarr` writes).')
        try:
            root = _open_group(p, 'r')
            attrs = root.attrs.asdict()
            if not isinstance(attrs, dict):
                raise TypeError(f'its attributes are a JSON {type(attrs).__name__}')
        except Exception as err:  # noqa: BLE001 - zarr raises many kinds on corrupt stores
            raise DatasetError(f'{p} is not a readable zarr training set '
                               f'({type(err).__name__}: {err}).') from err
        if attrs.get('format') != FORMAT:
            raise DatasetError(f'{p} is not a soft_rom training set (format attribute is '
                               f'{attrs.get("format")!r}, expected {FORMAT!r}).')
        version = attrs.get('format_version')
        if isinstance(version, bool) or version not in READ_VERSIONS:
            raise DatasetError(f'{p} has training-set format version {version!r}; this soft_rom '
                               f'reads versions {", ".join(map(str, READ_VERSIONS[:-1]))} and '
                               f'{FORMAT_VERSION}. Upgrade soft_rom or convert the bags again: '
                               f'{_reconvert(p, attrs)}')
        ts = cls(p, root, attrs)
        ts._check_attrs()
        ts._validate()
        if version == 1:
            ts._check_v1()
        return ts

    def _check_v1(self) -> None:
        """Version 1 stored absolute seconds: readable only when those were exact."""
        for name in self.episode_names:
            t = self._array(name, 't')
            start = float(t[0]) if t.shape[0] else 0.0
            if not abs(start) < V1_MAX_START_S:
                raise DatasetError(
                    f'{self.path} was written by an older soft_rom (format version 1) with '
                    f'absolute times (episode {name!r} starts at t = {start:.6f} s), whose '
                    'float64 seconds cannot hold the sample steps exactly. Convert the bags '
                    f'again: {_reconvert(self.path, self.attrs)}')
        self._v1 = True

    def _check_attrs(self) -> None:
        """Refuse root attributes of the wrong type (a hand-edited or damaged ``.zattrs``)."""
        for key in _NAME_LISTS:
            value = self.attrs.get(key)
            if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
                raise DatasetError(f'{self.path}: attribute {key!r} is missing or not a list '
                                   f'of strings (it is {_short(value)}).')
        names = self.attrs['episode_names']
        for name in names:
            try:
                _check_name(name)
            except DatasetError as err:
                raise DatasetError(f"{self.path}: attribute 'episode_names' holds {err}") \
                    from None
        if len(set(names)) != len(names):
            raise DatasetError(f"{self.path}: attribute 'episode_names' repeats names "
                               f'({_short(names)}).')
        prov = self.attrs.get('provenance')
        if prov is not None and not isinstance(prov, dict):
            raise DatasetError(f"{self.path}: attribute 'provenance' is "
                               f'{_short(prov)}, not a JSON object.')

    def _corrupt(self, where: str) -> str:
        """Beginning of a message about part ``where`` of a damaged set."""
        return f'training set {self.path} is corrupt or incomplete: {where}'

    def _advice(self) -> str:
        return ('restore it from a good copy or convert the bags again: '
                f'{_reconvert(self.path, self.attrs)}')

    def _validate(self) -> None:
        m, p = len(self.input_names), len(self.output_names)
        n = None if self.q_ref is None else self.q_ref.size
        if self.y_ref.shape != (p,):
            raise DatasetError(f'{self.path}: y_ref has shape {self.y_ref.shape}; expected '
                               f'({p},).')
        for name in self.episode_names:
            k = self._array(name, 't').shape[0]
            shapes = {'U': (m, k), 'Y': (p, k)}
            if self.has_state(name):
                shapes['Q'] = (n if n is not None else self._array(name, 'Q').shape[0], k)
            for key, want in shapes.items():
                got = self._array(name, key).shape
                if got != want:
                    raise DatasetError(f'{self.path}: episode {name!r} array {key} has '
                                       f'shape {got}; expected {want}.')

    def _group(self, name: str) -> Any:
        cached = self._groups.get(name)
        if cached is not None:
            return cached
        if name not in self.episode_names:
            raise DatasetError(f'no episode {name!r} in {self.path}; episodes are '
                               f'{self.episode_names}.')
        with translated(self._corrupt(f'episode {name!r}'), self._advice()):
            episodes = self._root['episodes'] if 'episodes' in self._root else None
            group = episodes[name] if episodes is not None and name in episodes else None
        if group is None:
            raise DatasetError(f'{self._corrupt(f"episode {name!r}")}: its group is missing '
                               f'(was the copy interrupted?); {self._advice()}')
        self._groups[name] = group
        return group

    @staticmethod
    def _where(name: str | None, key: str) -> str:
        return f'array {key}' if name is None else f'episode {name!r}, array {key}'

    def _has(self, name: str | None, key: str) -> bool:
        """Whether episode ``name`` (``None``: the root) has array ``key``."""
        if (name or '', key) in self._arrays:
            return True
        group = self._root if name is None else self._group(name)
        with translated(self._corrupt(self._where(name, key)), self._advice()):
            return key in group

    def _array(self, name: str | None, key: str) -> StoredArray:
        """Array ``key`` of episode ``name`` (``None``: a root array), opened once.

        Its chunks are checked at its first read (:meth:`StoredArray.check`).
        """
        cached = self._arrays.get((name or '', key))
        if cached is not None:
            return cached
        where = self._where(name, key)
        if not self._has(name, key):
            raise DatasetError(f'{self._corrupt(where)}: it is missing (was the copy '
                               f'interrupted?); {self._advice()}')
        group = self._root if name is None else self._group(name)
        with translated(f'{self._corrupt(where)}:', self._advice(),
                        what='its metadata (.zarray) cannot be read'):
            raw = group[key]
            base = self.path.absolute()      # a Dask worker's working folder is its own
            folder = base if name is None else base / 'episodes' / name
            hint = 'was the copy interrupted?'
            if self.attrs.get(ALL_CHUNKS) is not True and key != 'Q':
                hint += (' Sets written with zarr 3 by soft_rom before it stored every chunk '
                         'lack the chunks that were all zeros')
            arr = StoredArray(raw, folder / key, self._corrupt(where), self._advice(), hint)
        if self.checksummed and not arr.checksummed:
            raise DatasetError(f'{self._corrupt(where)}: its .zarray declares no crc32c '
                               f'checksum, but the set (format version '
                               f'{self.attrs.get("format_version")}) has one in every chunk; '
                               f'{self._advice()}')
        self._arrays[(name or '', key)] = arr
        return arr

    def _read(self, name: str | None, key: str) -> NDArray[np.float64]:
        """All of array ``key`` of episode ``name`` (``None``: a root array), float64."""
        return np.asarray(self._array(name, key)[...], dtype=np.float64)

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

        Names default to ``u1..um`` / ``y1..yp`` and units to ``''`` (one string: the unit
        of every channel); an episode's
        ``metadata['t0_ns']`` (default 0) is its absolute start.
        """
        if not episodes:
            raise DatasetError('from_episodes needs at least one episode.')
        m, p = episodes[0].U.shape[0], episodes[0].Y.shape[0]
        in_names = input_names if input_names is not None else [f'u{i + 1}' for i in range(m)]
        out_names = output_names if output_names is not None else [
            f'y{i + 1}' for i in range(p)]
        with TrainingSetWriter(
                path, input_names=in_names,
                input_units=input_units if input_units is not None else [''] * m,
                output_names=out_names,
                output_units=output_units if output_units is not None else [''] * p,
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
    def output_layout(self) -> OutputLayout | None:
        """Which points and components form ``y``, or ``None``.

        Stored by the converter; for sets from before it was, the layout the output names
        spell.
        """
        layout = layout_of(self.attrs, self.output_names)
        if layout is not None and layout.size != len(self.output_names):
            raise DatasetError(f'{self.path}: the output layout has {layout.size} outputs, '
                               f'the names {len(self.output_names)}.')
        return layout

    @property
    def checksummed(self) -> bool:
        """Whether every chunk ends with its CRC-32C (format version 3 and later)."""
        version = self.attrs.get('format_version')
        return isinstance(version, int) and version >= CHECKSUM_VERSION

    @property
    def provenance(self) -> dict[str, Any]:
        """Provenance attributes (bags, topics, conversion options)."""
        return dict(self.attrs.get('provenance') or {})

    @property
    def q_ref(self) -> NDArray[np.float64] | None:
        """Reference configuration ``(n,)``, or ``None`` without states."""
        if not self._has(None, 'q_ref'):
            return None
        return self._read(None, 'q_ref')

    @property
    def y_ref(self) -> NDArray[np.float64]:
        """Reference output ``(p,)``."""
        return self._read(None, 'y_ref')

    @property
    def n_states(self) -> int | None:
        """State dimension ``n`` or ``None``."""
        q = self.q_ref
        return None if q is None else int(q.size)

    def has_state(self, name: str) -> bool:
        """True if episode ``name`` stores ``Q``.

        Raises
        ------
        DatasetError
            The episode's metadata says it has states, but ``Q`` is gone.
        """
        if self._has(name, 'Q'):
            return True
        if self.metadata(name).get('has_state') is True:
            raise DatasetError(f'{self._corrupt(self._where(name, "Q"))}: it is missing, but '
                               "the episode's metadata says it has states (was the copy "
                               f'interrupted?); {self._advice()}')
        return False

    def q_array(self, name: str) -> StoredArray:
        """The array ``Q`` (n, k) of episode ``name``, lazy (a :class:`StoredArray`)."""
        if not self.has_state(name):
            raise DatasetError(f'episode {name!r} of {self.path} has no states (Q); convert '
                               'the bags without --no-state.')
        return self._array(name, 'Q')

    def metadata(self, name: str) -> dict[str, Any]:
        """Episode attributes (``t0_ns``, source bag, topics, conversion report)."""
        group = self._group(name)
        where = self._corrupt(f'episode {name!r}')
        with translated(f'{where}: its attributes (.zattrs)', self._advice()):
            attrs = group.attrs.asdict()
        if not isinstance(attrs, dict):
            raise DatasetError(f'{where}: its attributes (.zattrs) are a JSON '
                               f'{type(attrs).__name__}, not an object; {self._advice()}')
        meta = attrs.get('metadata')
        if meta is not None and not isinstance(meta, dict):
            raise DatasetError(f"{where}: its attribute 'metadata' is {_short(meta)}, not "
                               f'a JSON object; {self._advice()}')
        meta = dict(meta or {})
        t0 = meta.get('t0_ns')
        if t0 is not None and (not isinstance(t0, int) or isinstance(t0, bool)):
            raise DatasetError(f"{where}: its metadata 't0_ns' is {_short(t0)}, not an "
                               f'integer number of nanoseconds; {self._advice()}')
        if self._v1 and t0 is None:
            t = self._array(name, 't')
            meta['t0_ns'] = int(round(float(t[0]) * 1e9)) if t.shape[0] else 0
        if meta.get('t0_ns') is None:
            meta['t0_ns'] = 0
        return meta

    def times(self, name: str) -> NDArray[np.float64]:
        """Sample times of episode ``name`` in seconds from its start (``t[0] = 0``)."""
        t = self._read(name, 't')
        return t - t[0] if self._v1 and t.size else t

    def t0_ns(self, name: str) -> int:
        """Absolute start of episode ``name`` in integer nanoseconds."""
        return int(self.metadata(name)['t0_ns'])

    def __getitem__(self, name: str) -> Episode:
        return Episode(t=self.times(name), U=self._read(name, 'U'), Y=self._read(name, 'Y'),
                       Q=self._array(name, 'Q') if self.has_state(name) else None, name=name,
                       metadata=self.metadata(name))

    def episodes(self, names: Sequence[str] | None = None) -> list[Episode]:
        """Episodes ``names`` (default all, in order); ``Q`` is lazy (zarr) or ``None``.

        One name as a string is a list of that episode (not of its letters).
        """
        if isinstance(names, str):
            names = [names]
        return [self[n] for n in (self.episode_names if names is None else names)]

    def __iter__(self) -> Iterator[Episode]:
        return iter(self.episodes())

    def __len__(self) -> int:
        return len(self.episode_names)

    def describe(self, verify: bool = True) -> dict[str, Any]:
        """Summary for ``soft-rom info``: per episode ``t0_ns`` and times from its start.

        Every array's chunks are checked: a set copied incompletely is refused here too
        (:class:`~soft_rom.errors.DatasetError`), not only when a fit reads the damaged
        array. With checksums (format version 3) and ``verify`` every chunk is read and
        checked against its CRC-32C (all of ``Q``: at disk speed); else listings only.
        """
        eps = {}
        for name in self.episode_names:
            t = self.times(name)
            q = self.q_array(name) if self.has_state(name) else None
            for arr in [self._array(name, 'U'), self._array(name, 'Y')] + (
                    [q] if q is not None else []):
                if verify:
                    arr.verify()
                else:
                    arr.check()
            eps[name] = {
                'n_samples': int(t.size), 't0_ns': self.t0_ns(name),
                'duration_s': float(t[-1]) if t.size else 0.0,
                'dt_mean': float(np.mean(np.diff(t))) if t.size > 1 else float('nan'),
                'Q': list(q.shape) if q is not None else None,
                'Q_chunks': list(q.chunks) if q is not None else None,
                'source': self.metadata(name).get('source_bag'),
            }
        return {'path': str(self.path), 'format_version': self.attrs.get('format_version'),
                'checksums': 'CRC-32C per chunk' if self.checksummed else None,
                'input_names': self.input_names, 'input_units': self.input_units,
                'output_names': self.output_names, 'output_units': self.output_units,
                'n_states': self.n_states, 'episodes': eps, 'provenance': self.provenance}


def _short(value: Any, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters (for messages about attributes)."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + '...'
