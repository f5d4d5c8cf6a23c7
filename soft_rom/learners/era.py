"""ERA/OKID: linear ROMs from input/output data alone (paper section 2.4).

Two steps, each usable alone:

1. :func:`okid_markov` -- observer/Kalman filter identification (Juang, Phan, Horta & Longman,
   *Identification of observer/Kalman filter Markov parameters: theory and experiments*,
   J. Guid. Control Dyn. 16(2), 1993). With :math:`v_k = [u_k; y_k]` the observer model

   .. math:: y_k = D u_k + \\sum_{i=1}^{l} \\bar Y_i v_{k-i},
       \\qquad \\bar Y_i = C \\bar A^{i-1} [B + G D, \\; -G],

   is fitted by least squares over the samples :math:`k = l, \\dots, K-1` (no assumption on
   the initial state), and the system Markov parameters are recovered by

   .. math:: Y_0 = D, \\qquad
       Y_k = \\bar Y^{(1)}_k + \\sum_{i=1}^{\\min(k, l)} \\bar Y^{(2)}_i Y_{k-i},

   with :math:`\\bar Y^{(1)}_k = 0` for :math:`k > l`; so any number of Markov parameters
   can be computed from an observer of order ``l``.
2. :func:`era` -- the eigensystem realization algorithm (Juang & Pappa, *An eigensystem
   realization algorithm for modal parameter identification and model reduction*, J. Guid.
   Control Dyn. 8(5), 1985): block Hankel matrices :math:`H_0 = [Y_{i+j+1}]`,
   :math:`H_1 = [Y_{i+j+2}]`, SVD :math:`H_0 = P S Q^\\top`, and

   .. math:: A = S_r^{-1/2} P_r^\\top H_1 Q_r S_r^{-1/2}, \\quad
       B = S_r^{1/2} Q_r^\\top E_m, \\quad C = E_p^\\top P_r S_r^{1/2}, \\quad D = Y_0.

The model is :math:`x_{k+1} = A x_k + B u_k`, :math:`y_k = C x_k + D u_k + y_{ref}`.

The horizon problem and its knobs. With ``p = 40`` outputs the observer regression has
``m + l (m + p)`` unknowns per output row, so ``K`` samples allow an observer of order
``l < K / (m + p + 1)`` (a few dozen samples at 1 kHz), while the slow modes of a soft body
last seconds. The knobs:

* ``observer_order`` (``l``) and the ridge weight of the (well-posed) OKID solve;
* ``n_markov``: how many system Markov parameters feed the Hankel matrices (their time span
  ``n_markov · dt_model`` should cover the slow modes);
* ``decimation``: fit at ``dt_fit = decimation · dt_data``: outputs are sampled every
  ``decimation`` samples and inputs averaged over each block (the input held over one model
  step); the model is then resampled to the data step when possible.

:class:`ERAOKID` chooses them from the data by the held-out error of a cross-validation
over blocks of the episode (:mod:`soft_rom.learners.era_select`, which also explains why the
ridge solve is needed); named presets (:data:`ERA_PRESETS`) give the hand-tuned settings.

About 710 lines: the learner's fit carries the search over decimations, the refit on the
whole episode and the presets; the selection itself lives in
:mod:`soft_rom.learners.era_select`.

Unit invariance: inputs and outputs are divided by their per-channel RMS before OKID/ERA
and the realization is scaled back (``B = B_s diag(1/s_u)``, ``C = diag(s_y) C_s``,
``D = diag(s_y) D_s diag(1/s_u)``); the Hankel singular values are those of the scaled data.
"""

from __future__ import annotations

from collections.abc import Sequence
import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import as_signal, check_finite, Episode
from soft_rom.envelope import training_envelope
from soft_rom.errors import ConfigError, DimensionError, NotFittedError
from soft_rom.learners import era_select
from soft_rom.learners.dmdc import channel_scale
from soft_rom.models import DiscreteModel
from soft_rom.resources import check_memory

__all__ = ['ERA_EEL_OPTIONS', 'ERA_PRESETS', 'ERAOKID', 'check_hankel_memory', 'decimate',
           'era', 'hankel_rank', 'okid_markov']

#: The hand-tuned settings of the eel study (1 kHz, 40 outputs, slow lightly damped modes):
#: identify on the 4 leading output principal components at the full rate with a 36-step
#: observer and 500 Markov parameters (0.5 s), plain least squares (no ridge, no selection).
ERA_EEL_OPTIONS: dict[str, Any] = {'decimation': 1, 'output_rank': 4, 'observer_order': 36,
                                   'n_markov': 500, 'selection': 'none', 'refit': False,
                                   'output_scale_floor': 0.0, 'input_rank': None}

#: Named settings for :meth:`ERAOKID.from_preset` (and ``soft-rom fit --era-preset``):
#: ``'auto'`` the data-driven defaults; ``'eel'`` the study's hand-tuned settings;
#: ``'legacy'`` the former defaults (decimation 5, 100 Markov parameters, automatic
#: observer order capped at 10, Hankel singular value rule for r).
ERA_PRESETS: dict[str, dict[str, Any]] = {
    'auto': {},
    'eel': ERA_EEL_OPTIONS,
    'legacy': {'decimation': 5, 'n_markov': 100, 'max_observer_order': 10,
               'output_rank': None, 'selection': 'none', 'refit': False,
               'output_scale_floor': 0.0, 'input_rank': None},
}

Array = NDArray[np.float64]


def decimate(U: ArrayLike, Y: ArrayLike, factor: int) -> tuple[Array, Array]:
    """Resample input/output data at ``factor`` times the sample time.

    Outputs are sampled at the start of each block (``Y[:, ::factor]``); inputs are averaged
    over the block (the value held during one model step). Only complete blocks are kept.

    Parameters
    ----------
    U : ndarray, shape (m, k)
    Y : ndarray, shape (p, k)
    factor : int

    Returns
    -------
    Ud : ndarray, shape (m, k // factor)
    Yd : ndarray, shape (p, k // factor)
    """
    U = as_signal('U', U)
    Y = as_signal('Y', Y, cols=U.shape[1])
    d = int(factor)
    if d < 1:
        raise ConfigError(f'decimation must be a positive integer; got {factor!r}.')
    if d == 1:
        return U, Y
    kd = U.shape[1] // d
    Ud = U[:, :kd * d].reshape(U.shape[0], kd, d).mean(axis=2)
    return Ud, Y[:, :kd * d:d]


def okid_markov(U: ArrayLike, Y: ArrayLike, *, observer_order: int, n_markov: int,
                rcond: float | None = None, ridge: float | None = None,
                intercept: bool = False) -> tuple[Array, dict[str, Any]]:
    """System Markov parameters from arbitrary input/output data by OKID.

    Parameters
    ----------
    U : ndarray, shape (m, K)
        Inputs (deviations or absolute: the model has no input offset).
    Y : ndarray, shape (p, K)
        Output deviations from ``y_ref``.
    observer_order : int
        ``l``, number of past samples in the observer model; needs
        ``K - l >= m + l (m + p)``.
    n_markov : int
        Number of Markov parameters ``Y_1 .. Y_n_markov`` to return besides ``Y_0 = D``.
    rcond : float, optional
        Cut-off for the least-squares solve (``numpy.linalg.lstsq``).
    ridge : float, optional
        Relative Tikhonov weight ``ρ`` (``λ = ρ σ_1(Φ)²``;
        :mod:`soft_rom.learners.era_select`): the well-posed solve. ``None``: plain least
        squares (exact data only).
    intercept : bool
        Ridge solve with an unpenalized constant term (insensitive to an output offset).

    Returns
    -------
    markov : ndarray, shape (n_markov + 1, p, m)
        ``markov[0] = D``, ``markov[k] = C A^{k-1} B``.
    info : dict
        ``residual`` (relative residual of the observer fit), ``rank`` and ``n_unknowns``.
    """
    U = as_signal('U', U)
    Y = as_signal('Y', Y, cols=U.shape[1])
    m, K = U.shape
    p = Y.shape[0]
    lo = int(observer_order)
    nm = int(n_markov)
    if lo < 1:
        raise ConfigError(f'observer_order must be >= 1; got {observer_order!r}.')
    if nm < 1:
        raise ConfigError(f'n_markov must be >= 1; got {n_markov!r}.')
    n_unknowns = m + lo * (m + p)
    rows = K - lo
    if rows < n_unknowns:
        kmax = (K - m) // (m + p + 1)
        raise ConfigError(
            f'OKID with observer_order={lo} has {n_unknowns} unknowns per output but only '
            f'{rows} equations ({K} samples): use observer_order <= {max(kmax, 0)}, more data, '
            'or less decimation.')
    if ridge is not None:
        markov, info = era_select.ridge_markov(U, Y, lo, nm, (float(ridge),), intercept)[0]
        info['rank'] = info['effective_rank']
        return markov, info
    V = np.concatenate([U, Y], axis=0)                       # (m + p, K)
    Phi = np.empty((n_unknowns, rows))
    Phi[:m] = U[:, lo:]
    for i in range(1, lo + 1):
        a = m + (i - 1) * (m + p)
        Phi[a:a + m + p] = V[:, lo - i:K - i]
    theta, _, rank, _ = np.linalg.lstsq(Phi.T, Y[:, lo:].T, rcond=rcond)
    theta = theta.T                                          # (p, n_unknowns)
    resid = Y[:, lo:] - theta @ Phi
    den = np.linalg.norm(Y[:, lo:])
    markov = era_select.markov_from_observer(theta, m, p, lo, nm)
    info = {'residual': float(np.linalg.norm(resid) / den) if den > 0 else 0.0,
            'rank': int(rank), 'n_unknowns': int(n_unknowns)}
    return markov, info


def check_hankel_memory(rows: int, cols: int, copies: float = 4.0) -> None:
    """Refuse Hankel matrices of ``rows`` x ``cols`` that would not fit in memory.

    ``copies``: matrices of that size alive at once (``H_0``, ``H_1`` and the SVD's factors
    and workspace). Raises :class:`~soft_rom.errors.ResourceError` before they are built.
    """
    check_memory(8.0 * copies * rows * cols, f'ERA on a {rows} x {cols} Hankel matrix',
                 'Use a shorter Markov horizon (n_markov), decimation, or fewer outputs '
                 '(output_rank).')


def _hankel(markov: Array, start: int, rows: int, cols: int) -> Array:
    """Block Hankel matrix ``[Y_{start+i+j}]`` (rows · p, cols · m), from a strided view."""
    _, p, m = markov.shape
    mk = np.ascontiguousarray(markov[start:start + rows + cols - 1])
    s0, s1, s2 = mk.strides
    view = np.lib.stride_tricks.as_strided(mk, shape=(rows, p, cols, m),
                                           strides=(s0, s1, s0, s2), writeable=False)
    return np.ascontiguousarray(view.reshape(rows * p, cols * m))


def hankel_rank(hsv: ArrayLike, *, tol: float = 1e-3) -> int:
    """Default order rule: number of Hankel singular values above ``tol · σ_1``.

    Parameters
    ----------
    hsv : ndarray, shape (s,)
        Hankel singular values, descending.
    tol : float
        Relative threshold (on the scaled data, so independent of units).
    """
    s = np.asarray(hsv, dtype=np.float64).reshape(-1)
    if s.size == 0 or s[0] <= 0:
        raise DimensionError('all Hankel singular values are zero: the outputs do not respond '
                             'to the inputs in these data.')
    return max(int(np.sum(s > tol * s[0])), 1)


def era(markov: ArrayLike, r: int | None = None, *, n_block_rows: int | None = None,
        n_block_cols: int | None = None,
        tol: float = 1e-3, _factors: dict[str, Array] | None = None
        ) -> tuple[Array, Array, Array, Array, Array]:
    """Eigensystem realization from Markov parameters (Juang & Pappa 1985).

    Parameters
    ----------
    markov : ndarray, shape (N + 1, p, m)
        ``markov[0] = D``, ``markov[k] = C A^{k-1} B``.
    r : int, optional
        Order; ``None``: :func:`hankel_rank` with ``tol``.
    n_block_rows, n_block_cols : int, optional
        Block rows/columns of the Hankel matrices; need ``rows + cols <= N``. Default: split
        the ``N`` Markov parameters so that ``H_0`` is about square (``rows · p ≈ cols · m``).

    Returns
    -------
    A : ndarray, shape (r, r)
    B : ndarray, shape (r, m)
    C : ndarray, shape (p, r)
    D : ndarray, shape (p, m)
    hsv : ndarray
        All Hankel singular values of ``H_0`` (to choose ``r``).
    """
    markov = np.asarray(markov, dtype=np.float64)
    if markov.ndim != 3 or markov.shape[0] < 3:
        raise DimensionError(
            f'markov must have shape (N + 1, p, m) with N >= 2; got {markov.shape}.')
    N = markov.shape[0] - 1
    p, m = markov.shape[1:]
    if n_block_rows is None and n_block_cols is None:
        # Balance the Hankel matrix: rows·p ≈ cols·m (square H0, the cheapest SVD for the
        # largest attainable rank).
        n_block_rows = min(max(int(round(N * m / (m + p))), 1), N - 1)
        n_block_cols = N - n_block_rows
    elif n_block_rows is None and n_block_cols is not None:
        n_block_rows = N - int(n_block_cols)
    elif n_block_cols is None and n_block_rows is not None:
        n_block_cols = N - int(n_block_rows)
    assert n_block_rows is not None and n_block_cols is not None
    a, b = int(n_block_rows), int(n_block_cols)
    if a < 1 or b < 1 or a + b > N:
        raise ConfigError(f'Hankel blocks ({a} rows, {b} columns) need 1 <= rows, cols and '
                          f'rows + cols <= {N} (the number of Markov parameters).')
    check_hankel_memory(a * p, b * m)
    H0 = _hankel(markov, 1, a, b)
    H1 = _hankel(markov, 2, a, b)
    P, s, Qt = np.linalg.svd(H0, full_matrices=False)
    r = hankel_rank(s, tol=tol) if r is None else int(r)
    if not 1 <= r <= s.size or s[r - 1] <= 0:
        raise ConfigError(f'r must be between 1 and the numerical rank of the Hankel matrix '
                          f'({int(np.sum(s > 0))} of {s.size} singular values > 0); got {r}.')
    R = min(max(r, _CACHED_ORDERS), int(np.sum(s > 0)))
    factors = {'M': P[:, :R].T @ H1 @ Qt[:R].T, 's': s, 'Qm': Qt[:R, :m].copy(),
               'Pp': P[:p, :R].copy(), 'D': markov[0].copy()}
    if _factors is not None:
        _factors.update(factors)
    A, B, C, D = _era_from_factors(factors, r)
    return A, B, C, D, s


#: Orders whose realizations :func:`era` keeps factors for (``ERAOKID.model_for``).
_CACHED_ORDERS = 200


def _era_from_factors(f: dict[str, Array], r: int) -> tuple[Array, Array, Array, Array]:
    """Order-``r`` ERA realization from the factors :func:`era` kept (``r <= R``)."""
    sq = np.sqrt(f['s'][:r])
    A = f['M'][:r, :r] / np.outer(sq, sq)
    B = sq[:, None] * f['Qm'][:r]
    C = f['Pp'][:, :r] * sq[None, :]
    return A, B, C, f['D'].copy()


class ERAOKID:
    """ERA/OKID learner: a discrete ROM from the inputs and outputs of one episode.

    Defaults (``selection='holdout'``): well-posed ridge OKID (module
    :mod:`soft_rom.learners.era_select`), with the decimation, the observer order ``l``, the
    ridge weight ``ρ``, the OKID intercept and the order ``r`` chosen together by the held-out
    error of the stabilized, output-refitted ERA model in a blocked cross-validation over the
    episode (5 blocks, each predicted by a model fitted without it; errors within ``tie_tol``
    of the best are tied and broken by a fixed preference, so tiny perturbations do not change
    the choice), then refitted on the whole episode; the Markov horizon is a third of the
    samples (at most 500); outputs are identified on their leading principal components and
    inputs on the directions the data excite. Any of ``r``, ``observer_order``,
    ``okid_ridge`` given by hand is kept fixed in the search.

    Parameters
    ----------
    r : int, optional
        Order of the ROM; ``None``: selected (``selection='holdout'``) or the Hankel
        singular value rule (``selection='none'``).
    n_markov : int, optional
        System Markov parameters used in the Hankel matrices (their span is
        ``n_markov · decimation · dt``); ``None``: ``min(K // 3, 500)``. At most ``K - 1``
        (``K`` samples after decimation): a longer horizon is refused
        (:class:`~soft_rom.errors.ConfigError`) before any work.
    observer_order : int, optional
        OKID observer order ``l``; ``None``: selected, or (``selection='none'``) the largest
        order with two equations per unknown, capped at ``max_observer_order``. An order the
        data cannot fit is refused (:class:`~soft_rom.errors.ConfigError`), never replaced:
        with ``selection='holdout'`` it must leave two equations per unknown in the
        training part of a fold, with ``'none'`` one per unknown in the episode.
    decimation : int or 'auto'
        Fit at ``decimation`` times the data sample time; ``'auto'`` (default): a factor of
        :data:`~soft_rom.learners.era_select.DECIMATION_GRID`, selected with the other
        settings by the cross-validated error. A model fitted at ``d > 1`` is resampled to the
        data step (:func:`~soft_rom.learners.era_select.to_data_rate`: exact ``d``-th root), so it
        predicts on the data grid without interpolation; the metadata state ``decimation``,
        ``dt_fit``, ``dt_model`` and ``resampled_to_data_rate``. If no real root exists the
        model keeps ``dt = d · dt_data`` (printed by ``soft-rom fit``).
    n_block_rows, n_block_cols : int, optional
        Hankel block sizes (default: ``H_0`` about square).
    hsv_tol : float
        Threshold of the Hankel singular value rule.
    max_observer_order : int
        Cap of the equation-count observer order (``selection='none'``).
    output_rank : int, 'auto' or None
        Identify on the leading ``output_rank`` principal components of the scaled outputs
        (``Y_s ≈ P Z``) and lift ``C = P C_Z``, ``D = P D_Z``; ``'auto'`` (default): the
        components holding 99 % of the energy, at least ``min(p, 4)``; ``None``: all ``p``.
    input_rank : int, 'auto' or None
        Identify on the input directions the data excite
        (:func:`~soft_rom.learners.era_select.compress_inputs`; ``'auto'``, default: singular
        values of the scaled inputs above ``1e-8`` of the largest), so that the responses to
        input combinations never applied (antagonistic pairs) are zero instead of
        undetermined; ``None``: all ``m`` inputs (the presets).
    okid_rcond : float, optional
        Relative singular-value cut-off of the plain least-squares OKID solve (only when
        ``okid_ridge`` is ``None`` and ``selection='none'``).
    okid_ridge : float, optional
        Relative ridge weight ``ρ`` of OKID; ``None``: selected from
        :data:`~soft_rom.learners.era_select.RIDGE_GRID` (``selection='holdout'``) or plain
        least squares (``selection='none'``).
    selection : {'holdout', 'none'}
        Data-driven settings (default) or the given ones as they are.
    holdout : float
        Fraction of the episode held out in each fold of the selection (``1 / holdout``
        blocks).
    criterion : {'blocked', 'tail'}
        Blocked cross-validation (default) or the former single held-out tail
        (:func:`~soft_rom.learners.era_select.cv_folds`).
    refit : bool
        Stabilize the realization (eigenvalues outside the unit circle reflected inside) and
        refit ``C, D`` by least squares on the simulated states (default); ``False``: the ERA
        realization as it is (the presets).
    tie_tol : float
        Relative band of held-out errors treated as tied in the selection.
    output_scale_floor : float
        Output channels are scaled by their RMS, at least this fraction of the largest
        channel RMS (``0``: plain per-channel RMS, as the presets).
    blas_threads : int, optional
        BLAS threads while fitting (needs ``threadpoolctl``; without it, or with ``None``, the
        process's setting applies). Default 1: the many medium-sized factorizations of the
        selection run many times slower with threads on a loaded machine.

    Presets: :meth:`from_preset` with a name of :data:`ERA_PRESETS` (``'eel'``: the study's
    hand-tuned settings :data:`ERA_EEL_OPTIONS`).

    Attributes
    ----------
    model_ : DiscreteModel
        ``method='era'``, ``dt = decimation · dt_data``.
    hankel_singular_values_ : ndarray
    markov_ : ndarray, shape (n_markov + 1, p, m)
        Markov parameters of the scaled data.
    observer_order_ : int
    okid_ridge_ : float or None
    selection_ : dict or None
        The search table (``selection='holdout'``).
    okid_residual_ : float
        Relative residual of the observer fit.
    output_basis_ : ndarray, shape (p, q) or None
        Output principal directions used when ``output_rank`` is set.
    y_ref_ : ndarray, shape (p,)
    input_scale_, output_scale_ : ndarray
    """

    def __init__(self, r: int | None = None, *, n_markov: int | None = None,
                 observer_order: int | None = None, decimation: int | str = 'auto',
                 n_block_rows: int | None = None, n_block_cols: int | None = None,
                 hsv_tol: float = 1e-3, max_observer_order: int = 10,
                 output_rank: int | str | None = 'auto', okid_rcond: float | None = None,
                 okid_ridge: float | None = None, selection: str = 'holdout',
                 holdout: float = 0.2, refit: bool = True,
                 tie_tol: float = era_select.TIE_TOL,
                 output_scale_floor: float = era_select.OUTPUT_SCALE_FLOOR,
                 input_rank: int | str | None = 'auto', criterion: str = 'blocked',
                 blas_threads: int | None = 1) -> None:
        self.r = r
        self.n_markov = n_markov
        self.observer_order = observer_order
        self.decimation = decimation
        self.n_block_rows = n_block_rows
        self.n_block_cols = n_block_cols
        self.hsv_tol = hsv_tol
        self.max_observer_order = max_observer_order
        self.output_rank = output_rank
        self.okid_rcond = okid_rcond
        self.okid_ridge = okid_ridge
        self.selection = selection
        self.holdout = holdout
        self.refit = refit
        self.tie_tol = tie_tol
        self.output_scale_floor = output_scale_floor
        self.input_rank = input_rank
        self.criterion = criterion
        self.blas_threads = blas_threads

    @classmethod
    def from_preset(cls, name: str, **overrides: Any) -> ERAOKID:
        """A learner with the settings of :data:`ERA_PRESETS` ``[name]`` (then ``overrides``)."""
        if name not in ERA_PRESETS:
            raise ConfigError(f'unknown ERA preset {name!r}; choose one of '
                              f'{sorted(ERA_PRESETS)}.')
        return cls(**{**ERA_PRESETS[name], **overrides})

    def fit(self, episode: Episode | Sequence[Episode], y_ref: ArrayLike | None = None, *,
            input_names: Sequence[str] | None = None,
            output_names: Sequence[str] | None = None,
            input_units: Sequence[str] | None = None,
            output_units: Sequence[str] | None = None,
            metadata: dict[str, Any] | None = None) -> ERAOKID:
        """Identify the ROM from one episode (see the class for the settings).

        Parameters
        ----------
        episode : Episode
            Uniformly sampled ``U (m, k)``, ``Y (p, k)``; ``Q`` is ignored. A list with one
            episode is accepted; several are refused (OKID needs one continuous record).
        y_ref : ndarray, shape (p,), optional
            Output reference; default the first output sample.

        Returns
        -------
        self
        """
        with era_select.blas_threads(self.blas_threads):
            return self._fit(episode, y_ref, input_names=input_names,
                             output_names=output_names, input_units=input_units,
                             output_units=output_units, metadata=metadata)

    def _fit(self, episode: Episode | Sequence[Episode], y_ref: ArrayLike | None, *,
             input_names: Sequence[str] | None, output_names: Sequence[str] | None,
             input_units: Sequence[str] | None, output_units: Sequence[str] | None,
             metadata: dict[str, Any] | None) -> ERAOKID:
        t0 = time.perf_counter()
        ep = _one_episode(episode)
        if not ep.is_uniform():
            raise DimensionError(f'episode {ep.name!r} is not uniformly sampled.')
        check_finite(f'U of episode {ep.name!r}', ep.U)
        check_finite(f'Y of episode {ep.name!r}', ep.Y)
        m, p = ep.U.shape[0], ep.Y.shape[0]
        y_ref = ep.Y[:, 0].copy() if y_ref is None else as_signal(
            'y_ref', np.reshape(y_ref, (-1, 1)), rows=p)[:, 0]
        if self.selection not in ('holdout', 'none'):
            raise ConfigError(f"selection must be 'holdout' or 'none'; got {self.selection!r}.")
        if self.criterion not in ('blocked', 'tail'):
            raise ConfigError(f"criterion must be 'blocked' or 'tail'; got {self.criterion!r}.")
        rank = self.input_rank
        if not (rank is None or rank == 'auto' or (isinstance(rank, (int, np.integer))
                                                   and not isinstance(rank, bool)
                                                   and 1 <= rank <= m)):
            raise ConfigError(f"input_rank must be None, 'auto' or an integer from 1 to m = {m}; "
                              f'got {rank!r}.')
        auto_d = self.decimation == 'auto'
        selecting = self.selection == 'holdout' or auto_d
        if auto_d:
            grid = [d for d in era_select.DECIMATION_GRID
                    if d == 1 or ep.n_samples // d >= 200]
        else:
            grid = [_positive_int('decimation', self.decimation)]
        n_markov = None if self.n_markov is None else _positive_int('n_markov', self.n_markov)
        if self.observer_order is not None:
            _positive_int('observer_order', self.observer_order)
        if n_markov is not None:
            # Before any work: at the finest decimation tried (the most samples).
            _check_horizon(n_markov, ep, min(grid))
        ridge = self.okid_ridge
        sel = None
        tried: list[dict[str, Any]] = []
        prepared: dict[int, tuple[Array, Array, Array, Array, Array | None,
                                  Array | None]] = {}
        if selecting:
            rows: list[dict[str, Any]] = []
            per_d: dict[int, dict[str, Any]] = {}
            for d in grid:
                try:
                    if n_markov is not None:
                        _check_horizon(n_markov, ep, d)
                    prepared[d] = self._prepare(ep, y_ref, d)
                    Us, Ys = prepared[d][:2]
                    nm_d = n_markov
                    res = era_select.select_okid(
                        Us, Ys, holdout=float(self.holdout),
                        observer_orders=None if self.observer_order is None else (
                            int(self.observer_order),),
                        rhos=era_select.RIDGE_GRID if ridge is None else (float(ridge),),
                        n_markov=nm_d, r_values=None if self.r is None else (int(self.r),),
                        refit=bool(self.refit), tie_tol=float(self.tie_tol),
                        criterion=str(self.criterion))
                except (ConfigError, DimensionError) as err:
                    if not auto_d:
                        raise
                    tried.append({'decimation': d, 'tail_error': None, 'error': str(err)})
                    continue
                per_d[d] = res
                rows.extend({**row, 'decimation': d} for row in res['rows'])
                tried.append({'decimation': d, 'tail_error': res['tail_error']})
            if not per_d:
                raise DimensionError(
                    f'ERA/OKID found no usable setting for episode {ep.name!r} '
                    f'({ep.n_samples} samples): {tried[0]["error"] if tried else ""}')
            best = era_select.choose(rows, float(self.tie_tol))
            d = int(best['decimation'])
            sel = dict(per_d[d])
            sel.update({'observer_order': int(best['observer_order']),
                        'ridge': float(best['ridge']), 'r': int(best['r']),
                        'tail_error': float(best['tail_error'])})
            sel['table'] = [{**row, 'decimation': dd} for dd, res in per_d.items()
                            for row in res['table']]
            del sel['rows']
            lo, ridge = sel['observer_order'], sel['ridge']
            intercept = bool(best.get('intercept', False))
            sel['intercept'] = intercept
            r_sel: int | None = sel['r'] if self.r is None else int(self.r)
        else:
            d = grid[0]
            r_sel = self.r
            intercept = False
        Us, Ys, s_u, s_y, P, Pu = (prepared[d] if d in prepared
                                   else self._prepare(ep, y_ref, d))
        p_id = Ys.shape[0]
        m_id = Us.shape[0]
        K = Us.shape[1]
        nm = era_select.default_n_markov(K) if n_markov is None else n_markov
        if sel is None:
            if self.observer_order is None:
                # Keep at least 2 equations per unknown: near-square regressions fit the
                # noise and give unstable Markov sequences.
                lo = min(int(self.max_observer_order), (K // 2 - m_id) // (m_id + p_id))
                if lo < 1:
                    raise DimensionError(
                        f'episode {ep.name!r} has {K} samples after decimation {d}: too few '
                        f'for OKID with m={m}, p={p_id} (needs at least {2 * (2 * m + p_id)}). '
                        'Use less decimation or a longer episode.')
            else:
                lo = int(self.observer_order)
        markov, info = okid_markov(Us, Ys, observer_order=lo, n_markov=nm,
                                   rcond=self.okid_rcond, ridge=ridge, intercept=intercept)
        factors: dict[str, Array] = {}
        A, Bs, Cs, Ds, hsv = era(markov, r_sel, n_block_rows=self.n_block_rows,
                                 n_block_cols=self.n_block_cols, tol=self.hsv_tol,
                                 _factors=factors)
        refitted = stabilized = False
        if self.refit:
            A, Cs, Ds, refitted, stabilized = era_select.stabilize_refit(A, Bs, Cs, Ds, Us, Ys)
        if sel is not None and not refitted and np.max(np.abs(np.linalg.eigvals(A))) >= 1:
            # The refit on the whole episode can move a lightly damped pole out of the unit
            # circle: keep the model validated on the held-out tail (fitted on the head).
            cut = int(sel['cut'])
            markov, info = okid_markov(Us[:, :cut], Ys[:, :cut], observer_order=lo,
                                       n_markov=nm, ridge=ridge, intercept=intercept)
            A, Bs, Cs, Ds, hsv = era(markov, r_sel, n_block_rows=self.n_block_rows,
                                     n_block_cols=self.n_block_cols, tol=self.hsv_tol,
                                     _factors=factors)
            sel['refit'] = 'head (the whole-episode refit was unstable)'
        elif sel is not None:
            sel['refit'] = 'whole episode'
        self._train = (Us, Ys)
        self._factors = factors
        if P is not None:
            Cs, Ds = P @ Cs, P @ Ds
        if Pu is not None:
            Bs, Ds = Bs @ Pu.T, Ds @ Pu.T
        self.output_basis_ = P
        self.input_basis_ = Pu
        B = Bs / s_u[None, :]
        C = s_y[:, None] * Cs
        D = s_y[:, None] * Ds / s_u[None, :]
        r = A.shape[0]
        dt = d * ep.dt
        self.dt_fit_ = dt
        resampled = era_select.to_data_rate(A, B, d) if d > 1 else None
        if resampled is not None:
            A, B = resampled
            dt = ep.dt
        self.resampled_ = resampled is not None
        ev = np.linalg.eigvals(A)
        self.markov_ = markov
        self.hankel_singular_values_ = hsv
        self.observer_order_ = lo
        self.okid_ridge_ = ridge
        self.selection_ = sel
        self.decimation_ = d
        self.okid_residual_ = info['residual']
        self.y_ref_ = y_ref
        self.input_scale_ = s_u
        self.output_scale_ = s_y
        self.fit_time_ = time.perf_counter() - t0
        meta = dict(metadata or {})
        meta.setdefault('envelope', training_envelope([ep], y_ref))
        meta.update({
            'learner': 'ERAOKID', 'r': r, 'episode': ep.name,
            'decimation': d, 'dt_data': ep.dt, 'dt_fit': d * ep.dt, 'dt_model': dt,
            'resampled_to_data_rate': self.resampled_, 'n_markov': nm,
            'okid_ridge': ridge, 'okid_intercept': intercept, 'selection': self.selection,
            'selection_table': None if sel is None else _finite_rows(sel['table']),
            'selection_tail_error': None if sel is None else sel['tail_error'],
            'selection_refit': None if sel is None else sel.get('refit'),
            'selection_tie_tol': None if sel is None else float(self.tie_tol),
            'selection_criterion': None if sel is None else sel.get('criterion'),
            'selection_folds': None if sel is None else sel.get('folds'),
            'output_refit': bool(refitted), 'stabilized': bool(stabilized),
            'observer_order': lo, 'okid_residual': info['residual'],
            'okid_rank': info['rank'], 'okid_unknowns': info['n_unknowns'],
            'n_block_rows': self.n_block_rows, 'n_block_cols': self.n_block_cols,
            'hsv_tol': self.hsv_tol, 'output_rank': None if P is None else int(P.shape[1]),
            'input_rank': m if Pu is None else int(Pu.shape[1]),
            'okid_rcond': self.okid_rcond,
            'hankel_singular_values': hsv[:200].tolist(),
            'input_scale': s_u.tolist(), 'output_scale': s_y.tolist(),
            'eigenvalues_real': ev.real.tolist(), 'eigenvalues_imag': ev.imag.tolist(),
            'stability_margin': float(1.0 - np.max(np.abs(ev))),
            'fit_time_s': self.fit_time_,
        })
        if auto_d:
            meta['decimation_search'] = tried
        self.model_ = DiscreteModel(A, B, C, D, dt=dt, method='era', y_ref=y_ref,
                                    input_names=input_names, output_names=output_names,
                                    input_units=input_units, output_units=output_units,
                                    metadata=meta)
        return self

    def _prepare(self, ep: Episode, y_ref: Array, d: int
                 ) -> tuple[Array, Array, Array, Array, Array | None, Array | None]:
        """Decimated, scaled, compressed data: ``Us, Ys, s_u, s_y, P, P_u``."""
        m = ep.U.shape[0]
        Ud, Yd = decimate(ep.U, ep.Y - y_ref[:, None], d)
        if Ud.shape[1] < 2 * (2 * m + 1):
            raise DimensionError(
                f'episode {ep.name!r} has {Ud.shape[1]} samples after decimation {d}: too few '
                f'for OKID with m={m} inputs. Use less decimation or a longer episode.')
        s_u = channel_scale(Ud)
        s_y = channel_scale(Yd)
        s_y = np.maximum(s_y, float(self.output_scale_floor) * float(np.max(s_y)))
        Us, Ys = Ud / s_u[:, None], Yd / s_y[:, None]
        Ys, P = era_select.compress_outputs(Ys, self.output_rank)
        Us, Pu = era_select.compress_inputs(Us, self.input_rank)
        return Us, Ys, s_u, s_y, P, Pu

    def markov_parameters(self) -> Array:
        """OKID Markov parameters in data units, shape (n_markov + 1, p, m).

        ``markov[0] = D``, ``markov[k]`` the response of the outputs ``k`` model steps after a
        unit input pulse (lifted from the output components, scales undone).
        """
        if not hasattr(self, 'markov_'):
            raise NotFittedError('this ERAOKID is not fitted yet; call fit(episode) first.')
        mk = self.markov_ if self.output_basis_ is None else self.output_basis_ @ self.markov_
        Pu = getattr(self, 'input_basis_', None)
        if Pu is not None:
            mk = mk @ Pu.T
        return np.asarray(self.output_scale_[:, None] * mk / self.input_scale_[None, :])

    def model_for(self, r: int) -> DiscreteModel:
        """The ROM of order ``r`` from the stored Markov parameters (no new OKID solve)."""
        if not hasattr(self, 'markov_'):
            raise NotFittedError('this ERAOKID is not fitted yet; call fit(episode) first.')
        f = getattr(self, '_factors', None)
        if f and 1 <= int(r) <= f['M'].shape[0]:
            A, Bs, Cs, Ds = _era_from_factors(f, int(r))
        else:
            A, Bs, Cs, Ds, _ = era(self.markov_, int(r), n_block_rows=self.n_block_rows,
                                   n_block_cols=self.n_block_cols, tol=self.hsv_tol)
        if self.refit:
            A, Cs, Ds = era_select.stabilize_refit(A, Bs, Cs, Ds, *self._train)[:3]
        if self.output_basis_ is not None:
            Cs, Ds = self.output_basis_ @ Cs, self.output_basis_ @ Ds
        if self.input_basis_ is not None:
            Bs, Ds = Bs @ self.input_basis_.T, Ds @ self.input_basis_.T
        s_u, s_y = self.input_scale_, self.output_scale_
        old = self.model_
        Bp = Bs / s_u[None, :]
        if getattr(self, 'resampled_', False):
            d = int(round(self.dt_fit_ / old.dt))
            res = era_select.to_data_rate(A, Bp, d)
            if res is None:
                raise ConfigError(f'the order-{r} realization has no real {d}-th root; fit '
                                  'with decimation=1.')
            A, Bp = res
        ev = np.linalg.eigvals(A)
        meta = dict(old.metadata)
        meta.update({'r': int(r), 'eigenvalues_real': ev.real.tolist(),
                     'eigenvalues_imag': ev.imag.tolist(),
                     'stability_margin': float(1.0 - np.max(np.abs(ev)))})
        return DiscreteModel(A, Bp, s_y[:, None] * Cs,
                             s_y[:, None] * Ds / s_u[None, :], dt=old.dt, method='era',
                             y_ref=self.y_ref_, input_names=old.input_names,
                             output_names=old.output_names, input_units=old.input_units,
                             output_units=old.output_units, metadata=meta)


def _positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ConfigError(f'{name} must be an integer >= 1; got {value!r}.')
    return int(value)


def _check_horizon(n_markov: int, ep: Episode, d: int) -> None:
    """Refuse a Markov horizon longer than the episode at decimation ``d`` (before any work).

    The ``n_markov`` Markov parameters are the impulse response over ``n_markov`` model
    steps; a record of ``K`` samples constrains it over at most ``K - 1`` steps, and the
    Hankel matrices grow with ``n_markov²`` (100 000 of them would need over 100 GiB).
    """
    K = ep.n_samples // d
    if n_markov > K - 1:
        raise ConfigError(
            f'n_markov={n_markov} exceeds what episode {ep.name!r} supports: it has {K} '
            f'samples at decimation {d}, so the Markov horizon can be at most {max(K - 1, 0)} '
            f'(default {era_select.default_n_markov(K)}). Give a smaller n_markov, a longer '
            'episode, or less decimation.')


def _finite_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """JSON-safe copy of a selection table (``inf``/``nan`` become ``None``)."""
    return [{k: (None if isinstance(v, float) and not np.isfinite(v) else v)
             for k, v in row.items()} for row in rows]


def _one_episode(episode: Episode | Sequence[Episode]) -> Episode:
    """The one episode ERA/OKID fits (one continuous record)."""
    eps = [episode] if isinstance(episode, Episode) else list(episode)
    if len(eps) != 1:
        raise DimensionError(
            f'ERA/OKID fits one episode at a time (one continuous record); got '
            f'{len(eps)} episodes. Fit one model per episode, e.g. '
            '--era-episode ep2 on the command line.')
    return eps[0]
