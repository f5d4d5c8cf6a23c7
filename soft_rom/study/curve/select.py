"""The learning curve's held-out choices of ``r``: folds of training episodes, pooled errors.

Settings are chosen on the training episodes only: the episodes are split into ``K``
interleaved folds (:func:`~soft_rom.pipeline.cubic.folds_of`), each candidate is fitted on
the other folds and simulated on the episodes left out, and the squared output errors are
pooled over the folds (:func:`held_out`). This chooses ``r`` of linear LOpInf and of DMDc; the
cubic model's settings and verdict are the fit pipeline's one selection
(:class:`~soft_rom.pipeline.cubic.HeldOutCubicSelection`), on the same folds, the one that
``soft-rom fit --forces cubic|auto`` uses.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import logging
import math
from typing import Any

import numpy as np

from soft_rom.data import Episode
from soft_rom.errors import SoftRomError
from soft_rom.models import LinearROM
from soft_rom.pipeline.cubic import folds_of
from soft_rom.reduce import ReducedData

__all__ = ['Reduction', 'folds_of', 'held_out']

LOG = logging.getLogger(__name__)


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

    def reduced(self, idx: Sequence[int], r: int) -> ReducedData:
        """The leading ``r`` coordinates of the episodes ``idx``."""
        eps = [self.train[i] for i in idx]
        return ReducedData(coordinates=tuple(self.Qhat[i][:r] for i in idx),
                           U=tuple(ep.U for ep in eps), Y=tuple(ep.Y for ep in eps),
                           t=tuple(ep.t for ep in eps), y_ref=self.y_ref,
                           names=tuple(ep.name for ep in eps), basis='pod')

    def lopinf(self, idx: Sequence[int], r_values: Sequence[int]) -> dict[int, LinearROM]:
        """Linear LOpInf for every ``r`` (one fit at the largest, the others from it)."""
        from soft_rom.learners.lopinf import LOpInf
        r_max = max(r_values)
        learner = LOpInf(r=r_max).fit(self.reduced(idx, r_max))
        return {r: learner.model_for(r) for r in r_values}

    def dmdc(self, idx: Sequence[int], r_values: Sequence[int], variant: str,
             n_coordinates: int) -> dict[int, LinearROM]:
        """DMDc of ``variant`` for every ``r``, on the leading POD coordinates."""
        from soft_rom.learners.dmdc import DMDc
        l_ = min(n_coordinates, self.Qhat[0].shape[0])
        eps = [Episode(t=self.train[i].t, U=self.train[i].U, Y=self.train[i].Y,
                       Q=self.Qhat[i][:l_], name=self.train[i].name) for i in idx]
        learner = DMDc(r=r_values[0], variant=variant).fit(eps, np.zeros(l_), self.y_ref)
        return {r: learner.model_for(r) for r in r_values}
