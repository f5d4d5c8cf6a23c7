"""Data-driven ERA/OKID settings: blocked cross-validation over the episode.

For every block of the episode and every candidate ``(d, l, ρ, intercept)``, the ridge OKID
(:func:`~soft_rom.learners.era.okid.ridge_markov`) is fitted on the observer equations
outside the block (and outside the ``l`` samples after it, whose regressors are the block's
outputs); its ERA model (:func:`~soft_rom.learners.era.realization.era_truncated`) is, for
every order of :data:`R_GRID`, stabilized, simulated from rest over the whole episode, its
``C, D`` refitted on the samples outside the block, and its output error on the block summed;
the score is the pooled relative error over the blocks (:func:`select_okid`). Errors within
:data:`TIE_TOL` of the best are tied and the tie is broken by a fixed preference
(:func:`choose`), so that a perturbation of the data far smaller than the band cannot change
the settings. The reasons and the measurements behind these choices are in
``docs/methods_variants.md`` (ERA/OKID).
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import ConfigError
from soft_rom.learners.era.okid import default_n_markov, RIDGE_FLOOR, ridge_markov
from soft_rom.learners.era.realization import (
    era_truncated,
    first_order_responses,
    fit_output_map,
    modal_inputs,
    real_modal_states,
    simulate_states,
)

__all__ = ['DECIMATION_GRID', 'INTERCEPTS', 'OBSERVER_GRID', 'OUTPUT_SCALE_FLOOR', 'R_GRID',
           'R_MAX', 'RIDGE_GRID', 'TIE_TOL', 'blas_threads', 'choose', 'cv_folds',
           'fold_errors', 'select_okid']

Array = NDArray[np.float64]

#: Candidate relative ridge weights ``ρ``.
RIDGE_GRID = (1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-4)


#: Output channels are scaled by their RMS, but never by less than this fraction of the
#: largest channel RMS (nearly static channels would otherwise amplify their perturbations).
OUTPUT_SCALE_FLOOR = 0.1


#: Orders tried by the selection (up to ``r_max``).
R_GRID = (2, 4, 6, 8, 10, 12, 16, 20, 24, 28, 32, 40, 48, 56)


#: OKID regressions tried without / with an intercept (:func:`ridge_markov`).
INTERCEPTS = (False, True)


#: Candidate observer orders (those that fit the data are tried).
OBSERVER_GRID = (8, 16, 32, 64)


#: Largest order tried by the selection.
R_MAX = 40


#: Relative band of held-out errors treated as tied (:func:`choose`).
TIE_TOL = 0.03


#: Decimation factors tried by ``ERAOKID(decimation='auto')``.
DECIMATION_GRID = (1, 5)


def choose(rows: list[dict[str, Any]], tie_tol: float = TIE_TOL) -> dict[str, Any]:
    """The selected candidate: the preferred one among those tied with the best.

    Candidates whose held-out error is within ``tie_tol`` (relative) of the best are tied;
    among them the preference is fixed: the largest ridge weight, then the regression with an
    intercept, then the smallest order ``r``, then the smallest observer order, then the
    smallest decimation. A perturbation of
    the data that moves the errors by much less than ``tie_tol`` cannot change the choice
    unless an error sits within that perturbation of the band's edge.
    """
    ok = [row for row in rows if np.isfinite(row['tail_error'])]
    if not ok:
        raise ConfigError('no OKID setting gave a stable ERA realization on these data; give '
                          '--observer-order, --okid-ridge and --r by hand.')
    best = min(row['tail_error'] for row in ok)
    tied = [row for row in ok if row['tail_error'] <= best * (1.0 + tie_tol)]
    return min(tied, key=lambda row: (-row['ridge'], not row.get('intercept', False), row['r'],
                                      row['observer_order'], row.get('decimation', 1)))


def cv_folds(K: int, lo: int, holdout: float, criterion: str = 'blocked'
             ) -> list[tuple[NDArray[np.bool_], NDArray[np.bool_]]]:
    """Validation folds ``[(rows, test), ...]``: boolean masks of shape (K,).

    ``rows``: the samples whose observer equations are fitted; ``test``: the samples scored
    (the output map ``C, D`` is refitted on the others). ``'tail'``: one fold, the last
    ``holdout`` of the episode. ``'blocked'``: ``n = round(1 / holdout)`` contiguous blocks,
    each left out once; the ``l`` equations after a block are dropped as well, since their
    regressors are the block's outputs (hv-block cross-validation).
    """
    if criterion not in ('blocked', 'tail'):
        raise ConfigError(f"criterion must be 'blocked' or 'tail'; got {criterion!r}.")
    idx = np.arange(K)
    if criterion == 'tail':
        cut = int(round(K * (1.0 - holdout)))
        return [(idx < cut, idx >= cut)]
    n = max(int(round(1.0 / holdout)), 2)
    edges = np.round(np.linspace(0, K, n + 1)).astype(int)
    return [(~((idx >= a) & (idx < b + lo)), (idx >= a) & (idx < b))
            for a, b in zip(edges[:-1], edges[1:])]


def select_okid(Us: Array, Ys: Array, *, holdout: float = 0.2,
                observer_orders: tuple[int, ...] | None = None,
                rhos: tuple[float, ...] = RIDGE_GRID, n_markov: int | None = None,
                r_max: int = R_MAX, r_values: tuple[int, ...] | None = None,
                refit: bool = True, tie_tol: float = TIE_TOL,
                intercepts: tuple[bool, ...] | None = None,
                criterion: str = 'blocked') -> dict[str, Any]:
    """Choose ``(l, ρ, r)`` by the held-out error of the ERA/OKID model.

    Parameters
    ----------
    Us : ndarray, shape (m, K)
        Scaled inputs.
    Ys : ndarray, shape (p, K)
        Scaled output deviations (or their principal components).
    holdout : float
        Fraction of the episode held out in each fold (:func:`cv_folds`).
    observer_orders : tuple of int, optional
        Candidates (default :data:`OBSERVER_GRID` and the largest order with two equations
        per unknown in a fold, each if it fits): at high sample rates the observer must
        span many samples to see slow modes. Given ones that do not fit are skipped; if
        none fits, :class:`~soft_rom.errors.ConfigError`.
    rhos : tuple of float
        Candidate ridge weights (each at least :data:`RIDGE_FLOOR`).
    n_markov : int, optional
        Markov horizon (default :func:`default_n_markov` of the samples of a fold).
    r_max : int
        Largest order tried (when ``r_values`` is not given: the orders of :data:`R_GRID`
        up to ``r_max``).
    r_values : tuple of int, optional
        Orders tried.
    refit : bool
        Score the stabilized realization with ``C, D`` refitted on the fold's other samples
        (:func:`stabilize`, :func:`fit_output_map`); ``False``: the ERA realization as it
        is, unstable ones rejected.
    tie_tol : float
        Relative band of tied errors (:func:`choose`).
    intercepts : tuple of bool
        OKID regressions tried without / with an intercept (:func:`ridge_markov`).
    criterion : {'blocked', 'tail'}
        Blocked cross-validation (default) or the last ``holdout`` only (:func:`cv_folds`).

    Returns
    -------
    dict
        ``observer_order``, ``ridge``, ``intercept``, ``r``, ``tail_error`` (held-out
        relative error of the chosen candidate, pooled over the folds), ``rows`` (every
        candidate tried), ``table`` (best ``r`` of every ``(l, ρ, intercept)``), ``cut``
        (samples before the last fold), ``n_markov``, ``folds``.
    """
    if not 0.0 < holdout < 0.9:
        raise ConfigError(f'holdout must be in (0, 0.9); got {holdout!r}.')
    K = Us.shape[1]
    cut = int(round(K * (1.0 - holdout)))
    cands = _observer_candidates(Us.shape[0], Ys.shape[0], K, cut, observer_orders)
    nm = default_n_markov(cut) if n_markov is None else int(n_markov)
    rhos = tuple(max(float(x), RIDGE_FLOOR) for x in rhos)
    rr = max(r_values) if r_values else r_max
    search = _Search(Us, Ys, nm, rhos, [r for r in (r_values or R_GRID) if r <= rr], rr,
                     refit)
    pairs = [(lo, icpt) for lo in cands
             for icpt in (INTERCEPTS if intercepts is None else intercepts)]
    folds = {lo: cv_folds(K, lo, holdout, criterion) for lo in cands}
    search.run(pairs, folds, tie_tol)
    # The scored samples do not depend on l: one reference for every candidate.
    ref = float(sum(np.sum(Ys[:, test] ** 2) for _, test in cv_folds(K, 1, holdout,
                                                                      criterion)))
    rows, table = search.tabulate(pairs, ref)
    best = choose(rows, tie_tol)
    return {'observer_order': int(best['observer_order']), 'ridge': float(best['ridge']),
            'intercept': bool(best['intercept']), 'r': int(best['r']),
            'tail_error': float(best['tail_error']), 'rows': rows,
            'table': table, 'cut': cut, 'n_markov': nm, 'folds': len(folds[cands[0]]),
            'criterion': criterion}


def _observer_candidates(m: int, p: int, K: int, cut: int,
                         given: tuple[int, ...] | None) -> list[int]:
    """Observer orders the folds can fit (two equations per unknown in a fold)."""
    l_max = (cut // 2 - m) // (m + p)
    if l_max < 1 or K - cut < 2:
        raise ConfigError(f'{K} samples are too few to select OKID settings on held-out '
                          f'blocks (m={m}, p={p}); give --observer-order and --okid-ridge '
                          '(or use a longer episode).')
    cands = sorted({lo for lo in (given or OBSERVER_GRID + (l_max,)) if 1 <= lo <= l_max})
    if not cands:       # only orders given by hand can all be out of reach
        raise ConfigError(
            f'--observer-order {", ".join(str(lo) for lo in given or ())} is too large for '
            f'{K} samples: the selection fits each fold on {cut} samples with two equations '
            f'per unknown ({m} inputs, {p} identified outputs), so --observer-order '
            f'<= {l_max}. Give a smaller observer order, a longer episode, or less '
            'decimation.')
    return cands


class _Search:
    """The pooled held-out errors of every candidate, fold by fold, with exact pruning.

    The pooled squared error only grows from fold to fold, so an order (and a ridge weight,
    once all its orders are out) whose partial error already exceeds the band of the best
    complete candidate (``best (1 + tie_tol)``) can be neither chosen nor tied; its remaining
    folds are skipped and its rows carry that lower bound (``complete: False``). Each order is
    scored independently, so the choice is the same as without pruning.
    """

    def __init__(self, Us: Array, Ys: Array, nm: int, rhos: tuple[float, ...],
                 grid_r: list[int], rr: int, refit: bool) -> None:
        self.Us, self.Ys, self.nm, self.rhos, self.grid_r = Us, Ys, nm, rhos, grid_r
        self.rr, self.refit = rr, refit
        self.err: dict[tuple[int, bool], Array] = {}
        self.radius: dict[tuple[int, bool], Array] = {}
        self.alive: dict[tuple[int, bool], NDArray[np.bool_]] = {}

    def run(self, pairs: list[tuple[int, bool]],
            folds: dict[int, list[tuple[NDArray[np.bool_], NDArray[np.bool_]]]],
            tie_tol: float) -> None:
        """Every candidate through its folds, pruned.

        The last block of every candidate first, then the candidates in the order of that
        error, each through its other blocks: good candidates complete early and set the bound.
        """
        shape = (len(self.rhos), len(self.grid_r))
        for c in pairs:
            self.err[c], self.radius[c] = np.zeros(shape), np.zeros(shape)
            self.alive[c] = np.ones(shape, dtype=bool)
        bound = float('inf')
        for c in pairs:
            self._fold(c, folds[c[0]][-1], bound)
        for c in sorted(pairs, key=lambda c: float(np.min(self.err[c]))):
            self.alive[c] &= self.err[c] <= bound
            for fold in folds[c[0]][-2::-1]:
                if not self.alive[c].any():
                    break
                self._fold(c, fold, bound)
            if self.alive[c].any():
                bound = min(bound, float(np.min(self.err[c][self.alive[c]]))
                            * (1.0 + tie_tol) ** 2)

    def _fold(self, c: tuple[int, bool], fold: tuple[NDArray[np.bool_], NDArray[np.bool_]],
              bound: float) -> None:
        lo, icpt = c
        err, radius, alive = self.err[c], self.radius[c], self.alive[c]
        live = np.flatnonzero(alive.any(axis=1))
        fits = ridge_markov(self.Us, self.Ys, lo, self.nm, tuple(self.rhos[i] for i in live),
                            icpt, rows=fold[0])
        for i, (markov, _info) in zip(live, fits):
            try:
                A, B, C, D, _ = era_truncated(markov, self.rr)
                cand_r = [r for j, r in enumerate(self.grid_r)
                          if alive[i, j] and r <= A.shape[0]]
                found = {row['r']: row for row in fold_errors(
                    A, B, C, D, self.Us, self.Ys, fold[1], cand_r, refit=self.refit)}
            except (ConfigError, np.linalg.LinAlgError):
                found = {}
            for j, r in enumerate(self.grid_r):
                if not alive[i, j]:
                    continue
                row = found.get(r)
                err[i, j] += row['sq_error'] if row is not None else float('inf')
                radius[i, j] = max(radius[i, j], row['spectral_radius']
                                   if row is not None else float('inf'))
            alive[i] &= err[i] <= bound

    def tabulate(self, pairs: list[tuple[int, bool]], ref: float
                 ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
        """Every candidate's row, and the best ``r`` of every ``(l, ρ, intercept)``."""
        rows: list[dict[str, Any]] = []
        table: list[dict[str, Any]] = []
        for c in pairs:
            lo, icpt = c
            for i, rho in enumerate(self.rhos):
                base = {'observer_order': lo, 'ridge': rho, 'intercept': icpt}
                found = []
                for j, r in enumerate(self.grid_r):
                    e = float(np.sqrt(self.err[c][i, j] / ref)) if ref > 0 else float('inf')
                    found.append({**base, 'r': r, 'complete': bool(self.alive[c][i, j]),
                                  'tail_error': e if np.isfinite(e) else float('inf'),
                                  'spectral_radius': float(self.radius[c][i, j])})
                rows.extend(found)
                fin = [row for row in found if np.isfinite(row['tail_error'])]
                table.append(min(fin, key=lambda row: row['tail_error']) if fin else
                             {**base, 'r': None, 'tail_error': float('inf')})
        return rows, table


def fold_errors(A_full: Array, B_full: Array, C_full: Array, D: Array, Us: Array,
                Ys: Array, test: NDArray[np.bool_], r_candidates: list[int], *,
                refit: bool = True) -> list[dict[str, Any]]:
    """Squared output error on the samples ``test`` of every order ``r`` (from rest).

    ``A_full, B_full, C_full`` are the balanced realization of the largest candidate order;
    the leading ``r`` states of a balanced ERA realization are the order-``r`` realization,
    simulated from rest over the whole episode. With ``refit`` it is stabilized and ``C, D``
    are refitted on the other samples; otherwise unstable realizations score ``inf``.
    Rows: ``r``, ``sq_error``, ``spectral_radius``.
    """
    rows = []
    fit = ~test
    if refit:
        modal = [modal_inputs(A_full[:r, :r], B_full[:r], Us) for r in r_candidates]
        live = [x for x in modal if x[0] is not None]
        if live:
            Z = first_order_responses(np.concatenate([x[0] for x in live]),
                                      np.concatenate([x[1] for x in live]))
        at = 0
        for r, (ev, _G, rho) in zip(r_candidates, modal):
            if ev is None:
                rows.append({'r': r, 'sq_error': float('inf'), 'spectral_radius': rho})
                continue
            X = real_modal_states(ev, Z[at:at + r])
            at += r
            C, Dr = fit_output_map(X[:, fit], Us[:, fit], Ys[:, fit])
            e = float(np.sum((C @ X[:, test] + Dr @ Us[:, test] - Ys[:, test]) ** 2))
            rows.append({'r': r, 'sq_error': e if np.isfinite(e) else float('inf'),
                         'spectral_radius': rho})
        return rows
    for r in r_candidates:
        A, B, C = A_full[:r, :r], B_full[:r], C_full[:, :r]
        rho = float(np.max(np.abs(np.linalg.eigvals(A))))
        if not rho < 1.0:
            rows.append({'r': r, 'sq_error': float('inf'), 'spectral_radius': rho})
            continue
        X = simulate_states(A, B, Us)
        e = float(np.sum((C @ X[:, test] + D @ Us[:, test] - Ys[:, test]) ** 2))
        rows.append({'r': r, 'sq_error': e if np.isfinite(e) else float('inf'),
                     'spectral_radius': rho})
    return rows


def blas_threads(n: int | None) -> Any:
    """Limit BLAS threads to ``n`` while fitting (threadpoolctl, when installed)."""
    if n is None:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # optional: without it the process's BLAS settings apply
        return contextlib.nullcontext()
    return threadpool_limits(limits=int(n), user_api='blas')
