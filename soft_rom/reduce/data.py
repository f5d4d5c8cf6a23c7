"""What the reducers take and what they hand to the learners.

:class:`TrainingData` is the training episodes as they are on disk or in memory (``U``, ``Y``,
``t`` in memory; full states ``Q`` possibly lazy) with their references and channel names.
:class:`ReducedData` is what every learner fits on: the reduced coordinates of each episode
in an orthonormal basis, the inputs and outputs, the sample times, and the few numbers of the
full-order snapshots a learner needs besides (POD energies, the number of full-order states
and the squared norm of the snapshots that start a pair, for DMDc's unit-invariant scaling).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import as_signal, check_finite, Episode, nonuniform_message
from soft_rom.errors import ConfigError, DimensionError

__all__ = ['BASES', 'ReducedData', 'TrainingData']

Array = NDArray[np.float64]

#: Kinds of coordinates a reducer hands over: ``'pod'`` (POD coordinates, leading modes
#: first), ``'identity'`` (the centred snapshots themselves: nothing truncated) and ``'none'``
#: (inputs and outputs only, for ERA/OKID).
BASES = ('pod', 'identity', 'none')

_CHANNEL_KEYS = ('input_names', 'output_names', 'input_units', 'output_units')


def _common_dt(t: Sequence[Array], names: Sequence[str]) -> float:
    """The sample time shared by every episode (uniform to 1e-6), else a DimensionError."""
    dts = []
    for ti, name in zip(t, names):
        d = np.diff(ti)
        if ti.size < 2 or (ti.size > 2 and np.max(np.abs(d - d.mean())) > 1e-6 * d.mean()):
            raise DimensionError(nonuniform_message(name, ti))
        dts.append(float(np.mean(d)))
    if any(abs(d - dts[0]) > 1e-6 * dts[0] for d in dts):
        raise DimensionError(f'episodes have different sample times {dts}; resample first '
                             '(soft-rom convert --dt).')
    return dts[0]


@dataclass
class TrainingData:
    """Training episodes and their common references, before any reduction.

    Attributes
    ----------
    episodes : list of Episode
        ``U``, ``Y``, ``t`` in memory; ``Q`` (full states) may be lazy on disk, or ``None``.
    q_ref : ndarray, shape (n,) or None
        Reference configuration of the states.
    y_ref : ndarray, shape (p,)
    names : dict
        ``input_names``, ``input_units``, ``output_names``, ``output_units`` (may be None).
    provenance : dict
        Where the episodes come from (stored in the models' ``metadata['training']``).
    """

    episodes: list[Episode]
    q_ref: Array | None
    y_ref: Array
    names: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def dt(self) -> float:
        """Common sample time (seconds)."""
        return _common_dt([ep.t for ep in self.episodes], [ep.name for ep in self.episodes])

    def model_names(self) -> dict[str, Any]:
        """The names and units known for the model (keyword arguments of the models)."""
        return {k: list(v) for k, v in self.names.items() if v is not None}


@dataclass(frozen=True, eq=False)
class ReducedData:
    """Reduced coordinates of every training episode, and what the learners need besides.

    The coordinates are ``Wᵀ (Q_i - q_ref)`` in an orthonormal basis ``W`` of the snapshots:
    the POD modes, leading first (``basis='pod'``; LOpInf uses the leading ``r``), or the
    identity (``basis='identity'``: the centred snapshots, nothing truncated; DMDc's SVDs are
    then exactly the paper's). ERA/OKID needs no coordinates (``basis='none'``).

    Parameters
    ----------
    coordinates : sequence of ndarray, each shape (l, k_i), or None
    U : sequence of ndarray, each shape (m, k_i)
        Inputs.
    Y : sequence of ndarray, each shape (p, k_i)
        Absolute outputs.
    t : sequence of ndarray, each shape (k_i,)
        Sample times (uniform, one common step).
    y_ref : ndarray, shape (p,)
    names : sequence of str
        Episode names.
    basis : {'pod', 'identity', 'none'}
    energy : ndarray, shape (s,), optional
        Cumulative energy fraction captured by the leading POD modes (``energy[r - 1]``).
    singular_values : ndarray, shape (s,), optional
        Singular values of the centred snapshot matrix (all that were computed).
    n_states : int, optional
        Number ``n`` of full-order states.
    pairs_sq_norm : float, optional
        :math:`\\|[X_1[:, :-1], \\dots, X_E[:, :-1]]\\|_F^2` of the centred snapshots that
        start a pair (DMDc's state scale is its RMS over ``n`` rows).
    q_ref : ndarray, shape (n,), optional
    modes : ndarray, shape (n, l), optional
        The basis ``W`` when it is held in memory (``None`` for the identity, and for a
        streamed POD that did not compute its modes).
    channels : dict
        ``input_names``, ``output_names``, ``input_units``, ``output_units``.
    metadata : dict
        Merged into the metadata of every model fitted on these data (training provenance,
        coordinates, the reducer's summary).
    """

    coordinates: tuple[Array, ...] | None
    U: tuple[Array, ...]
    Y: tuple[Array, ...]
    t: tuple[Array, ...]
    y_ref: Array
    names: tuple[str, ...] = ()
    basis: str = 'pod'
    energy: Array | None = None
    singular_values: Array | None = None
    n_states: int | None = None
    pairs_sq_norm: float | None = None
    q_ref: Array | None = None
    modes: Array | None = None
    channels: dict[str, Any] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.basis not in BASES:
            raise ConfigError(f'basis must be one of {BASES}; got {self.basis!r}.')
        U = tuple(as_signal('U', u) for u in self.U)
        Y = tuple(as_signal('Y', y) for y in self.Y)
        t = tuple(np.asarray(ti, dtype=np.float64).reshape(-1) for ti in self.t)
        if not U or not len(U) == len(Y) == len(t):
            raise DimensionError(f'U, Y and t need one array per episode; got {len(U)}, '
                                 f'{len(Y)} and {len(t)}.')
        names = tuple(self.names) or tuple(f'episode{i}' for i in range(len(U)))
        if len(names) != len(U):
            raise DimensionError(f'{len(names)} episode names for {len(U)} episodes.')
        m, p = U[0].shape[0], Y[0].shape[0]
        coords: tuple[Array, ...] | None = None
        if self.coordinates is not None:
            coords = tuple(as_signal('Qhat', q) for q in self.coordinates)
            if len(coords) != len(U):
                raise DimensionError(f'Qhat, U and Y need one array per episode; got '
                                     f'{len(coords)}, {len(U)} and {len(Y)}.')
        l = None if coords is None else coords[0].shape[0]
        for i, (u, y, ti) in enumerate(zip(U, Y, t)):
            q = None if coords is None else coords[i]
            if u.shape[0] != m or y.shape[0] != p or (q is not None and q.shape[0] != l):
                raise DimensionError(
                    f'episode {names[i]!r} has (m, p) = ({u.shape[0]}, {y.shape[0]})'
                    + ('' if q is None else f' and {q.shape[0]} coordinates')
                    + f'; the first episode has ({m}, {p}).')
            ks = {u.shape[1], y.shape[1], ti.size} | ({q.shape[1]} if q is not None else set())
            if len(ks) != 1:
                raise DimensionError(f'episode {names[i]!r}: coordinates, U, Y and t must have '
                                     f'the same number of samples; got {sorted(ks)}.')
            for name, a in (('U', u), ('Y', y)) + ((('Qhat', q),) if q is not None else ()):
                check_finite(f'{name} of episode {names[i]!r}', a)
        y_ref = Y[0][:, 0] if self.y_ref is None else self.y_ref
        y_ref = as_signal('y_ref', np.reshape(np.asarray(y_ref, dtype=np.float64), (-1, 1)),
                          rows=p)[:, 0].copy()
        for key, value in (('coordinates', coords), ('U', U), ('Y', Y), ('t', t),
                           ('names', names), ('y_ref', y_ref)):
            object.__setattr__(self, key, value)

    @classmethod
    def from_arrays(cls, Qhat: Sequence[ArrayLike], U: Sequence[ArrayLike],
                    Y: Sequence[ArrayLike], dt: float, y_ref: ArrayLike | None = None, *,
                    names: Sequence[str] | None = None, energy: ArrayLike | None = None,
                    **kwargs: Any) -> ReducedData:
        """POD coordinates given directly, one ``(r, k_i)`` array per episode at step ``dt``.

        Parameters
        ----------
        Qhat : sequence of ndarray, each shape (r, k_i)
            Reduced coordinates ``Vᵀ (Q_i - q_ref)``, leading modes first.
        U, Y : sequence of ndarray
            Inputs ``(m, k_i)`` and absolute outputs ``(p, k_i)``.
        dt : float
            Sample time (s); the episodes' times are ``0, dt, 2 dt, ...``.
        y_ref : ndarray, shape (p,), optional
            Default the first output of the first episode.
        names : sequence of str, optional
        energy : ndarray, optional
            Cumulative POD energy fractions (diagnostics).
        **kwargs
            Other fields of :class:`ReducedData` (``channels``, ``metadata``, ...).
        """
        dt = float(dt)
        if not np.isfinite(dt) or dt <= 0:
            raise DimensionError(f'dt must be a positive number of seconds; got {dt!r}.')
        Us = [as_signal('U', u) for u in U]
        Ys = [as_signal('Y', y) for y in Y]
        t = [np.arange(u.shape[1], dtype=np.float64) * dt for u in Us]
        if y_ref is None and Ys:
            y_ref = Ys[0][:, 0]
        return cls(coordinates=tuple(as_signal('Qhat', q) for q in Qhat), U=tuple(Us),
                   Y=tuple(Ys), t=tuple(t),
                   y_ref=np.asarray(y_ref, dtype=np.float64), names=tuple(names or ()),
                   basis='pod', energy=None if energy is None else np.asarray(energy),
                   **kwargs)

    # -- sizes and times --------------------------------------------------------------
    @property
    def dt(self) -> float:
        """Common sample time (seconds) of the episodes."""
        return _common_dt(self.t, self.names)

    @property
    def n_coordinates(self) -> int:
        """Number ``l`` of coordinates per snapshot (0 without coordinates)."""
        return 0 if self.coordinates is None else int(self.coordinates[0].shape[0])

    @property
    def time_ranges(self) -> list[list[float]]:
        """``[t_start, t_end]`` of every episode (seconds)."""
        return [[float(ti[0]), float(ti[-1])] for ti in self.t]

    def leading(self, r: int) -> list[Array]:
        """The leading ``r`` coordinates of every episode: a list of ``(r, k_i)`` arrays."""
        if self.coordinates is None or self.basis != 'pod':
            raise ConfigError(f'the leading r coordinates need POD coordinates; these data '
                              f'have basis {self.basis!r}.')
        if not 1 <= r <= self.n_coordinates:
            raise ConfigError(f'r = {r} exceeds the {self.n_coordinates} POD coordinates '
                              'reduced; reduce with more coordinates (a larger r).')
        return [np.ascontiguousarray(z[:r]) for z in self.coordinates]

    def energy_captured(self, r: int) -> float | None:
        """Energy fraction of the leading ``r`` POD modes (``None`` when unknown)."""
        if self.energy is None or not 1 <= r <= self.energy.size:
            return None
        return float(self.energy[r - 1])

    def episode(self, i: int | str) -> Episode:
        """Episode ``i`` (index or name) with its inputs and outputs only."""
        j = self.names.index(i) if isinstance(i, str) else int(i)
        return Episode(t=self.t[j], U=self.U[j], Y=self.Y[j], name=self.names[j])

    def lift(self, V: Array) -> Array | None:
        """Coordinate-space vectors ``V`` (l, j) in full-order space ``W V`` (n, j), if known."""
        if self.basis == 'identity':
            return V
        return None if self.modes is None else self.modes[:, :V.shape[0]] @ V

    def subset(self, keep: Sequence[int]) -> ReducedData:
        """The same reduced data restricted to the episodes ``keep`` (indices)."""
        idx = [int(i) for i in keep]
        coords = None if self.coordinates is None else tuple(self.coordinates[i] for i in idx)
        return replace(self, coordinates=coords, U=tuple(self.U[i] for i in idx),
                       Y=tuple(self.Y[i] for i in idx), t=tuple(self.t[i] for i in idx),
                       names=tuple(self.names[i] for i in idx), pairs_sq_norm=None)

    def head(self, fraction: float) -> tuple[ReducedData, ReducedData]:
        """Each episode cut in a head (the first ``fraction`` of its samples) and a tail.

        Returns ``(heads, tails)``: the same episodes, each cut at the same fraction.
        """
        cuts = [max(int(round(ti.size * float(fraction))), 1) for ti in self.t]

        def part(sl: list[slice]) -> ReducedData:
            coords = None if self.coordinates is None else tuple(
                z[:, s] for z, s in zip(self.coordinates, sl))
            return replace(self, coordinates=coords,
                           U=tuple(u[:, s] for u, s in zip(self.U, sl)),
                           Y=tuple(y[:, s] for y, s in zip(self.Y, sl)),
                           t=tuple(ti[s] for ti, s in zip(self.t, sl)), pairs_sq_norm=None)

        return part([slice(None, c) for c in cuts]), part([slice(c, None) for c in cuts])

    def model_names(self) -> dict[str, Any]:
        """Channel names and units (keyword arguments of the models)."""
        return {k: list(v) for k, v in self.channels.items()
                if k in _CHANNEL_KEYS and v is not None}
