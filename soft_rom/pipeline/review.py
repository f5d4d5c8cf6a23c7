"""What the fit table says about each model besides its errors: trust, steps, variants.

:func:`review_rows` adds notes to the rows of ``soft-rom fit``'s table:

* a model that cannot be trusted (:meth:`~soft_rom.models.LinearROM.trust_issues`);
* a model that steps at another time step than the data (ERA/OKID at a decimation whose
  realization of that order has no real root at the data step);
* a stable-variant DMDc model whose training error is worse than the paper variant's of the
  same SVDs, or worse than that of a smaller ``r`` of the same fit, with the reason.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from soft_rom.evaluation import evaluate
from soft_rom.pipeline.fit import FittedModel

__all__ = ['review_rows']


def review_rows(rows: Sequence[dict[str, Any]], fitted: Sequence[FittedModel],
                data: Any) -> None:
    """Add notes to ``rows`` (one per fitted model, same order), in place."""
    for row, fit in zip(rows, fitted):
        if row['trust']:
            row['notes'].append('NOT TRUSTED: ' + '; '.join(row['trust']))
        dt_data = fit.data_dt
        if dt_data is not None and abs(fit.model.dt - dt_data) > 1e-9 * dt_data:
            meta = fit.model.metadata
            row['notes'].append(
                f'steps at dt = {fit.model.dt:g} s, not the data step {dt_data:g} s: its '
                f'realization at decimation {meta.get("decimation")} has no real root at the '
                'data step (--decimation 1 fits at the data step)')
    stable = [(row, fit) for row, fit in zip(rows, fitted)
              if fit.model.method == 'dmdc' and fit.model.metadata.get('variant') == 'stable']
    if stable:
        _review_stable_dmdc(stable, data)


def _review_stable_dmdc(pairs: list[tuple[dict[str, Any], FittedModel]], data: Any) -> None:
    """Compare each stable DMDc model with the paper variant, and along ``r``."""
    best: tuple[int, float] | None = None
    for row, fit in sorted(pairs, key=lambda pair: pair[0]['r']):
        err = row['train_relative_deviation_error']
        learner = fit.learner
        if learner is not None:
            paper = learner.model_for(row['r'], variant='paper')
            e_paper = evaluate(paper, data.episodes).get()['relative_deviation_error']
            row['paper_variant_train_relative_deviation_error'] = e_paper
            if err > e_paper:
                row['notes'].append(f'training error {err:.3g} is worse than the paper '
                                    f"variant's {e_paper:.3g} at r = {row['r']} "
                                    '(--dmdc-variant paper)')
        if best is not None and err > best[1] * 1.05:
            row['notes'].append(f'training error {err:.3g} is above that of r = {best[0]} '
                                f'({best[1]:.3g}) of this fit: {_why(fit)}')
        if np.isfinite(err) and (best is None or err < best[1]):
            best = (row['r'], err)


def _why(fit: FittedModel) -> str:
    """Why a larger stable DMDc model fits its training data worse (from its metadata)."""
    meta = fit.model.metadata
    clipped = int(meta.get('eigenvalues_clipped') or 0)
    ridge = meta.get('lag_ridge')
    why = ('its lag regression fits one step at a time, not the simulation, and more '
           'coordinates bring more weakly determined directions')
    if ridge is not None:
        why += f' (ridge {ridge:g}, chosen on held-out tails)'
    if clipped:
        why += (f'; {clipped} eigenvalue(s) outside |z| <= {meta.get("max_spectral_radius"):.6g} '
                'were pulled onto that circle')
    return why
