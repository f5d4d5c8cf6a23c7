"""Time derivatives of uniformly sampled states: central finite differences, Savitzky-Golay.

Edge treatment (one rule for every order): **the edges are trimmed**. A central stencil of
order ``p`` (``p`` = 2, 4, 6, 8) has half-width ``h = p / 2``; derivatives are returned only
for the interior columns ``h .. k-h-1`` where the full stencil fits, together with the states
(and, through :meth:`FiniteDifference.trim`, any other signal such as the inputs) of the same
columns. Every returned derivative therefore has the nominal order of accuracy; an episode
loses ``h`` samples at each end (4 at order 8). Derivatives are computed per episode
(:meth:`FiniteDifference.episodes`) and never straddle two episodes.

Reference: Fornberg, *Generation of finite difference formulas on arbitrarily spaced
grids*, Math. Comp. 51 (1988) -- the coefficients below are his central-difference tables.

Measured coordinates (motion capture) carry noise: an order-``p`` difference amplifies a
noise of standard deviation ``s`` into ``q''`` by about ``c_p s / dt^2`` (``c_8 ~ 4``:
0.5 mm at 120 Hz becomes ~30 m/s^2). :class:`SavitzkyGolay` fits a polynomial of degree
``polyorder`` to a window of ``window`` samples around each point by least squares and
differentiates it (Savitzky and Golay, Anal. Chem. 36 (1964); :func:`scipy.signal.
savgol_coeffs`); its noise gain on ``q''`` falls as ``window^-2.5`` (0.5 mm at 120 Hz:
0.34 m/s^2 for window 21 and degree 4, 0.036 m/s^2 for window 31 and degree 3, whose gain
equals that of degree 2 by symmetry; degrees 4 and 5 cost 3.5x more). It is one linear
time-invariant filter ``S``: the states come back as ``S q``, the derivatives as
``(S q)'`` and ``(S q)''``, and :meth:`SavitzkyGolay.trim` returns ``S x`` for every other
signal (inputs, outputs), so that a linear relation ``q'' + C q' + K q = B u``,
``y = E q`` that holds for the raw signals holds exactly for the filtered ones, up to how
well the local polynomial resolves each mode.
Defaults: ``window = 31``, ``polyorder = 5``. The window (0.26 s at 120 Hz) is set by the
noise: its gain on ``q''`` falls as ``window^-2.5``. The degree is set by the bias: noise on
``q''`` (the regressand of the fit) averages out in the least-squares problem, while a
too-low degree flattens the modes that are kept (the lab-rig measurements behind these
defaults are in ``docs/methods.md``). Scale the window with the sample rate (the same time
span) and lengthen it for noisier data. The same trimming rule holds: ``window // 2``
samples are lost at each end of an episode.

Names for command lines (:func:`parse_estimator`): ``fd2``, ``fd4``, ``fd6``, ``fd8``,
``savgol`` (defaults) or ``savgol:WINDOW`` / ``savgol:WINDOW:POLYORDER``.
"""

from __future__ import annotations

from collections.abc import Sequence
from fractions import Fraction as F
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.errors import ConfigError, DimensionError

__all__ = ['DerivativeEstimator', 'FiniteDifference', 'SavitzkyGolay', 'as_estimator',
           'parse_estimator']

Array = NDArray[np.float64]

# Central stencils on offsets -h..h (Fornberg 1988, table 1).
_FIRST: dict[int, list[F | int]] = {
    2: [F(-1, 2), 0, F(1, 2)],
    4: [F(1, 12), F(-2, 3), 0, F(2, 3), F(-1, 12)],
    6: [F(-1, 60), F(3, 20), F(-3, 4), 0, F(3, 4), F(-3, 20), F(1, 60)],
    8: [F(1, 280), F(-4, 105), F(1, 5), F(-4, 5), 0, F(4, 5), F(-1, 5), F(4, 105),
        F(-1, 280)],
}
_SECOND: dict[int, list[F | int]] = {
    2: [1, -2, 1],
    4: [F(-1, 12), F(4, 3), F(-5, 2), F(4, 3), F(-1, 12)],
    6: [F(1, 90), F(-3, 20), F(3, 2), F(-49, 18), F(3, 2), F(-3, 20), F(1, 90)],
    8: [F(-1, 560), F(8, 315), F(-1, 5), F(8, 5), F(-205, 72), F(8, 5), F(-1, 5), F(8, 315),
        F(-1, 560)],
}


def _states(Q: ArrayLike, need: int, what: str) -> Array:
    """``Q`` as a 2-D ``(r, k)`` float array with at least ``need`` samples for ``what``."""
    X = np.asarray(Q, dtype=np.float64)
    if X.ndim == 1:
        X = X[np.newaxis, :]
    if X.ndim != 2:
        raise DimensionError(f'states must be 2-D (r, k); got shape {X.shape}.')
    if X.shape[1] < need:
        raise DimensionError(f'{what} needs at least {need} samples per episode; got '
                             f'{X.shape[1]}.')
    return X


def _check_dt(dt: float) -> None:
    if not np.isfinite(dt) or dt <= 0:
        raise DimensionError(f'dt must be a positive number of seconds; got {dt!r}.')


@runtime_checkable
class DerivativeEstimator(Protocol):
    """What the LOpInf learner needs from a derivative estimator."""

    def derivatives(self, Q: ArrayLike, dt: float) -> tuple[Array, Array, Array]:
        """Return aligned ``(states, first, second)`` derivatives of ``Q`` (r, k)."""
        ...

    def trim(self, X: ArrayLike) -> Array:
        """Return the columns of ``X`` (c, k) aligned with :meth:`derivatives`' output."""
        ...


class FiniteDifference:
    """Central finite differences of order 2, 4, 6 or 8 with trimmed edges.

    .. math::

        \\dot q_j \\approx \\frac{1}{\\Delta t}\\sum_{i=-h}^{h} a_i q_{j+i}, \\qquad
        \\ddot q_j \\approx \\frac{1}{\\Delta t^2}\\sum_{i=-h}^{h} b_i q_{j+i},
        \\qquad h = p/2,

    both with truncation error :math:`O(\\Delta t^p)`.

    Parameters
    ----------
    order : int
        Order of accuracy ``p``: 2, 4, 6 or 8 (default 8).
    """

    def __init__(self, order: int = 8) -> None:
        if order not in _FIRST:
            raise ConfigError(f'finite-difference order must be one of 2, 4, 6, 8; got {order!r}.')
        self.order = int(order)

    def __repr__(self) -> str:
        return f'FiniteDifference(order={self.order})'

    def __str__(self) -> str:
        return f'fd{self.order}'                # as --ddt spells it

    @property
    def half_width(self) -> int:
        """Samples lost at each end of an episode (``order // 2``)."""
        return self.order // 2

    def _check(self, Q: ArrayLike) -> Array:
        return _states(Q, self.order + 1, f'an order-{self.order} central difference')

    def trim(self, X: ArrayLike) -> Array:
        """Columns ``h .. k-h-1`` of ``X`` (c, k): those that have derivatives."""
        X = self._check(X)
        h = self.half_width
        return X[:, h:X.shape[1] - h]

    def derivatives(self, Q: ArrayLike, dt: float) -> tuple[Array, Array, Array]:
        """First and second time derivatives of one episode.

        Parameters
        ----------
        Q : ndarray, shape (r, k)
            Uniformly sampled states, one column per sample.
        dt : float
            Sample time in seconds.

        Returns
        -------
        Q_mid : ndarray, shape (r, k - order)
            The states at the columns where derivatives exist (:meth:`trim` of ``Q``).
        Qd, Qdd : ndarray, shape (r, k - order)
            First and second derivatives at those columns.
        """
        X = self._check(Q)
        _check_dt(dt)
        h, k = self.half_width, X.shape[1]
        n = k - 2 * h
        d1 = np.zeros((X.shape[0], n))
        d2 = np.zeros((X.shape[0], n))
        for i, (a, b) in enumerate(zip(_FIRST[self.order], _SECOND[self.order])):
            cols = X[:, i:i + n]
            if a:
                d1 += float(a) * cols
            if b:
                d2 += float(b) * cols
        return X[:, h:k - h].copy(), d1 / dt, d2 / dt ** 2

    def episodes(self, Qs: Sequence[ArrayLike], dt: float,
                 others: Sequence[Sequence[ArrayLike]] = ()
                 ) -> tuple[Array, Array, Array, list[Array]]:
        """Derivatives of several episodes, each on its own, stacked along time.

        Parameters
        ----------
        Qs : sequence of ndarray, each shape (r, k_i)
        dt : float
        others : sequence of sequences of ndarray
            Other signals (e.g. ``[U_list]``) to trim the same way, one list per signal with
            one ``(c, k_i)`` array per episode.

        Returns
        -------
        Q, Qd, Qdd : ndarray, shape (r, sum_i (k_i - order))
        trimmed : list of ndarray
            One stacked, trimmed array per entry of ``others``.
        """
        return _episodes(self, Qs, dt, others)


class SavitzkyGolay:
    """Smoothing derivatives by local least-squares polynomials, trimmed edges.

    Parameters
    ----------
    window : int
        Odd number of samples per local fit (default 31; at least ``polyorder + 2``).
    polyorder : int
        Degree of the local polynomial, 2 or more (default 5).
    """

    def __init__(self, window: int = 31, polyorder: int = 5) -> None:
        window, polyorder = int(window), int(polyorder)
        if polyorder < 2:
            raise ConfigError(f'Savitzky-Golay polyorder must be >= 2 for a second '
                              f'derivative; got {polyorder}.')
        if window % 2 == 0 or window < polyorder + 2:
            raise ConfigError(f'Savitzky-Golay window must be odd and >= polyorder + 2 = '
                              f'{polyorder + 2}; got {window}.')
        self.window = window
        self.polyorder = polyorder

    def __repr__(self) -> str:
        return f'SavitzkyGolay(window={self.window}, polyorder={self.polyorder})'

    def __str__(self) -> str:
        return f'savgol:{self.window}:{self.polyorder}'     # as --ddt spells it

    @property
    def half_width(self) -> int:
        """Samples lost at each end of an episode (``window // 2``)."""
        return self.window // 2

    def _check(self, Q: ArrayLike) -> Array:
        return _states(Q, self.window, f'a Savitzky-Golay window of {self.window}')

    def trim(self, X: ArrayLike) -> Array:
        """``X`` (c, k) filtered like the states, at the columns that have derivatives."""
        return self._filter(self._check(X), 0, 1.0)

    def _filter(self, X: Array, deriv: int, dt: float) -> Array:
        from scipy.signal import savgol_coeffs

        n = X.shape[1] - 2 * self.half_width
        # use='dot': coefficient i multiplies X[j - h + i] (offsets -h..h in order)
        c = savgol_coeffs(self.window, self.polyorder, deriv=deriv, delta=dt, use='dot')
        acc = np.zeros((X.shape[0], n))
        for i, ci in enumerate(c):
            acc += ci * X[:, i:i + n]
        return acc

    def derivatives(self, Q: ArrayLike, dt: float) -> tuple[Array, Array, Array]:
        """Smoothed states and their first and second derivatives at the interior columns.

        Parameters
        ----------
        Q : ndarray, shape (r, k)
        dt : float
            Sample time in seconds.

        Returns
        -------
        Q_mid, Qd, Qdd : ndarray, shape (r, k - 2 * (window // 2))
        """
        X = self._check(Q)
        _check_dt(dt)
        return self._filter(X, 0, dt), self._filter(X, 1, dt), self._filter(X, 2, dt)

    def episodes(self, Qs: Sequence[ArrayLike], dt: float,
                 others: Sequence[Sequence[ArrayLike]] = ()
                 ) -> tuple[Array, Array, Array, list[Array]]:
        """Derivatives of several episodes, each on its own (as :class:`FiniteDifference`)."""
        return _episodes(self, Qs, dt, others)


def _episodes(est: FiniteDifference | SavitzkyGolay, Qs: Sequence[ArrayLike], dt: float,
              others: Sequence[Sequence[ArrayLike]]) -> tuple[Array, Array, Array, list[Array]]:
    """``est.episodes``: each episode differentiated on its own, then stacked along time."""
    parts = [est.derivatives(Q, dt) for Q in Qs]
    if not parts:
        raise DimensionError('no episode given.')
    stacked = [np.concatenate([p[j] for p in parts], axis=1) for j in range(3)]
    trimmed = []
    for signal in others:
        if len(signal) != len(parts):
            raise DimensionError('every signal in others needs one array per episode.')
        trimmed.append(np.concatenate([est.trim(x) for x in signal], axis=1))
    return stacked[0], stacked[1], stacked[2], trimmed


def parse_estimator(text: str) -> DerivativeEstimator:
    """An estimator from its command-line name: ``fd2`` .. ``fd8``, ``savgol[:W[:P]]``."""
    s = str(text).strip().lower()
    if s in ('fd2', 'fd4', 'fd6', 'fd8'):
        return FiniteDifference(int(s[2]))
    if s == 'savgol' or s.startswith('savgol:'):
        parts = s.split(':')[1:]
        try:
            nums = [int(x) for x in parts]
        except ValueError as err:
            raise ConfigError(f'--ddt {text!r}: savgol takes integers, savgol:WINDOW or '
                              'savgol:WINDOW:POLYORDER.') from err
        if len(nums) > 2:
            raise ConfigError(f'--ddt {text!r}: at most savgol:WINDOW:POLYORDER.')
        return SavitzkyGolay(*nums)
    raise ConfigError(f'--ddt must be fd2, fd4, fd6, fd8, savgol, savgol:WINDOW or '
                      f'savgol:WINDOW:POLYORDER; got {text!r}.')


def as_estimator(ddt: int | str | DerivativeEstimator) -> DerivativeEstimator:
    """An estimator from an order (8: ``FiniteDifference(8)``), a name, or an estimator.

    Names are those of :func:`parse_estimator`.
    """
    if isinstance(ddt, (int, np.integer)) and not isinstance(ddt, bool):
        return FiniteDifference(int(ddt))
    if isinstance(ddt, str):
        return parse_estimator(ddt)
    if isinstance(ddt, DerivativeEstimator):
        return ddt
    raise ConfigError(f'ddt must be an order (2, 4, 6, 8), a name (fd8, savgol) or an object '
                      f'with derivatives() and trim(); got {ddt!r}.')
