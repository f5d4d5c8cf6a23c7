"""Reading a training set: :class:`TrainingSet` (lazy ``Q``, format versions 1 and 2)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom import outputs
from soft_rom.data import Episode
from soft_rom.dataset._format import (
    _open_group,
    _reconvert,
    FORMAT,
    FORMAT_VERSION,
    Q_CHUNK_COLS,
    Q_CHUNK_ROWS,
    V1_MAX_START_S,
)
from soft_rom.dataset.writer import TrainingSetWriter
from soft_rom.errors import DatasetError
from soft_rom.layout import layout_of, OutputLayout

__all__ = ['TrainingSet']

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


