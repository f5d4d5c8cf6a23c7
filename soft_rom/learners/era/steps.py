"""The steps of an ERA/OKID fit: settings checked, searched, chosen; data prepared.

:class:`ERASteps` holds the steps :class:`~soft_rom.learners.era.learner.ERAOKID` runs in
``fit`` besides OKID and ERA themselves: the plan (decimations to try, horizon checked before
any work), the blocked cross-validation over the decimations
(:func:`~soft_rom.learners.era.select.select_okid`), the choice of the settings, and the
decimated, scaled, compressed data.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.data import Episode
from soft_rom.errors import ConfigError, DimensionError
from soft_rom.learners.dmdc import channel_scale
from soft_rom.learners.era import select as era_select
from soft_rom.learners.era.okid import (
    compress_inputs,
    compress_outputs,
    decimate,
    default_n_markov,
)

__all__ = ['ERASteps', 'Prepared']

Array = NDArray[np.float64]
#: Decimated, scaled, compressed data: ``Us, Ys, s_u, s_y, P, P_u``.
Prepared = tuple[Array, Array, Array, Array, 'Array | None', 'Array | None']


class ERASteps:
    """The settings-related steps of :class:`~soft_rom.learners.era.learner.ERAOKID`."""

    r: int | None
    n_markov: int | None
    observer_order: int | None
    decimation: int | str
    n_block_rows: int | None
    n_block_cols: int | None
    hsv_tol: float
    output_rank: int | str | None
    okid_rcond: float | None
    okid_ridge: float | None
    selection: str
    holdout: float
    refit: bool
    tie_tol: float
    output_scale_floor: float
    input_rank: int | str | None
    criterion: str
    orders: Sequence[int] | None
    output_basis_: Array | None
    input_basis_: Array | None
    input_scale_: Array
    output_scale_: Array
    resampled_: bool
    decimation_: int
    fit_time_: float

    def _orders(self) -> list[int]:
        """The orders asked for: :attr:`orders`, and :attr:`r` (those given)."""
        out = [] if self.orders is None else [int(r) for r in self.orders]
        if self.r is not None and int(self.r) not in out:
            out.insert(0, int(self.r))
        return out

    def _plan(self, ep: Episode) -> tuple[list[int], int | None]:
        """Check the settings against the episode; the decimations to try and ``n_markov``."""
        m = ep.U.shape[0]
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
        if self.decimation == 'auto':
            grid = [d for d in era_select.DECIMATION_GRID
                    if d == 1 or ep.n_samples // d >= 200]
        else:
            grid = [_positive_int('decimation', self.decimation)]
        n_markov = None if self.n_markov is None else _positive_int('n_markov', self.n_markov)
        if self.observer_order is not None:
            _positive_int('observer_order', self.observer_order)
        for r in self._orders():
            _positive_int('r', r)
        if n_markov is not None:
            # Before any work: at the finest decimation tried (the most samples).
            _check_horizon(n_markov, ep, min(grid))
        return grid, n_markov

    def _search(self, ep: Episode, y_ref: Array, grid: list[int], n_markov: int | None,
                prepared: dict[int, Prepared]) -> dict[str, Any]:
        """The blocked cross-validation over every decimation of ``grid`` (when selecting)."""
        out: dict[str, Any] = {'rows': [], 'per_d': {}, 'tried': [], 'excluded': []}
        if not (self.selection == 'holdout' or self.decimation == 'auto'):
            return out
        orders = tuple(self._orders()) or None
        ridge = self.okid_ridge
        for d in grid:
            try:
                if n_markov is not None:
                    _check_horizon(n_markov, ep, d)
                prepared[d] = self._prepare(ep, y_ref, d)
                Us, Ys = prepared[d][:2]
                res = era_select.select_okid(
                    Us, Ys, holdout=float(self.holdout),
                    observer_orders=None if self.observer_order is None else (
                        int(self.observer_order),),
                    rhos=era_select.RIDGE_GRID if ridge is None else (float(ridge),),
                    n_markov=n_markov, r_values=orders,
                    refit=bool(self.refit), tie_tol=float(self.tie_tol),
                    criterion=str(self.criterion))
            except (ConfigError, DimensionError) as err:
                if self.decimation != 'auto':
                    raise
                out['tried'].append({'decimation': d, 'tail_error': None, 'error': str(err)})
                continue
            out['per_d'][d] = res
            out['rows'].extend({**row, 'decimation': d} for row in res['rows'])
            out['tried'].append({'decimation': d, 'tail_error': res['tail_error']})
        if not out['per_d']:
            raise DimensionError(
                f'ERA/OKID found no usable setting for episode {ep.name!r} '
                f'({ep.n_samples} samples): '
                f'{out["tried"][0]["error"] if out["tried"] else ""}')
        return out

    def _settings(self, search: dict[str, Any], grid: list[int], excluded: set[int]
                  ) -> tuple[dict[str, Any] | None, int, int | None, float | None, bool,
                             int | None]:
        """``(selection, d, l, ρ, intercept, r)``: chosen, or as given (``selection='none'``)."""
        if not search['per_d']:
            return None, grid[0], self.observer_order, self.okid_ridge, False, self.r
        rows = [row for row in search['rows'] if row['decimation'] not in excluded]
        best = era_select.choose(rows, float(self.tie_tol))
        d = int(best['decimation'])
        sel = dict(search['per_d'][d])
        sel.update({'observer_order': int(best['observer_order']),
                    'ridge': float(best['ridge']), 'r': int(best['r']),
                    'tail_error': float(best['tail_error'])})
        sel['table'] = [{**row, 'decimation': dd} for dd, res in search['per_d'].items()
                        for row in res['table']]
        del sel['rows']
        intercept = bool(best.get('intercept', False))
        sel['intercept'] = intercept
        r_sel = sel['r'] if self.r is None else int(self.r)
        return sel, d, sel['observer_order'], sel['ridge'], intercept, r_sel

    def _fit_metadata(self, ep: Episode, fit: dict[str, Any], sel: dict[str, Any] | None,
                      A: Array, dt: float, m: int) -> dict[str, Any]:
        ev = np.linalg.eigvals(A)
        P, Pu, d = self.output_basis_, self.input_basis_, self.decimation_
        return {
            'learner': 'ERAOKID', 'r': int(A.shape[0]), 'episode': ep.name,
            'decimation': d, 'dt_data': ep.dt, 'dt_fit': d * ep.dt, 'dt_model': dt,
            'resampled_to_data_rate': self.resampled_, 'n_markov': fit['nm'],
            'okid_ridge': fit['ridge'], 'okid_intercept': fit['intercept'],
            'selection': self.selection,
            'selection_table': None if sel is None else _finite_rows(sel['table']),
            'selection_tail_error': None if sel is None else sel['tail_error'],
            'selection_refit': None if sel is None else sel.get('refit'),
            'selection_tie_tol': None if sel is None else float(self.tie_tol),
            'selection_criterion': None if sel is None else sel.get('criterion'),
            'selection_folds': None if sel is None else sel.get('folds'),
            'output_refit': bool(fit['refitted']), 'stabilized': bool(fit['stabilized']),
            'observer_order': fit['lo'], 'okid_residual': fit['info']['residual'],
            'okid_rank': fit['info']['rank'], 'okid_unknowns': fit['info']['n_unknowns'],
            'n_block_rows': self.n_block_rows, 'n_block_cols': self.n_block_cols,
            'hsv_tol': self.hsv_tol, 'output_rank': None if P is None else int(P.shape[1]),
            'input_rank': m if Pu is None else int(Pu.shape[1]),
            'okid_rcond': self.okid_rcond,
            'hankel_singular_values': fit['hsv'][:200].tolist(),
            'input_scale': self.input_scale_.tolist(),
            'output_scale': self.output_scale_.tolist(),
            'eigenvalues_real': ev.real.tolist(), 'eigenvalues_imag': ev.imag.tolist(),
            'stability_margin': float(1.0 - np.max(np.abs(ev))),
            'fit_time_s': self.fit_time_,
        }

    def _prepare(self, ep: Episode, y_ref: Array, d: int) -> Prepared:
        """Decimated, scaled, compressed data: ``Us, Ys, s_u, s_y, P, P_u``."""
        m = ep.U.shape[0]
        Ud, Yd = decimate(ep.U, ep.Y - y_ref[:, None], d)
        if Ud.shape[1] < 2 * (2 * m + 1):
            raise DimensionError(
                f'episode {ep.name!r} has {Ud.shape[1]} samples after decimation {d}: too few '
                f'for OKID with m={m} inputs. Use less decimation (--decimation 1) or a longer '
                'episode.')
        s_u = channel_scale(Ud)
        s_y = channel_scale(Yd)
        s_y = np.maximum(s_y, float(self.output_scale_floor) * float(np.max(s_y)))
        Us, Ys = Ud / s_u[:, None], Yd / s_y[:, None]
        Ys, P = compress_outputs(Ys, self.output_rank)
        Us, Pu = compress_inputs(Us, self.input_rank)
        return Us, Ys, s_u, s_y, P, Pu


def _positive_int(name: str, value: Any) -> int:
    """``value`` as an int >= 1, else a ConfigError naming the option as its CLI flag."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ConfigError(f'--{name.replace("_", "-")} must be an integer >= 1; got '
                          f'{value!r}.')
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
            f'--n-markov {n_markov} exceeds what episode {ep.name!r} supports: it has {K} '
            f'samples at decimation {d}, so the Markov horizon can be at most {max(K - 1, 0)} '
            f'(default {default_n_markov(K)}). Give a smaller --n-markov, a longer '
            'episode, or less decimation.')


def _finite_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """JSON-safe copy of a selection table (``inf``/``nan`` become ``None``)."""
    return [{k: (None if isinstance(v, float) and not np.isfinite(v) else v)
             for k, v in row.items()} for row in rows]
