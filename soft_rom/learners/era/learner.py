"""ERA/OKID: the learner of linear ROMs from input/output data alone (paper section 2.4).

:class:`ERAOKID` identifies the Markov parameters by OKID
(:mod:`soft_rom.learners.era.okid`) and realizes them by ERA
(:mod:`soft_rom.learners.era.realization`): :math:`x_{k+1} = A x_k + B u_k`,
:math:`y_k = C x_k + D u_k + y_{ref}`.

The horizon problem and its knobs. With ``p = 40`` outputs the observer regression has
``m + l (m + p)`` unknowns per output row, so ``K`` samples allow an observer of order
``l < K / (m + p + 1)`` (a few dozen samples at 1 kHz), while the slow modes of a soft body
last seconds. The knobs: ``observer_order`` (``l``) and the ridge weight of the (well-posed)
OKID solve; ``n_markov``, how many Markov parameters feed the Hankel matrices (their span
``n_markov · dt_model`` should cover the slow modes); ``decimation``, the fit at
``decimation · dt_data`` (outputs sampled every ``decimation`` samples, inputs averaged over
each block), the model then resampled to the data step when a real root exists. By default
they are chosen by blocked cross-validation (:mod:`soft_rom.learners.era.select`), for every
order asked for at once (``orders``), so that one set of Markov parameters at one step serves
them all: a decimation whose realization of an asked order cannot be resampled to the data
step is set aside and the next best chosen.

Unit invariance: inputs and outputs are divided by their per-channel RMS before OKID/ERA
and the realization is scaled back (``B = B_s diag(1/s_u)``, ``C = diag(s_y) C_s``,
``D = diag(s_y) D_s diag(1/s_u)``); the Hankel singular values are those of the scaled data.
"""

from __future__ import annotations

from collections.abc import Sequence
import time
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import as_signal, check_finite, Episode, nonuniform_message
from soft_rom.envelope import training_envelope
from soft_rom.errors import ConfigError, DimensionError, NotFittedError
from soft_rom.learners.era import select as era_select
from soft_rom.learners.era.okid import (
    default_n_markov,
    okid_markov,
)
from soft_rom.learners.era.realization import era, era_from_factors, stabilize_refit, to_data_rate
from soft_rom.learners.era.steps import ERASteps, Prepared
from soft_rom.models import DiscreteModel
from soft_rom.reduce import ReducedData

__all__ = ['ERAOKID']

Array = NDArray[np.float64]


class ERAOKID(ERASteps):
    """ERA/OKID learner: a discrete ROM from the inputs and outputs of one episode.

    Defaults (``selection='holdout'``): well-posed ridge OKID (module
    :mod:`soft_rom.learners.era.select`), with the decimation, the observer order ``l``, the
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
        :data:`~soft_rom.learners.era.select.DECIMATION_GRID`, selected with the other
        settings by the cross-validated error. A model fitted at ``d > 1`` is resampled to the
        data step (:func:`~soft_rom.learners.era.select.to_data_rate`: exact ``d``-th root), so it
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
        (:func:`~soft_rom.learners.era.select.compress_inputs`; ``'auto'``, default: singular
        values of the scaled inputs above ``1e-8`` of the largest), so that the responses to
        input combinations never applied (antagonistic pairs) are zero instead of
        undetermined; ``None``: all ``m`` inputs (the presets).
    okid_rcond : float, optional
        Relative singular-value cut-off of the plain least-squares OKID solve (only when
        ``okid_ridge`` is ``None`` and ``selection='none'``).
    okid_ridge : float, optional
        Relative ridge weight ``ρ`` of OKID; ``None``: selected from
        :data:`~soft_rom.learners.era.select.RIDGE_GRID` (``selection='holdout'``) or plain
        least squares (``selection='none'``).
    selection : {'holdout', 'none'}
        Data-driven settings (default) or the given ones as they are.
    holdout : float
        Fraction of the episode held out in each fold of the selection (``1 / holdout``
        blocks).
    criterion : {'blocked', 'tail'}
        Blocked cross-validation (default) or the former single held-out tail
        (:func:`~soft_rom.learners.era.select.cv_folds`).
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

    The eel study's hand-tuned settings are :data:`soft_rom.study.presets.ERA_EEL_OPTIONS`
    (``ERAOKID(**ERA_EEL_OPTIONS)``).

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

    #: What the learner needs from a reducer: inputs and outputs only.
    reduction: ClassVar[str] = 'none'
    #: The method name of its models and of ``soft-rom fit --method``.
    method: ClassVar[str] = 'era'

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
                 blas_threads: int | None = 1, orders: Sequence[int] | None = None,
                 episode: str | None = None) -> None:
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
        self.orders = orders
        self.episode = episode

    def coordinates_needed(self, r_max: int | None, n_inputs: int) -> int | None:
        """No coordinates: ERA/OKID needs inputs and outputs only."""
        return None

    def fit(self, episode: ReducedData | Episode | Sequence[Episode],
            y_ref: ArrayLike | None = None, *,
            input_names: Sequence[str] | None = None,
            output_names: Sequence[str] | None = None,
            input_units: Sequence[str] | None = None,
            output_units: Sequence[str] | None = None,
            metadata: dict[str, Any] | None = None) -> ERAOKID:
        """Identify the ROM from one episode (see the class for the settings).

        Parameters
        ----------
        episode : Episode or ReducedData
            Uniformly sampled ``U (m, k)``, ``Y (p, k)``; ``Q`` is ignored. A list with one
            episode is accepted; several are refused (OKID needs one continuous record).
            Reduced data: the episode named :attr:`episode` (default the first), with the
            data's ``y_ref``, names and metadata.
        y_ref : ndarray, shape (p,), optional
            Output reference; default the first output sample.

        Returns
        -------
        self
        """
        names = dict(input_names=input_names, output_names=output_names,
                     input_units=input_units, output_units=output_units)
        if isinstance(episode, ReducedData):
            data = episode
            if self.episode is not None and self.episode not in data.names:
                raise ConfigError(f'--era-episode {self.episode!r} is not among the selected '
                                  f'episodes {list(data.names)}.')
            episode = data.episode(self.episode if self.episode is not None else 0)
            y_ref = data.y_ref
            names = {**names, **data.model_names()}
            metadata = {**data.metadata, **(metadata or {})}
            metadata['training'] = {**metadata.get('training', {}), 'episodes': [episode.name]}
        with era_select.blas_threads(self.blas_threads):
            return self._fit(episode, y_ref, names, metadata)

    def _fit(self, episode: Episode | Sequence[Episode], y_ref: ArrayLike | None,
             names: dict[str, Any], metadata: dict[str, Any] | None) -> ERAOKID:
        t0 = time.perf_counter()
        ep = _one_episode(episode)
        if not ep.is_uniform():
            raise DimensionError(nonuniform_message(ep.name, ep.t))
        check_finite(f'U of episode {ep.name!r}', ep.U)
        check_finite(f'Y of episode {ep.name!r}', ep.Y)
        p = ep.Y.shape[0]
        y_ref = ep.Y[:, 0].copy() if y_ref is None else as_signal(
            'y_ref', np.reshape(y_ref, (-1, 1)), rows=p)[:, 0]
        grid, n_markov = self._plan(ep)
        prepared: dict[int, Prepared] = {}
        search = self._search(ep, y_ref, grid, n_markov, prepared)
        excluded: set[int] = set()
        while True:
            sel, d, lo, ridge, intercept, r_sel = self._settings(search, grid, excluded)
            fit = self._realize(ep, y_ref, d, sel, lo, ridge, intercept, r_sel, n_markov,
                                prepared)
            unserved = self._unserved(d)
            if not unserved or self.decimation != 'auto' or d == 1 or sel is None:
                break
            excluded.add(d)         # an order this decimation cannot serve: choose another
            search['excluded'].append({'decimation': d, 'orders_without_real_root': unserved})
        self._finish(ep, y_ref, fit, sel, search, t0, names, metadata)
        return self

    def _realize(self, ep: Episode, y_ref: Array, d: int, sel: dict[str, Any] | None,
                 lo: int | None, ridge: float | None, intercept: bool, r_sel: int | None,
                 n_markov: int | None, prepared: dict[int, Prepared]) -> dict[str, Any]:
        """OKID and ERA at decimation ``d`` with the settings; stabilized and refitted."""
        Us, Ys, s_u, s_y, P, Pu = (prepared[d] if d in prepared
                                   else self._prepare(ep, y_ref, d))
        p_id, m_id, K = Ys.shape[0], Us.shape[0], Us.shape[1]
        nm = default_n_markov(K) if n_markov is None else n_markov
        if lo is None:
            # Keep at least 2 equations per unknown: near-square regressions fit the noise
            # and give unstable Markov sequences.
            lo = min(int(self.max_observer_order), (K // 2 - m_id) // (m_id + p_id))
            if lo < 1:
                raise DimensionError(
                    f'episode {ep.name!r} has {K} samples after decimation {d}: too few for '
                    f'OKID with m={ep.U.shape[0]}, p={p_id} (needs at least '
                    f'{2 * (2 * ep.U.shape[0] + p_id)}). Use less decimation (--decimation 1) '
                    'or a longer episode.')
        lo = int(lo)
        markov, info = okid_markov(Us, Ys, observer_order=lo, n_markov=nm,
                                   rcond=self.okid_rcond, ridge=ridge, intercept=intercept)
        factors: dict[str, Array] = {}
        A, Bs, Cs, Ds, hsv = era(markov, r_sel, n_block_rows=self.n_block_rows,
                                 n_block_cols=self.n_block_cols, tol=self.hsv_tol,
                                 _factors=factors)
        refitted = stabilized = False
        if self.refit:
            A, Cs, Ds, refitted, stabilized = stabilize_refit(A, Bs, Cs, Ds, Us, Ys)
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
        self.markov_ = markov
        self.decimation_ = d
        self.dt_fit_ = d * ep.dt
        self.output_basis_, self.input_basis_ = P, Pu
        self.input_scale_, self.output_scale_ = s_u, s_y
        return {'A': A, 'Bs': Bs, 'Cs': Cs, 'Ds': Ds, 'hsv': hsv, 'lo': lo, 'ridge': ridge,
                'intercept': intercept, 'info': info, 'nm': nm, 'refitted': refitted,
                'stabilized': stabilized}

    def _unserved(self, d: int) -> list[int]:
        """Orders asked for whose realization at decimation ``d`` has no real ``d``-th root."""
        if d == 1:
            return []
        return [r for r in self._orders() if self._realization(r)[2] is None]

    def _finish(self, ep: Episode, y_ref: Array, fit: dict[str, Any],
                sel: dict[str, Any] | None, search: dict[str, Any], t0: float,
                names: dict[str, Any], metadata: dict[str, Any] | None) -> None:
        """Lift, unscale and resample the realization; the model and its metadata."""
        A, Bs, Cs, Ds, P, Pu = (fit['A'], fit['Bs'], fit['Cs'], fit['Ds'], self.output_basis_,
                                self.input_basis_)
        d, m = self.decimation_, ep.U.shape[0]
        if P is not None:
            Cs, Ds = P @ Cs, P @ Ds
        if Pu is not None:
            Bs, Ds = Bs @ Pu.T, Ds @ Pu.T
        B = Bs / self.input_scale_[None, :]
        C = self.output_scale_[:, None] * Cs
        D = self.output_scale_[:, None] * Ds / self.input_scale_[None, :]
        dt = d * ep.dt
        resampled = to_data_rate(A, B, d) if d > 1 else None
        if resampled is not None:
            A, B = resampled
            dt = ep.dt
        self.resampled_ = resampled is not None
        self.hankel_singular_values_ = fit['hsv']
        self.observer_order_ = fit['lo']
        self.okid_ridge_ = fit['ridge']
        self.selection_ = sel
        self.okid_residual_ = fit['info']['residual']
        self.y_ref_ = y_ref
        self.dt_data_ = ep.dt
        self.fit_time_ = time.perf_counter() - t0
        meta = dict(metadata or {})
        meta.setdefault('envelope', training_envelope([ep], y_ref, ep.dt))
        meta.update(self._fit_metadata(ep, fit, sel, A, dt, m))
        if self.decimation == 'auto':
            meta['decimation_search'] = search['tried']
            if search['excluded']:
                meta['decimation_excluded'] = search['excluded']
        self.model_ = DiscreteModel(A, B, C, D, dt=dt, method='era', y_ref=y_ref,
                                    metadata=meta,
                                    **{k: v for k, v in names.items() if v is not None})

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

    def _realization(self, r: int) -> tuple[Array, Array, tuple[Array, Array] | None,
                                            Array, Array]:
        """``(A, B)`` of order ``r`` at the fit step, at the data step (or None), ``C, D``."""
        f = getattr(self, '_factors', None)
        if f and 1 <= int(r) <= f['M'].shape[0]:
            A, Bs, Cs, Ds = era_from_factors(f, int(r))
        else:
            A, Bs, Cs, Ds, _ = era(self.markov_, int(r), n_block_rows=self.n_block_rows,
                                   n_block_cols=self.n_block_cols, tol=self.hsv_tol)
        if self.refit:
            A, Cs, Ds = stabilize_refit(A, Bs, Cs, Ds, *self._train)[:3]
        if self.output_basis_ is not None:
            Cs, Ds = self.output_basis_ @ Cs, self.output_basis_ @ Ds
        if self.input_basis_ is not None:
            Bs, Ds = Bs @ self.input_basis_.T, Ds @ self.input_basis_.T
        s_u, s_y = self.input_scale_, self.output_scale_
        Bp = Bs / s_u[None, :]
        d = self.decimation_
        at_data = to_data_rate(A, Bp, d) if d > 1 else (A, Bp)
        return A, Bp, at_data, s_y[:, None] * Cs, s_y[:, None] * Ds / s_u[None, :]

    def model_for(self, r: int) -> DiscreteModel:
        """The ROM of order ``r`` from the stored Markov parameters (no new OKID solve).

        At the data step when the fit's decimation allows it (a real ``d``-th root),
        else at the fit step ``d · dt`` (``metadata['dt_model']`` says which).
        """
        if not hasattr(self, 'markov_'):
            raise NotFittedError('this ERAOKID is not fitted yet; call fit(episode) first.')
        A, Bp, at_data, C, D = self._realization(int(r))
        old = self.model_
        dt = self.dt_data_
        if at_data is None:
            dt = self.dt_fit_
        else:
            A, Bp = at_data
        ev = np.linalg.eigvals(A)
        meta = dict(old.metadata)
        meta.update({'r': int(r), 'eigenvalues_real': ev.real.tolist(),
                     'eigenvalues_imag': ev.imag.tolist(), 'dt_model': dt,
                     'resampled_to_data_rate': at_data is not None and self.decimation_ > 1,
                     'stability_margin': float(1.0 - np.max(np.abs(ev)))})
        return DiscreteModel(A, Bp, C, D, dt=dt, method='era', y_ref=self.y_ref_,
                             input_names=old.input_names, output_names=old.output_names,
                             input_units=old.input_units, output_units=old.output_units,
                             metadata=meta)


def _one_episode(episode: Episode | Sequence[Episode]) -> Episode:
    """The one episode ERA/OKID fits (one continuous record)."""
    eps = [episode] if isinstance(episode, Episode) else list(episode)
    if len(eps) != 1:
        raise DimensionError(
            f'ERA/OKID fits one episode at a time (one continuous record); got '
            f'{len(eps)} episodes. Fit one model per episode, e.g. '
            '--era-episode ep2 on the command line.')
    return eps[0]
