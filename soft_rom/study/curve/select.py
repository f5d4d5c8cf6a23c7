"""The held-out choices of the learning curve and of ``soft-rom fit --forces cubic|auto``.

Settings are chosen on the training episodes only: the episodes are split into ``K``
interleaved folds (:func:`folds_of`), each candidate is fitted on the other folds and
simulated on the episodes left out, and the squared output errors are pooled over the folds
(:func:`held_out`). :func:`choose_forces` is the one verdict of linear against cubic forces
that both the study and the CLI use: at a given ``r``, the cubic model's ``(reg, eps4)`` is
chosen on the folds, and ``forces='auto'`` keeps it only when its held-out error is at most
``1 - margin`` times the linear model's.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
import logging
import math
import time
from typing import Any

import numpy as np

from soft_rom.data import Episode
from soft_rom.errors import ConfigError, SoftRomError
from soft_rom.models import LinearROM

__all__ = ['AUTO_MARGIN', 'CUBIC_GRID', 'ForcesVerdict', 'Reduction', 'choose_forces',
           'fit_with_verdict', 'folds_of', 'forces_verdict', 'held_out']

LOG = logging.getLogger(__name__)

#: Candidate ``(reg, eps4)`` of the cubic LOpInf (held-out choice).
CUBIC_GRID: tuple[tuple[float, float], ...] = ((1e-3, 1e-6), (1e-2, 1e-6), (1e-1, 1e-6),
                                                (1e-2, 1e-2))

#: ``forces='auto'`` keeps the cubic model only when its held-out error is at most
#: ``1 - AUTO_MARGIN`` times the linear model's.
AUTO_MARGIN = 0.1

#: Held-out folds over the training episodes (at most one per episode).
FOLDS = 4


def _pooled(errors: Sequence[tuple[float, float]]) -> float:
    """``sqrt(Σ err² / Σ dev²)`` over ``(err², dev²)`` pairs (``inf`` if any is not finite)."""
    e = sum(a for a, _ in errors)
    d = sum(b for _, b in errors)
    return math.sqrt(e / d) if d > 0 and math.isfinite(e) else math.inf


def _squares(model: LinearROM, ep: Episode, y_ref: np.ndarray) -> tuple[float, float]:
    """``(|Y - Ŷ|², |Y - y_ref|²)`` of one held-out episode (``inf`` when it fails)."""
    from soft_rom.evaluation import predict
    dev = float(np.sum((ep.Y - y_ref[:, None]) ** 2))
    try:
        with np.errstate(all='ignore'):
            Yh = predict(model, ep)
    except (SoftRomError, np.linalg.LinAlgError, FloatingPointError, ValueError):
        return math.inf, dev
    err = float(np.sum((ep.Y - Yh) ** 2))
    return (err if math.isfinite(err) else math.inf), dev


def folds_of(n: int, k: int) -> list[list[int]]:
    """``min(n, k)`` interleaved groups of episode indices (each held out once)."""
    k = max(1, min(int(n), int(k)))
    return [list(range(i, n, k)) for i in range(k)]


def held_out(fit: Callable[[list[int]], dict[Any, LinearROM]], episodes: Sequence[Episode],
             folds: Sequence[Sequence[int]], y_ref: np.ndarray) -> dict[Any, float]:
    """Pooled held-out deviation error of every candidate ``fit`` returns.

    ``fit(train_indices)`` returns ``{key: model}`` fitted on those episodes (a candidate
    whose fit failed is left out); each model is scored on the episodes of the fold left
    out, and the squares are pooled over the folds. A candidate missing from some fold, or
    that blows up there, scores ``inf``.
    """
    parts: dict[Any, list[tuple[float, float]]] = {}
    seen: dict[Any, int] = {}
    n = len(episodes)
    for hold in folds:
        keep = [i for i in range(n) if i not in hold]
        for key, model in fit(keep).items():
            seen[key] = seen.get(key, 0) + 1
            parts.setdefault(key, []).extend(_squares(model, episodes[i], y_ref) for i in hold)
    return {key: _pooled(v) if seen[key] == len(folds) else math.inf
            for key, v in parts.items()}


def _tied_pick(table: dict[Any, float], prefer: Callable[[Any], Any],
               tie_tol: float = 0.03) -> Any:
    """The key of the lowest error (``None`` when nothing is finite).

    Errors within ``tie_tol`` of the lowest are tied; ``prefer`` (largest wins) breaks the tie.
    """
    finite = {k: v for k, v in table.items() if math.isfinite(v)}
    if not finite:
        return None
    best = min(finite.values())
    tied = [k for k, v in finite.items() if v <= best * (1.0 + tie_tol)]
    return max(tied, key=prefer)


# ------------------------------------------------------------------------- fitters
class Reduction:
    """The POD of training episodes, and the fits on its coordinates.

    The basis comes from the training episodes only (``r_pod`` modes, or those that hold
    ``energy`` of the snapshot energy when ``r_pod`` is None); every fitter takes the indices
    of the episodes it may use (a fold, or all of them).
    """

    def __init__(self, train: Sequence[Episode], q_ref: np.ndarray, y_ref: np.ndarray,
                 r_pod: int | None, energy: float = 0.95) -> None:
        from soft_rom.basis import POD, project
        k = sum(ep.n_samples for ep in train)
        pod = POD(r=None if r_pod is None else min(r_pod, k), energy=energy).fit(
            [ep.Q for ep in train], q_ref)
        self.r_pod = int(pod.r_)
        self.energy = np.asarray(pod.energy_)
        self.Qhat = [project(ep.Q, pod.basis_, q_ref) for ep in train]
        self.train = list(train)
        self.y_ref = np.asarray(y_ref, dtype=np.float64)
        self.dt = float(train[0].dt)

    def _reduced(self, idx: Sequence[int], r: int) -> Any:
        """The leading ``r`` coordinates of the episodes ``idx`` (:class:`ReducedData`)."""
        from soft_rom.reduce import ReducedData
        eps = [self.train[i] for i in idx]
        return ReducedData(coordinates=tuple(self.Qhat[i][:r] for i in idx),
                           U=tuple(ep.U for ep in eps), Y=tuple(ep.Y for ep in eps),
                           t=tuple(ep.t for ep in eps), y_ref=self.y_ref,
                           names=tuple(ep.name for ep in eps), basis='pod')

    def lopinf(self, idx: Sequence[int], r_values: Sequence[int]) -> dict[int, LinearROM]:
        """Linear LOpInf for every ``r`` (one fit at the largest, the others from it)."""
        from soft_rom.learners.lopinf import LOpInf
        r_max = max(r_values)
        learner = LOpInf(r=r_max).fit(self._reduced(idx, r_max))
        return {r: learner.model_for(r) for r in r_values}

    def cubic(self, idx: Sequence[int], r: int, grid: Sequence[tuple[float, float]]
              ) -> dict[tuple[float, float], LinearROM]:
        """Cubic LOpInf for every ``(reg, eps4)`` of ``grid``; failed fits are left out."""
        from soft_rom.learners.lopinf import LOpInf
        out = {}
        for reg, eps4 in grid:
            try:
                out[(reg, eps4)] = LOpInf(r=r, forces='cubic', cubic_options={
                    'reg': reg, 'eps4': eps4}).fit(self._reduced(idx, r)).model_
            except (SoftRomError, np.linalg.LinAlgError) as err:
                LOG.info('cubic reg=%g eps4=%g failed: %s', reg, eps4, err)
        return out

    def dmdc(self, idx: Sequence[int], r_values: Sequence[int], variant: str,
             n_coordinates: int) -> dict[int, LinearROM]:
        """DMDc of ``variant`` for every ``r``, on the leading POD coordinates."""
        from soft_rom.learners.dmdc import DMDc
        l_ = min(n_coordinates, self.Qhat[0].shape[0])
        eps = [Episode(t=self.train[i].t, U=self.train[i].U, Y=self.train[i].Y,
                       Q=self.Qhat[i][:l_], name=self.train[i].name) for i in idx]
        learner = DMDc(r=r_values[0], variant=variant).fit(eps, np.zeros(l_), self.y_ref)
        return {r: learner.model_for(r) for r in r_values}


@dataclass
class ForcesVerdict:
    """Linear against cubic LOpInf at one ``r``, on held-out training episodes.

    Attributes
    ----------
    r : int
    linear_error : float
        Pooled held-out relative deviation error of the linear model (``inf``: blew up).
    cubic : list of dict
        Every cubic candidate: ``reg``, ``eps4``, ``error`` (held out).
    choice : dict or None
        The chosen candidate (lowest held-out error; ties within 3 % go to the larger
        ``reg``, then ``eps4``), None when every candidate failed.
    forces : {'linear', 'cubic'}
        What ``forces='auto'`` keeps.
    folds : list of list of int
        Episode indices held out in each fold.
    margin : float
    episodes : int
        Training episodes the folds split.
    """

    r: int
    linear_error: float
    cubic: list[dict[str, float]]
    choice: dict[str, float] | None
    forces: str
    folds: list[list[int]]
    margin: float
    episodes: int
    notes: list[str] = field(default_factory=list)

    @property
    def cubic_options(self) -> dict[str, float] | None:
        """``{'reg', 'eps4'}`` of the chosen cubic candidate (None if none fitted)."""
        return None if self.choice is None else {'reg': self.choice['reg'],
                                                 'eps4': self.choice['eps4']}

    @property
    def ratio(self) -> float:
        """Held-out error of the chosen cubic model over the linear model's."""
        if self.choice is None:
            return math.inf
        c, lin = self.choice['error'], self.linear_error
        if not math.isfinite(lin):
            return 0.0 if math.isfinite(c) else math.inf
        return c / lin if lin > 0 else math.inf

    def reason(self) -> str:
        """Why ``forces='auto'`` keeps what it keeps, in one sentence."""
        lim = f'{1 - self.margin:.2f}'
        if self.choice is None:
            return 'every cubic candidate failed to fit or blew up on the held-out episodes'
        if not math.isfinite(self.choice['error']):
            return 'the cubic model blew up on a held-out episode'
        if self.forces == 'cubic':
            return (f'its held-out error is {self.ratio:.2f} x the linear one (at most {lim} '
                    'needed)')
        return (f'the cubic held-out error is {self.ratio:.2f} x the linear one; a cubic model '
                f'must be clearly better (at most {lim} x) to be worth its costlier step and '
                'its extrapolation risk')

    def lines(self, asked: str) -> list[str]:
        """The console report: the comparison, and what was kept for ``--forces asked``."""
        lin = f'{self.linear_error:.3g}' if math.isfinite(self.linear_error) else 'blew up'
        if self.choice is None:
            cub = 'no cubic candidate fitted'
        else:
            e = self.choice['error']
            cub = (f'cubic {e:.3g}' if math.isfinite(e) else 'cubic blew up') + \
                f' (reg {self.choice["reg"]:g}, eps4 {self.choice["eps4"]:g})'
        head = (f'lopinf r = {self.r}, held-out deviation error on {len(self.folds)} folds of '
                f'{self.episodes} training episodes: linear {lin}, {cub}')
        if asked == 'auto':
            tail = f'--forces auto keeps {self.forces}: {self.reason()}.'
        elif self.forces == 'cubic':
            tail = f'cubic as asked; --forces auto would keep it too: {self.reason()}.'
        else:
            tail = (f'cubic as asked, but --forces auto would keep linear: {self.reason()}.')
        return [head, '  ' + tail, *('  ' + n for n in self.notes)]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready (``inf`` as None)."""
        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None
        return {'r': self.r, 'linear_error': num(self.linear_error),
                'cubic': [{**c, 'error': num(c['error'])} for c in self.cubic],
                'choice': None if self.choice is None else {**self.choice,
                                                            'error': num(self.choice['error'])},
                'forces_auto': self.forces, 'ratio': num(self.ratio), 'margin': self.margin,
                'folds': self.folds, 'episodes': self.episodes, 'reason': self.reason()}


def forces_verdict(red: Reduction, r: int, folds: Sequence[Sequence[int]],
                   linear_error: float, *, grid: Sequence[tuple[float, float]] = CUBIC_GRID,
                   margin: float = AUTO_MARGIN) -> ForcesVerdict:
    """The cubic candidates at ``r`` on ``folds``, against the linear ``linear_error``."""
    table = held_out(lambda idx: red.cubic(idx, r, grid), red.train, folds, red.y_ref)
    pick = _tied_pick(table, prefer=lambda key: key)
    choice = None if pick is None else {'reg': pick[0], 'eps4': pick[1], 'error': table[pick]}
    keep = choice is not None and choice['error'] <= (1.0 - margin) * linear_error
    return ForcesVerdict(r=int(r), linear_error=float(linear_error),
                         cubic=[{'reg': k[0], 'eps4': k[1], 'error': v}
                                for k, v in table.items()],
                         choice=choice, forces='cubic' if keep else 'linear',
                         folds=[list(f) for f in folds], margin=float(margin),
                         episodes=len(red.train))


def choose_forces(episodes: Sequence[Episode], q_ref: np.ndarray, y_ref: np.ndarray,
                  r_values: Sequence[int] | None, *, energy: float = 0.95,
                  folds: int = FOLDS, grid: Sequence[tuple[float, float]] = CUBIC_GRID,
                  margin: float = AUTO_MARGIN) -> list[ForcesVerdict]:
    """Linear against cubic LOpInf at each ``r``, held out on the training episodes.

    What the learning-curve study does at each training size, for the ``r`` a user asks
    for: a POD of the episodes' states (``max(r_values)`` modes, or ``energy`` when
    ``r_values`` is None), ``min(len(episodes), folds)`` interleaved folds of episodes, the
    linear model's pooled held-out error at each ``r``, and :func:`forces_verdict`.

    Parameters
    ----------
    episodes : list of Episode
        Training episodes with full states ``Q`` (shape ``(n, k_i)``), at least 2.
    q_ref : ndarray, shape (n,)
    y_ref : ndarray, shape (p,)
    r_values : tuple of int or None

    Returns
    -------
    list of ForcesVerdict
        One per ``r``, in the order given.

    Raises
    ------
    ConfigError
        Fewer than 2 episodes, or an episode without states.
    """
    if len(episodes) < 2:
        raise ConfigError('the held-out comparison of linear and cubic forces needs at least '
                          f'2 training episodes (one is held out at a time); got '
                          f'{len(episodes)}.')
    if any(ep.Q is None for ep in episodes):
        raise ConfigError('the held-out comparison of linear and cubic forces needs the full '
                          'states of the training episodes (a training set converted with '
                          'states).')
    y_ref = np.asarray(y_ref, dtype=np.float64)
    red = Reduction(episodes, np.asarray(q_ref, dtype=np.float64), y_ref,
                    None if not r_values else max(r_values), energy)
    rs = tuple(int(r) for r in r_values) if r_values else (red.r_pod,)
    fold_idx = folds_of(len(episodes), folds)
    table = held_out(lambda idx: red.lopinf(idx, rs), red.train, fold_idx, y_ref)
    return [forces_verdict(red, r, fold_idx, table.get(r, math.inf), grid=grid, margin=margin)
            for r in rs]


#: ``fit(r_values, forces, cubic_options)`` -> ``[(model, seconds), ...]`` (the CLI's fit).
FitFn = Callable[[tuple[int, ...] | None, str, 'dict[str, float] | None'],
                 list[tuple[Any, float]]]


def fit_with_verdict(fit: FitFn, episodes: Sequence[Episode], q_ref: np.ndarray | None,
                     y_ref: np.ndarray, r_values: Sequence[int] | None, *, asked: str,
                     coordinates: str, energy: float | None = None
                     ) -> tuple[list[tuple[Any, float]], list[str]]:
    """``soft-rom fit --forces cubic|auto``: the verdict of :func:`choose_forces`, then the fit.

    With ``asked='cubic'`` every model is cubic (at the held-out ``reg``, ``eps4``) and the
    comparison is reported; with ``'auto'`` each ``r`` keeps what the verdict keeps. The
    verdict is recorded in each model's ``metadata['forces_selection']``; its time is added
    to the models' fit times.

    Parameters
    ----------
    fit : callable
        ``fit(r_values, forces, cubic_options)`` fits LOpInf as the user asked otherwise.
    episodes : list of Episode
        The training episodes (states ``Q`` of shape ``(n, k_i)``).
    q_ref : ndarray, shape (n,), optional
        Reference state (default: the first episode's first state).
    y_ref : ndarray, shape (p,)
    r_values : tuple of int or None
        ``None``: ``r`` by POD energy (``energy``, default 0.95), as ``fit`` would choose.
    asked : {'cubic', 'auto'}
    coordinates : {'state', 'outputs'}
        The coordinates of the fit; the verdict is made on states.

    Returns
    -------
    fitted : list of (model, seconds)
    lines : list of str
        The comparison and what was kept, for the console.

    Raises
    ------
    ConfigError
        ``asked='auto'`` on output coordinates or a single episode (nothing to hold out).
    """
    if coordinates != 'state' or len(episodes) < 2:
        why = ('it needs the full states' if coordinates != 'state'
               else 'it needs at least 2 training episodes (one is held out at a time)')
        if asked == 'auto':
            raise ConfigError(f'--forces auto compares linear and cubic forces on held-out '
                              f'training episodes, and {why}; use --forces linear or cubic.')
        return fit(None if not r_values else tuple(r_values), 'cubic', None), [
            f'lopinf: no held-out comparison with the linear model: {why}.']
    t0 = time.perf_counter()
    q0 = (np.asarray(q_ref, dtype=np.float64) if q_ref is not None
          else np.asarray(episodes[0].Q[:, 0:1], dtype=np.float64)[:, 0])
    verdicts = choose_forces(episodes, q0, y_ref, r_values,
                             energy=0.95 if energy is None else energy)
    share = (time.perf_counter() - t0) / len(verdicts)
    fitted: list[tuple[Any, float]] = []
    lines: list[str] = []
    for v in verdicts:
        forces = v.forces if asked == 'auto' else 'cubic'
        opts = v.cubic_options if forces == 'cubic' else None
        for model, seconds in fit((v.r,), forces, opts):
            model.metadata['forces_selection'] = {**v.as_dict(), 'asked': asked,
                                                  'kept': forces}
            fitted.append((model, seconds + share))
        lines += v.lines(asked)
    return fitted, lines
