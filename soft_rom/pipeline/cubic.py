"""The cubic LOpInf's settings, chosen on held-out training data; linear when cubic does not pay.

The cubic (quartic-potential) LOpInf has two settings the data must decide: the Tikhonov weight
``reg`` on the nonlinear tensors and the relative floor ``eps4`` of the quartic form
(:mod:`soft_rom.learners.lopinf.cubic`). Too little of either lets the fitted potential grow
wells the training inputs never reach and test inputs do; too much makes it linear. So
:class:`HeldOutCubicSelection` fits every candidate of a small grid on part of the training
data and scores it, by the relative output error on deviations from ``y_ref``, on the rest:

* ``'episodes'`` -- leave one training episode out (each episode in turn), when there are
  two or more;
* ``'tails'`` -- fit on the first ``1 - tail`` of every episode, simulate the whole episodes,
  score the tails (one episode).

The linear LOpInf of the same settings is scored the same way; when no candidate beats it on
the held-out data the choice is the linear model (``forces='linear'``), and the selection
says so. Test data are never seen: only the reduced training data are used. The result
(:class:`CubicChoice`) carries the table of every candidate, so a learning-curve study or
``--forces auto`` can reuse it as it is.
"""

from __future__ import annotations

from collections.abc import Sequence
import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from soft_rom.data import Episode
from soft_rom.errors import ConfigError, SoftRomError
from soft_rom.evaluation import predict
from soft_rom.learners.lopinf import LOpInf
from soft_rom.metrics import relative_error_from_squares
from soft_rom.models import LinearROM
from soft_rom.reduce import ReducedData

__all__ = ['CUBIC_GRID', 'CubicChoice', 'HeldOutCubicSelection']

#: Candidate ``(reg, eps4)`` of the selection: from the learner's defaults to strong
#: regularization (a nearly linear potential).
CUBIC_GRID: tuple[tuple[float, float], ...] = (
    (1e-4, 1e-6), (1e-3, 1e-2), (1e-2, 1e-2), (1e-1, 1e-1))


@dataclass(frozen=True)
class CubicChoice:
    """The settings chosen and the held-out comparison they were chosen by.

    Attributes
    ----------
    forces : {'cubic', 'linear'}
        ``'linear'`` when no cubic candidate beat the linear model on held-out data.
    options : dict
        ``reg`` and ``eps4`` of the chosen cubic candidate (the best one when linear won).
    scheme : {'episodes', 'tails'}
        How the training data were split.
    linear_error : float
        Held-out relative deviation error of the linear LOpInf.
    cubic_error : float
        That of the chosen (best) cubic candidate.
    candidates : list of dict
        ``reg``, ``eps4``, ``error`` of every candidate (``inf``: the fit failed or the
        simulation blew up).
    """

    forces: str
    options: dict[str, float]
    scheme: str
    linear_error: float
    cubic_error: float
    candidates: list[dict[str, Any]] = field(default_factory=list)

    @property
    def note(self) -> str:
        """One line for the fit table."""
        held = f'held-out dev. error cubic {self.cubic_error:.3g} vs linear ' \
               f'{self.linear_error:.3g} ({self.scheme})'
        if self.forces == 'linear':
            return f'cubic terms did not pay on held-out data: linear forces ({held})'
        return (f'cubic reg={self.options["reg"]:g} eps4={self.options["eps4"]:g} chosen on '
                f'held-out data ({held})')

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (for a model's metadata)."""
        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None
        return {'forces': self.forces, 'options': dict(self.options), 'scheme': self.scheme,
                'linear_error': num(self.linear_error), 'cubic_error': num(self.cubic_error),
                'candidates': [{**c, 'error': num(c['error'])} for c in self.candidates]}


class HeldOutCubicSelection:
    """Choose ``reg`` and ``eps4`` of the cubic LOpInf on held-out training data.

    Parameters
    ----------
    grid : sequence of (reg, eps4)
        Candidates (default :data:`CUBIC_GRID`).
    scheme : {'auto', 'episodes', 'tails'}
        ``'auto'``: leave one episode out with two or more episodes, else the tails.
    tail : float
        Fraction of each episode held out by ``'tails'``.
    tie_tol : float
        Held-out errors within this relative band of the best are tied; the tie goes to the
        larger ``reg`` (the smoother potential).
    """

    def __init__(self, grid: Sequence[tuple[float, float]] = CUBIC_GRID, *,
                 scheme: str = 'auto', tail: float = 0.2, tie_tol: float = 0.03) -> None:
        self.grid = grid
        self.scheme = scheme
        self.tail = tail
        self.tie_tol = tie_tol

    def folds(self, data: ReducedData) -> tuple[str, list[tuple[ReducedData, list[Episode],
                                                                list[int]]]]:
        """``(scheme, [(train, test episodes, first scored sample of each), ...])``."""
        scheme = self.scheme
        if scheme == 'auto':
            scheme = 'episodes' if len(data.names) >= 2 else 'tails'
        if scheme == 'episodes':
            if len(data.names) < 2:
                raise ConfigError('leaving one episode out needs two or more training '
                                  'episodes; use the tails.')
            n = len(data.names)
            return scheme, [(data.subset([j for j in range(n) if j != i]), [data.episode(i)],
                             [0]) for i in range(n)]
        if scheme != 'tails':
            raise ConfigError(f"scheme must be 'auto', 'episodes' or 'tails'; got {scheme!r}.")
        heads, _tails = data.head(1.0 - float(self.tail))
        starts = [h.size for h in heads.t]
        return scheme, [(heads, [data.episode(i) for i in range(len(data.names))], starts)]

    def select(self, data: ReducedData, learner: LOpInf, r: int) -> CubicChoice:
        """The chosen settings for dimension ``r`` (``learner``: the other LOpInf settings)."""
        scheme, folds = self.folds(data)
        linear = _variant(learner, r, forces='linear', cubic_options=None)
        lin_err = _held_out_error(linear, folds, data.y_ref)
        rows = []
        for reg, eps4 in self.grid:
            cand = _variant(learner, r, forces='cubic', cubic_options={'reg': reg, 'eps4': eps4},
                            mass='identity', refine='none')
            rows.append({'reg': float(reg), 'eps4': float(eps4),
                         'error': _held_out_error(cand, folds, data.y_ref)})
        best = min(rows, key=lambda row: row['error'])
        tied = [row for row in rows if row['error'] <= best['error'] * (1.0 + self.tie_tol)]
        pick = max(tied, key=lambda row: (row['reg'], row['eps4']))
        forces = 'cubic' if np.isfinite(pick['error']) and pick['error'] < lin_err else 'linear'
        return CubicChoice(forces=forces, options={'reg': pick['reg'], 'eps4': pick['eps4']},
                           scheme=scheme, linear_error=lin_err, cubic_error=pick['error'],
                           candidates=rows)


def _variant(learner: LOpInf, r: int, **changes: Any) -> LOpInf:
    out = copy.copy(learner)
    out.r = int(r)
    for key, value in changes.items():
        setattr(out, key, value)
    return out


def _held_out_error(learner: LOpInf, folds: list[tuple[ReducedData, list[Episode], list[int]]],
                    y_ref: np.ndarray) -> float:
    """Pooled relative deviation error on the held-out samples (``inf`` if a fit fails)."""
    err = dev = 0.0
    for train, tests, starts in folds:
        try:
            model: LinearROM = copy.copy(learner).fit(train).model_
            for ep, k0 in zip(tests, starts):
                Yh = predict(model, ep)
                err += float(np.sum((ep.Y[:, k0:] - Yh[:, k0:]) ** 2))
                dev += float(np.sum((ep.Y[:, k0:] - y_ref[:, None]) ** 2))
        except (SoftRomError, np.linalg.LinAlgError, FloatingPointError):
            return float('inf')
    out = relative_error_from_squares(err, dev)
    return out if np.isfinite(out) else float('inf')
