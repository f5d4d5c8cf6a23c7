"""The one held-out selection of the cubic LOpInf: its settings, and whether it beats linear.

The cubic (quartic-potential) LOpInf has two settings the data must decide: the Tikhonov weight
``reg`` on the nonlinear tensors and the relative floor ``eps4`` of the quartic form
(:mod:`soft_rom.learners.lopinf.cubic`). Too little ``reg`` lets the fitted potential grow
wells the training inputs never reach and test inputs do; a large one shrinks the cubic and
quartic terms to the floor, and the model tends to the linear one. :class:`HeldOutCubicSelection`
is the one selection that ``soft-rom fit --forces cubic|auto``, the paper study's cubic slot
and the learning curve use:

1. **Folds.** With ``n >= 2`` training episodes, ``min(n, folds)`` interleaved groups of
   episodes (:func:`folds_of`); each candidate is fitted on the other groups and simulated on
   the episodes left out. With one episode, its last ``tail`` is held out (fitted on the rest
   of it, the whole episode simulated, the tail scored). The score is the pooled relative
   output error on deviations from ``y_ref`` over everything held out (``inf`` when a fit
   fails or a simulation blows up). Only the reduced training data are used.
2. **Best cubic.** Every ``(reg, eps4)`` of :data:`CUBIC_GRID` is scored; the lowest error
   wins, and errors within ``tie_tol`` (3 %) of it are tied, the tie going to the larger
   ``reg`` (the smoother, more nearly linear potential). ``--forces cubic`` fits this
   candidate on all the training data.
3. **Verdict** (what ``--forces auto`` keeps, :attr:`CubicVerdict.forces`). The linear LOpInf
   of the user's settings is scored on the same folds. The cubic model is kept only when
   there are at least ``min_folds`` (4) folds **and** its held-out error is at most
   ``1 - margin`` (0.9) times the linear one; otherwise the linear model is kept, and the
   verdict says why.

Why this grid and rule (the measurements are in ``docs/methods_variants.md``): the grid is a
path of ``reg`` from weak (1e-3) to strong (10) at the learner's quartic floor; its strong end
is within a few per cent of the linear model, so the best cubic candidate falls back towards
linear when the cubic terms do not pay. A larger floor (``eps4 = 1e-2``) was worse on
held-out and on test episodes of the eel at every ``reg`` tried. Held-out errors of a few
one-episode folds are noisy: with two folds, a cubic model that held out at 0.79 x the linear
one was 3.6-4.0 x worse on two of four test episodes, so a cubic model, whose predictor step
is about 20 x slower and which extrapolates outside the training range, is kept only when
four or more folds agree that it is clearly (10 %) better.
"""

from __future__ import annotations

from collections.abc import Sequence
import copy
from dataclasses import dataclass, field
import math
from typing import Any

import numpy as np

from soft_rom.data import Episode
from soft_rom.errors import ConfigError, SoftRomError
from soft_rom.evaluation import predict
from soft_rom.learners.lopinf import LOpInf
from soft_rom.metrics import relative_error_from_squares
from soft_rom.reduce import ReducedData

__all__ = ['CUBIC_GRID', 'CubicVerdict', 'FOLDS', 'HeldOutCubicSelection', 'MARGIN',
           'MIN_FOLDS', 'folds_of']

#: Candidate ``(reg, eps4)``: ``reg`` from weak to a nearly linear potential.
CUBIC_GRID: tuple[tuple[float, float], ...] = (
    (1e-3, 1e-6), (1e-2, 1e-6), (1e-1, 1e-6), (1.0, 1e-6), (10.0, 1e-6))

#: Held-out folds over the training episodes (at most one per episode).
FOLDS = 4

#: ``--forces auto`` keeps the cubic model only with at least this many folds ...
MIN_FOLDS = 4

#: ... and a held-out error at most ``1 - MARGIN`` times the linear model's.
MARGIN = 0.1

_Fold = tuple[ReducedData, list[Episode], list[int]]


def folds_of(n: int, k: int) -> list[list[int]]:
    """``min(n, k)`` interleaved groups of episode indices (each held out once)."""
    k = max(1, min(int(n), int(k)))
    return [list(range(i, n, k)) for i in range(k)]


@dataclass(frozen=True)
class CubicVerdict:
    """The best cubic candidate at one ``r`` and its held-out comparison with linear.

    Attributes
    ----------
    r : int
    scheme : {'episodes', 'tails'}
        Episodes left out, or the tail of the one episode.
    folds : list of list of int
        Episode indices held out in each fold (``'tails'``: one fold, every episode).
    episodes : int
        Training episodes.
    linear_error : float
        Held-out relative deviation error of the linear LOpInf (``inf``: failed or blew up).
    candidates : list of dict
        ``reg``, ``eps4``, ``error`` of every candidate (``inf``: failed or blew up).
    choice : dict or None
        The best candidate (``reg``, ``eps4``, ``error``); None when every one failed.
    forces : {'linear', 'cubic'}
        What ``--forces auto`` keeps (module docstring, step 3).
    margin : float
    min_folds : int
    tail : float
        Fraction of the episode held out by ``'tails'``.
    """

    r: int
    scheme: str
    folds: list[list[int]]
    episodes: int
    linear_error: float
    candidates: list[dict[str, float]]
    choice: dict[str, float] | None
    forces: str
    margin: float = MARGIN
    min_folds: int = MIN_FOLDS
    tail: float = 0.2
    notes: list[str] = field(default_factory=list)

    @property
    def cubic_options(self) -> dict[str, float] | None:
        """``{'reg', 'eps4'}`` of the best cubic candidate (None if none fitted)."""
        return None if self.choice is None else {'reg': self.choice['reg'],
                                                 'eps4': self.choice['eps4']}

    @property
    def cubic_error(self) -> float:
        """Held-out error of the best cubic candidate (``inf`` if none)."""
        return math.inf if self.choice is None else float(self.choice['error'])

    @property
    def ratio(self) -> float:
        """Held-out error of the best cubic candidate over the linear model's."""
        c, lin = self.cubic_error, self.linear_error
        if not math.isfinite(lin):
            return 0.0 if math.isfinite(c) else math.inf
        return c / lin if lin > 0 else math.inf

    def _where(self) -> str:
        if self.scheme == 'tails':
            return (f'the last {self.tail:.0%} of {self.episodes} training '
                    f'episode{"s" if self.episodes != 1 else ""}')
        return f'{len(self.folds)} folds of {self.episodes} training episodes'

    def reason(self) -> str:
        """Why ``--forces auto`` keeps what it keeps, in one sentence."""
        lim = f'{1 - self.margin:.2f}'
        if self.choice is None or not math.isfinite(self.cubic_error):
            return 'every cubic candidate failed to fit or blew up on held-out data'
        if self.forces == 'cubic':
            return (f'its held-out error is {self.ratio:.2f} x the linear one (at most {lim} '
                    f'needed, on {len(self.folds)} folds)')
        if len(self.folds) < self.min_folds:
            return (f'the cubic held-out error is {self.ratio:.2f} x the linear one, but on '
                    f'{len(self.folds)} fold{"s" if len(self.folds) != 1 else ""} only; a '
                    f'cubic model is kept from {self.min_folds} folds on (train on '
                    f'{self.min_folds} or more episodes): fewer held-out episodes cannot '
                    'tell one that generalizes from one that fits them by chance')
        return (f'the cubic held-out error is {self.ratio:.2f} x the linear one; a cubic model '
                f'must be clearly better (at most {lim} x) to be worth its costlier step and '
                'its extrapolation risk')

    def lines(self, asked: str) -> list[str]:
        """The comparison, and what was kept for ``--forces asked`` (the fit table's notes)."""
        lin = (f'{self.linear_error:.3g}' if math.isfinite(self.linear_error)
               else 'failed or blew up')
        if self.choice is None:
            cub = 'no cubic candidate fitted'
        else:
            e = self.cubic_error
            cub = ((f'cubic {e:.3g}' if math.isfinite(e) else 'cubic blew up')
                   + f' (reg {self.choice["reg"]:g}, eps4 {self.choice["eps4"]:g})')
        head = f'held-out deviation error on {self._where()}: linear {lin}, {cub}'
        if asked == 'auto':
            tail = f'--forces auto keeps {self.forces}: {self.reason()}.'
        elif self.choice is None:
            tail = f'linear forces: {self.reason()}.'
        elif self.forces == 'cubic':
            tail = f'cubic as asked; --forces auto would keep it too: {self.reason()}.'
        elif self.cubic_error > self.linear_error:
            tail = ('cubic as asked, but the linear model held out better; --forces auto '
                    f'would keep linear: {self.reason()}.')
        else:
            tail = f'cubic as asked; --forces auto would keep linear: {self.reason()}.'
        return [head, tail, *self.notes]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (``inf`` as None)."""
        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None
        return {'r': self.r, 'scheme': self.scheme, 'folds': self.folds,
                'episodes': self.episodes, 'linear_error': num(self.linear_error),
                'cubic': [{**c, 'error': num(c['error'])} for c in self.candidates],
                'choice': None if self.choice is None else {**self.choice,
                                                            'error': num(self.cubic_error)},
                'forces_auto': self.forces, 'ratio': num(self.ratio), 'margin': self.margin,
                'min_folds': self.min_folds, 'reason': self.reason()}


class HeldOutCubicSelection:
    """Choose ``reg`` and ``eps4`` of the cubic LOpInf on held-out training data, and judge it.

    Parameters
    ----------
    grid : sequence of (reg, eps4)
        Candidates (default :data:`CUBIC_GRID`).
    folds : int
        At most this many interleaved folds of episodes (default :data:`FOLDS`).
    min_folds : int
        ``--forces auto`` keeps the cubic model only with this many folds or more.
    margin : float
        ... and only at most ``1 - margin`` times the linear held-out error.
    tail : float
        Fraction of the episode held out when there is one.
    tie_tol : float
        Held-out errors within this relative band of the best are tied; the tie goes to the
        larger ``reg``, then ``eps4``.
    """

    def __init__(self, grid: Sequence[tuple[float, float]] = CUBIC_GRID, *,
                 folds: int = FOLDS, min_folds: int = MIN_FOLDS, margin: float = MARGIN,
                 tail: float = 0.2, tie_tol: float = 0.03) -> None:
        if not grid:
            raise ConfigError('the cubic selection needs at least one (reg, eps4) candidate.')
        if int(folds) < 2:
            raise ConfigError(f'folds must be at least 2; got {folds}.')
        self.grid = tuple((float(a), float(b)) for a, b in grid)
        self.folds = int(folds)
        self.min_folds = int(min_folds)
        self.margin = float(margin)
        self.tail = float(tail)
        self.tie_tol = float(tie_tol)

    def split(self, data: ReducedData) -> tuple[str, list[list[int]], list[_Fold]]:
        """``(scheme, held-out indices, [(train, held-out episodes, first scored sample)])``."""
        n = len(data.names)
        if n >= 2:
            groups = folds_of(n, self.folds)
            return 'episodes', groups, [
                (data.subset([j for j in range(n) if j not in hold]),
                 [data.episode(i) for i in hold], [0] * len(hold)) for hold in groups]
        heads, _tails = data.head(1.0 - self.tail)
        return 'tails', [list(range(n))], [
            (heads, [data.episode(i) for i in range(n)], [h.size for h in heads.t])]

    def select(self, data: ReducedData, learner: LOpInf, r: int, *,
               linear: LOpInf | None = None) -> CubicVerdict:
        """The verdict at dimension ``r``.

        Parameters
        ----------
        data : ReducedData
            The reduced training data (at least ``r`` POD coordinates).
        learner : LOpInf
            The cubic learner's other settings (derivatives, solver).
        r : int
        linear : LOpInf, optional
            The linear model to compare with (default ``learner`` with linear forces).
        """
        scheme, groups, folds = self.split(data)
        lin = _variant(linear if linear is not None else learner, r, forces='linear',
                       cubic_options=None)
        lin_err = _held_out_error(lin, folds, data.y_ref)
        rows = []
        for reg, eps4 in self.grid:
            cand = _variant(learner, r, forces='cubic', cubic_options={'reg': reg, 'eps4': eps4},
                            mass='identity', refine='none')
            rows.append({'reg': reg, 'eps4': eps4,
                         'error': _held_out_error(cand, folds, data.y_ref)})
        finite = [row for row in rows if math.isfinite(row['error'])]
        choice = None
        if finite:
            best = min(row['error'] for row in finite)
            tied = [row for row in finite if row['error'] <= best * (1.0 + self.tie_tol)]
            choice = dict(max(tied, key=lambda row: (row['reg'], row['eps4'])))
        keep = (choice is not None and len(groups) >= self.min_folds
                and choice['error'] <= (1.0 - self.margin) * lin_err)
        return CubicVerdict(r=int(r), scheme=scheme, folds=groups, episodes=len(data.names),
                            linear_error=float(lin_err), candidates=rows, choice=choice,
                            forces='cubic' if keep else 'linear', margin=self.margin,
                            min_folds=self.min_folds, tail=self.tail)


def _variant(learner: LOpInf, r: int, **changes: Any) -> LOpInf:
    out = copy.copy(learner)
    out.r = int(r)
    for key, value in changes.items():
        setattr(out, key, value)
    return out


def _held_out_error(learner: LOpInf, folds: list[_Fold], y_ref: np.ndarray) -> float:
    """Pooled relative deviation error on the held-out samples (``inf`` if a fit fails)."""
    err = dev = 0.0
    for train, tests, starts in folds:
        try:
            model = copy.copy(learner).fit(train).model_
            for ep, k0 in zip(tests, starts):
                with np.errstate(all='ignore'):
                    Yh = predict(model, ep)
                err += float(np.sum((ep.Y[:, k0:] - Yh[:, k0:]) ** 2))
                dev += float(np.sum((ep.Y[:, k0:] - y_ref[:, None]) ** 2))
        except (SoftRomError, np.linalg.LinAlgError, FloatingPointError, ValueError):
            return math.inf
    out = relative_error_from_squares(err, dev)
    return float(out) if math.isfinite(out) else math.inf
