"""Time-series containers shared by every part of soft_rom.

One convention, stated once: **arrays are ``(n_channels, n_samples)``, float64, time in
seconds.** A snapshot is a column. Bag nanoseconds are converted to seconds at the bag
boundary (:mod:`soft_rom.bags`) and nowhere else.

Time: within an episode, ``t`` is float seconds from the episode's own start
(``t[0] = 0`` for converted recordings); the absolute start is an integer number of
nanoseconds, ``metadata['t0_ns']`` (an epoch stamp near 1.7e18 ns for a live recording),
never a float.

Linear models act on *deviations* from a reference configuration: states are centred on
``q_ref`` (the body at rest) and outputs on ``y_ref``; predictions are returned in absolute
coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.errors import DimensionError

__all__ = ['Episode', 'MAX_STEP_RATIO', 'all_finite', 'as_signal', 'check_finite',
           'nonuniform_message', 'step_ratio_problem',
           'step_length']


def as_signal(name: str, values: ArrayLike, *, rows: int | None = None,
              cols: int | None = None, copy: bool = False) -> NDArray[np.float64]:
    """Return ``values`` as a 2-D float64 array ``(n_channels, n_samples)`` or raise.

    Parameters
    ----------
    name : str
        Name used in error messages (``'U'``, ``'Y'``, ...).
    values : array_like, shape (n_channels, n_samples) or (n_samples,)
        A 1-D array is read as a single channel.
    rows, cols : int, optional
        Expected number of channels / samples.
    copy : bool
        Always return a copy.
    """
    try:
        if np.iscomplexobj(values):
            raise DimensionError(f'{name} must be real; got complex values (casting them would '
                                 'drop the imaginary parts).')
        arr = np.array(values, dtype=np.float64, copy=True) if copy else np.asarray(
            values, dtype=np.float64)
    except (TypeError, ValueError) as err:
        if isinstance(err, DimensionError):
            raise
        raise DimensionError(f'{name} must be an array of numbers; {err}.') from err
    given = arr.shape
    if arr.ndim == 1:
        arr = arr[np.newaxis, :]
    if arr.ndim != 2:
        raise DimensionError(
            f'{name} must be a 2-D array (n_channels, n_samples); got shape {arr.shape}.')
    if rows is not None and arr.shape[0] != rows:
        raise DimensionError(
            f'{name} must have {rows} channels (rows); got shape {given}'
            f'{" (one channel)" if len(given) == 1 else ""}. '
            'Arrays are (n_channels, n_samples): transpose if you passed (samples, channels).')
    if cols is not None and arr.shape[1] != cols:
        flipped = (' Arrays are (n_channels, n_samples): transpose if you passed (samples, '
                   'channels).' if arr.shape[0] == cols else '')
        raise DimensionError(f'{name} must have {cols} samples (columns); got shape '
                             f'{arr.shape}.{flipped}')
    return arr


def all_finite(arr: ArrayLike) -> bool:
    """True if every value of ``arr`` is finite (one pass, no temporary in the common case).

    The sum of finite values is finite unless it overflows, so the element-wise test runs
    only when the sum is not finite.
    """
    a = np.asarray(arr)
    if a.size == 0:
        return True
    with np.errstate(all='ignore'):
        total = np.add.reduce(a, axis=None)
    return bool(np.isfinite(total)) or bool(np.all(np.isfinite(a)))


def check_finite(name: str, arr: NDArray[Any], before: str = 'fitting') -> None:
    """Raise :class:`ValueError` naming ``name`` and the first bad index if ``arr`` has NaN/Inf."""
    if not all_finite(arr):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise DimensionError(
            f'{name} contains NaN or Inf (first at index {tuple(int(i) for i in bad)}); '
            f'clean or drop those samples before {before}.')


def step_length(dt: Any) -> float:
    """``dt`` as a positive finite number of seconds, or :class:`DimensionError`."""
    try:
        h = float(dt)
    except (TypeError, ValueError):
        raise DimensionError(f'dt must be a positive number of seconds; got {dt!r}.') from None
    if not (math.isfinite(h) and h > 0):
        raise DimensionError(f'dt must be positive; got {dt!r}.')
    return h


def nonuniform_message(name: str, t: ArrayLike, rtol: float = 1e-6) -> str:
    """Why the sample times ``t`` of episode ``name`` are not uniform to ``rtol``, in words.

    Names the smallest and largest step; a spread that small (under 1e-3 of the step) is
    what float32 times (about 7 digits) or float epoch seconds (about 0.2 us at 1.7e9 s)
    give, so it says to pass float64 times from the episode's start.
    """
    d = np.diff(np.asarray(t, dtype=np.float64))
    mean = float(np.mean(d)) if d.size else math.nan
    spread = float(np.max(np.abs(d - mean))) / mean if d.size and mean > 0 else math.nan
    head = f'episode {name!r} is not uniformly sampled'
    if not math.isfinite(spread):
        return f'{head} (fewer than 2 samples); resample it first (soft-rom convert --dt).'
    head += (f': its steps range from {float(d.min()):.9g} s to {float(d.max()):.9g} s '
             f'(relative spread {spread:.2g}, allowed {rtol:g})')
    if spread < 1e-3:
        return (f'{head}; float32 times, or float seconds since the epoch (1.7e9), are this '
                "coarse: give float64 times from the episode's start (e.g. np.arange(k) * dt).")
    return f'{head}; resample it first (soft-rom convert --dt).'


#: Most by which an episode's step and a model's step may differ (either way) before the
#: times are taken for other units (ms given as s: a factor of 1000), not resampling.
MAX_STEP_RATIO = 100.0


def step_ratio_problem(name: str, h: float, dt: float, method: str) -> str:
    """Why episode ``name``'s step ``h`` looks like other units than the model's ``dt``.

    Empty where the two are within a factor of :data:`MAX_STEP_RATIO`.
    """
    ratio = h / dt
    if 1.0 / MAX_STEP_RATIO <= ratio <= MAX_STEP_RATIO:
        return ''
    return (f'episode {name!r} is sampled every {h:g} s and the {method} model steps by '
            f'{dt:g} s (a factor of {ratio:.3g}): are the episode times in seconds?')


@dataclass(frozen=True)
class Episode:
    """One recorded or simulated episode.

    Parameters
    ----------
    t : ndarray, shape (k,)
        Sample times in seconds, finite and strictly increasing (uniform for fitting).
    U : ndarray, shape (m, k)
        Inputs (e.g. chamber pressures in Pa), absolute.
    Y : ndarray, shape (p, k)
        Outputs (e.g. centerline x and z coordinates in m), absolute.
    Q : array_like, shape (n, k), optional
        Full states (nodal positions), absolute. May be a lazy on-disk array (zarr) for
        large models: anything with ``.shape`` and numpy-style slicing ``Q[:, a:b]``.
    name : str
        Human-readable name (``'ep1'``).
    metadata : dict
        Provenance (source bag, topics, time range, ...); JSON-serialisable.
    """

    t: NDArray[np.float64]
    U: NDArray[np.float64]
    Y: NDArray[np.float64]
    Q: Any = None
    name: str = ''
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        k = t.size
        if not all_finite(t):
            bad = int(np.flatnonzero(~np.isfinite(t))[0])
            raise DimensionError(f'episode {self.name!r}: time stamps must be finite; '
                                 f't[{bad}] = {t[bad]}.')
        object.__setattr__(self, 't', t)
        object.__setattr__(self, 'U', as_signal('U', self.U, cols=k))
        object.__setattr__(self, 'Y', as_signal('Y', self.Y, cols=k))
        if self.Q is not None:
            shape = getattr(self.Q, 'shape', None)
            if shape is None:
                object.__setattr__(self, 'Q', as_signal('Q', self.Q, cols=k))
            elif len(shape) != 2 or shape[1] != k:
                flipped = ' (transposed? arrays are (n_channels, n_samples))' if len(
                    shape) == 2 and shape[0] == k else ''
                raise DimensionError(
                    f'Q must have shape (n, {k}) to match t; got {tuple(shape)}{flipped}.')
        if k > 1 and np.any(np.diff(t) <= 0):
            raise DimensionError(
                f'episode {self.name!r}: time stamps must be strictly increasing.')

    @property
    def n_samples(self) -> int:
        """Number of samples ``k``."""
        return int(self.t.size)

    @property
    def dt(self) -> float:
        """Mean sample time in seconds (``nan`` for a single sample)."""
        return float(np.mean(np.diff(self.t))) if self.t.size > 1 else float('nan')

    def is_uniform(self, rtol: float = 1e-6) -> bool:
        """True if the sample times are uniform to ``rtol`` of the mean step."""
        if self.t.size < 3:
            return True
        d = np.diff(self.t)
        return bool(np.max(np.abs(d - d.mean())) <= rtol * d.mean())

    def slice(self, start: int | None = None, stop: int | None = None,
              name: str | None = None) -> Episode:
        """Return samples ``start:stop`` as a new episode (``Q`` stays lazy if it was)."""
        sl = slice(start, stop)
        q = None if self.Q is None else self.Q[:, sl]
        return Episode(t=self.t[sl], U=self.U[:, sl], Y=self.Y[:, sl], Q=q,
                       name=self.name if name is None else name,
                       metadata=dict(self.metadata))

    def time_slice(self, t_start: float | None = None, t_stop: float | None = None) -> Episode:
        """Return the samples with ``t_start <= t < t_stop`` (seconds)."""
        lo = 0 if t_start is None else int(np.searchsorted(self.t, t_start - 1e-12, 'left'))
        hi = self.t.size if t_stop is None else int(
            np.searchsorted(self.t, t_stop - 1e-12, 'left'))
        return self.slice(lo, hi)
