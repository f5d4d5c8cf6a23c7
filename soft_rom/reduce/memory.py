"""The in-memory reducer: snapshots read into memory, reduced by a thin SVD (or not at all).

:class:`InMemoryPOD` turns :class:`~soft_rom.reduce.data.TrainingData` into
:class:`~soft_rom.reduce.data.ReducedData`:

* ``basis='pod'`` (LOpInf) -- the POD basis of the centred snapshots
  (:class:`~soft_rom.basis.POD`, or a given basis builder) and each episode's coordinates
  in it, read in column blocks (:func:`~soft_rom.basis.project`);
* ``basis='identity'`` (DMDc) -- the centred snapshots themselves: DMDc takes its own two
  SVDs of them, exactly as in the paper (sec. 2.3);
* ``basis='none'`` (ERA/OKID) -- inputs and outputs only.
"""

from __future__ import annotations

from collections.abc import Sequence
import copy
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.basis import BasisBuilder, POD, project
from soft_rom.data import as_signal, check_finite, Episode
from soft_rom.errors import ConfigError, DimensionError
from soft_rom.reduce.data import ReducedData, TrainingData

__all__ = ['InMemoryPOD', 'training_data']

Array = NDArray[np.float64]

_CHANNEL_KEYS = ('input_names', 'output_names', 'input_units', 'output_units')


def training_data(episodes: Episode | Sequence[Episode], q_ref: ArrayLike | None = None,
                  y_ref: ArrayLike | None = None, *, names: dict[str, Any] | None = None,
                  provenance: dict[str, Any] | None = None) -> TrainingData:
    """Episodes and references as :class:`TrainingData` (defaults from the first episode).

    Parameters
    ----------
    episodes : Episode or sequence of Episode
    q_ref : ndarray, shape (n,), optional
        Default the first snapshot of the first episode (when it has ``Q``).
    y_ref : ndarray, shape (p,), optional
        Default the first output of the first episode.
    names : dict, optional
        ``input_names``, ... ; each missing one is taken from the first episode's metadata.
    provenance : dict, optional
    """
    eps = [episodes] if isinstance(episodes, Episode) else list(episodes)
    if not eps:
        raise DimensionError('no episodes given: a fit needs at least one episode.')
    for ep in eps:
        if not isinstance(ep, Episode):
            raise DimensionError(f'expected Episode objects; got {type(ep).__name__}.')
    given = dict(names or {})
    meta = eps[0].metadata if isinstance(eps[0].metadata, dict) else {}
    chan = {k: given.get(k) if given.get(k) is not None else meta.get(k) for k in _CHANNEL_KEYS}
    p = eps[0].Y.shape[0]
    y = eps[0].Y[:, 0].copy() if y_ref is None else as_signal(
        'y_ref', np.reshape(np.asarray(y_ref, dtype=np.float64), (-1, 1)), rows=p)[:, 0].copy()
    q = None
    if q_ref is not None:
        q = np.asarray(q_ref, dtype=np.float64).reshape(-1).copy()
    elif eps[0].Q is not None:
        q = np.asarray(eps[0].Q[:, 0:1], dtype=np.float64)[:, 0].copy()
    return TrainingData(episodes=eps, q_ref=q, y_ref=y, names=chan,
                        provenance=dict(provenance or {}))


def _snapshots(data: TrainingData, what: str) -> tuple[list[Any], int, Array]:
    """The episodes' ``Q`` (possibly lazy), ``n`` and ``q_ref``; refuses missing states."""
    for ep in data.episodes:
        if ep.Q is None:
            raise DimensionError(
                f'episode {ep.name!r} has no full states Q: {what} needs them (ERA/OKID does '
                'not; on measured outputs fit with --coordinates outputs).')
    n = int(data.episodes[0].Q.shape[0])
    for ep in data.episodes:
        if int(ep.Q.shape[0]) != n:
            raise DimensionError(f'episode {ep.name!r} has {ep.Q.shape[0]} states; the first '
                                 f'episode has {n}.')
    if data.q_ref is None or data.q_ref.size != n:
        size = None if data.q_ref is None else data.q_ref.size
        raise DimensionError(f'q_ref must have {n} entries (one per state); got {size}.')
    check_finite('q_ref', data.q_ref)
    return [ep.Q for ep in data.episodes], n, data.q_ref


class InMemoryPOD:
    """Reduce training data in memory: POD coordinates, the centred snapshots, or nothing.

    Parameters
    ----------
    energy : float
        POD energy fraction choosing the number of modes when ``r`` is not given
        (default 0.95, as in the paper).
    builder : BasisBuilder, optional
        A basis builder object (default :class:`~soft_rom.basis.POD`); copied before use.
    share_svd : bool
        Keep the thin SVD of the last snapshots reduced with the default POD, and reuse it
        when the same snapshot arrays (the same objects) and ``q_ref`` come again: several
        fits of one training set (the study's linear and cubic LOpInf, at other ``r``) then
        take one SVD, with the same basis bit for bit. It holds the ``(n, k)`` singular
        vectors in memory until the reducer is dropped.
    """

    name = 'memory'

    def __init__(self, energy: float = 0.95, *, builder: BasisBuilder | None = None,
                 share_svd: bool = False) -> None:
        self.energy = energy
        self.builder = builder
        self.share_svd = share_svd
        self._svd: tuple[tuple[Any, ...], bytes, Array, Array] | None = None

    def __repr__(self) -> str:
        return (f'InMemoryPOD(energy={self.energy!r}, builder={self.builder!r}, '
                f'share_svd={self.share_svd!r})')

    def _pod(self, arrays: list[Any], q_ref: Array, r: int | None) -> POD:
        """The default POD of ``arrays``, its SVD reused when :attr:`share_svd` allows."""
        builder = POD(r=r, energy=self.energy)
        if not self.share_svd:
            return builder.fit(arrays, q_ref)
        key = tuple(arrays)             # the arrays themselves: held, so never a reused id
        ref = np.ascontiguousarray(q_ref).tobytes()
        held = self._svd
        if held is None or len(held[0]) != len(key) or held[1] != ref or any(
                a is not b for a, b in zip(held[0], key)):
            V, s = builder.svd(arrays, q_ref)
            held = self._svd = (key, ref, V, s)
        return builder.fit_svd(held[2], held[3], q_ref)

    def reduce(self, data: TrainingData, *, basis: str = 'pod', r: int | None = None,
               n_coordinates: int | None = None, what: str = 'the POD') -> ReducedData:
        """The reduced data of ``data``.

        Parameters
        ----------
        data : TrainingData
        basis : {'pod', 'identity', 'none'}
            What the learner needs (module docstring).
        r : int, optional
            POD modes kept (``basis='pod'``); default by :attr:`energy`.
        n_coordinates : int, optional
            Ignored here (every coordinate the learner needs is kept).
        what : str
            The learner, for messages.
        """
        common = self._common(data)
        if basis == 'none':
            return ReducedData(coordinates=None, basis='none', **common)
        arrays, n, q_ref = _snapshots(data, what)
        if basis == 'identity':
            Qc = [np.asarray(Q[:, :], dtype=np.float64) - q_ref[:, None] for Q in arrays]
            return ReducedData(coordinates=tuple(Qc), basis='identity', n_states=n,
                               q_ref=q_ref, **common)
        if basis != 'pod':
            raise ConfigError(f"basis must be 'pod', 'identity' or 'none'; got {basis!r}.")
        builder: Any
        if self.builder is None:
            _ = data.dt                            # validate before the expensive POD
            builder = self._pod(arrays, q_ref, r)
        else:
            builder = copy.deepcopy(self.builder)
            if not callable(getattr(builder, 'fit', None)):
                raise ConfigError(f'basis must be a BasisBuilder object (fit, basis_, '
                                  f'singular_values_); got {type(builder).__name__}.')
            _ = data.dt                            # validate before the expensive POD
            builder.fit(arrays, q_ref)
        if not isinstance(builder, BasisBuilder):
            raise ConfigError(f'the basis builder {type(builder).__name__} has no basis_ or '
                              'singular_values_ after fit().')
        V = np.asarray(builder.basis_, dtype=np.float64)
        if V.ndim != 2 or V.shape[0] != n:
            raise DimensionError(f'the basis builder returned basis_ of shape {V.shape}; '
                                 f'expected ({n}, r).')
        Qhat = [project(Q, V, q_ref) for Q in arrays]
        s = np.asarray(builder.singular_values_, dtype=np.float64)
        energy = getattr(builder, 'energy_', None)
        energy = np.asarray(energy) if energy is not None else np.cumsum(s ** 2) / np.sum(s ** 2)
        last = 0.0
        for Q in arrays:
            x = np.asarray(Q[:, -1:], dtype=np.float64)[:, 0] - q_ref
            last += float(x @ x)
        return ReducedData(coordinates=tuple(Qhat), basis='pod', energy=energy,
                           singular_values=s, n_states=n,
                           pairs_sq_norm=float(np.sum(s ** 2)) - last, q_ref=q_ref,
                           modes=V, **common)

    @staticmethod
    def _common(data: TrainingData) -> dict[str, Any]:
        eps = data.episodes
        return dict(U=tuple(ep.U for ep in eps), Y=tuple(ep.Y for ep in eps),
                    t=tuple(ep.t for ep in eps), y_ref=data.y_ref,
                    names=tuple(ep.name for ep in eps), channels=dict(data.names),
                    metadata={'training': dict(data.provenance)} if data.provenance else {})
