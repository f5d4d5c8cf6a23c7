"""Predictions of a ROM on recorded episodes, and their errors.

:func:`predict` simulates a model on an episode's inputs and returns the outputs at the
episode's sample times; :func:`evaluate` reports both metrics of :mod:`soft_rom.metrics`
(the paper's relative error on absolute outputs, and the same on deviations from ``y_ref``)
per episode and overall, optionally split into a training part ``t < t_split`` and a test part
``t >= t_split`` of one continuous simulation (the paper's time-extrapolation study; times are
counted from each episode's first sample).

Sample-time rules of :func:`predict` (data step ``h``, model step ``Δ``):

* continuous models (LOpInf) are discretized exactly at ``h``;
* discrete models with ``h = j Δ`` (``j`` whole) step ``j`` native steps per sample;
* discrete models with ``Δ = d h`` (``d`` whole; decimated ERA/OKID) step at the model rate
  with the input of each step equal to the **mean of the data inputs over its ``d`` samples**
  (the rule used to fit them, :func:`soft_rom.learners.era.decimate`; a last incomplete block is
  averaged over the samples it has). The state is **linearly interpolated** between model
  steps back to the data times, and the feedthrough ``D u`` uses the data input at each sample:
  ``ŷ(t_i) = C x(t_i) + D u_i + y_ref``;
* anything else raises :class:`~soft_rom.errors.DimensionError`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.data import (
    check_finite,
    Episode,
    MAX_STEP_RATIO,
    nonuniform_message,
    step_ratio_problem,
)
from soft_rom.errors import ConfigError, DimensionError
from soft_rom.metrics import relative_error_from_squares
from soft_rom.models import DiscreteModel, LinearROM, run_states, SecondOrderModel
from soft_rom.reduce import episode_head

__all__ = ['Evaluation', 'MAX_STEP_RATIO', 'evaluate', 'held_out_errors', 'predict']

Array = NDArray[np.float64]

_INITIAL = ('reference', 'output')


def _check_sizes(model: LinearROM, ep: Episode) -> None:
    if ep.U.shape[0] != model.n_inputs or ep.Y.shape[0] != model.n_outputs:
        raise DimensionError(
            f'episode {ep.name!r} has {ep.U.shape[0]} inputs and {ep.Y.shape[0]} outputs; '
            f'the {model.method} model expects {model.n_inputs} inputs and '
            f'{model.n_outputs} outputs. Evaluate on data of the same robot/layout.')


def _check_step_ratio(model: LinearROM, name: str, h: float) -> None:
    problem = step_ratio_problem(name, h, model.dt, model.method)
    if problem:
        raise DimensionError(f'{problem} Steps that differ by more than a factor of '
                             f'{MAX_STEP_RATIO:g} are refused.')


def predict(model: LinearROM, episode: Episode, *, initial: str = 'reference') -> Array:
    """Simulate ``model`` on the inputs of ``episode``; outputs at the episode's times.

    Parameters
    ----------
    model : LinearROM
    episode : Episode
        Uniformly sampled, times in seconds (a step within a factor of
        :data:`MAX_STEP_RATIO` of the model's); ``U (m, k)`` absolute inputs, finite.
    initial : {'reference', 'output'}
        Initial state: the reference configuration (zero deviation, at rest), or the
        least-squares state matching the first measured output (``state_from_output``).

    Returns
    -------
    Y_hat : ndarray, shape (p, k)
        Absolute predicted outputs.
    """
    if initial not in _INITIAL:
        raise ConfigError(f"initial must be 'reference' or 'output'; got {initial!r}.")
    _check_sizes(model, episode)
    ep = episode
    check_finite(f'U of episode {ep.name!r}', ep.U, 'predicting')   # else NaN from there on
    k = ep.n_samples
    x0 = (model.state_from_output(ep.Y[:, 0], ep.U[:, 0]) if initial == 'output'
          else model.initial_state())
    if k == 1:
        return model.output(x0, ep.U[:, 0])[:, None]
    if not ep.is_uniform():
        raise DimensionError(nonuniform_message(ep.name, ep.t))
    h = ep.dt
    _check_step_ratio(model, ep.name, h)
    if getattr(model, 'is_nonlinear', False):    # continuous nonlinear model: its own stepper
        return np.asarray(model.simulate(ep.U, x0, dt=h))  # type: ignore[call-arg]
    if isinstance(model, SecondOrderModel):
        sys_ = model.discretize(h)
        X = run_states(sys_.A, sys_.B, x0, ep.U[:, :-1])
    else:
        ratio = h / model.dt
        if abs(ratio - round(ratio)) <= 1e-6 * max(ratio, 1.0) and round(ratio) >= 1:
            sys_ = model.discretize(round(ratio) * model.dt)
            X = run_states(sys_.A, sys_.B, x0, ep.U[:, :-1])
        else:
            inv = model.dt / h
            d = int(round(inv))
            if d < 2 or abs(inv - d) > 1e-6 * inv:
                raise DimensionError(
                    f'the {model.method} model steps by {model.dt:g} s and episode '
                    f'{ep.name!r} is sampled every {h:g} s: one must be a whole multiple of '
                    'the other.')
            sys_ = model.system
            n_steps = -(-k // d)                      # ceil(k / d) model steps
            pad = n_steps * d - k
            Upad = np.concatenate([ep.U, np.full((ep.U.shape[0], pad), np.nan)], axis=1)
            Ublk = np.nanmean(Upad.reshape(ep.U.shape[0], n_steps, d), axis=2)
            Xm = run_states(sys_.A, sys_.B, x0, Ublk)   # states at t_0 + j d h, j = 0..n_steps
            pos = np.arange(k) / d                    # data times in model steps
            j = np.minimum(np.floor(pos).astype(int), n_steps - 1)
            w = pos - j
            X = Xm[:, j] * (1.0 - w) + Xm[:, j + 1] * w
            return sys_.C @ X + sys_.D @ ep.U + model.y_ref[:, None]
    X = X[:, :k]
    return sys_.C @ X + sys_.D @ ep.U + model.y_ref[:, None]


@dataclass
class Evaluation:
    """Errors of one model on a list of episodes.

    Attributes
    ----------
    rows : list of dict
        One row per (episode, segment) with keys ``episode``, ``segment`` (``'all'``,
        ``'train'`` for ``t < t_split``, ``'test'`` for ``t >= t_split``), ``n_samples``,
        ``relative_error`` and ``relative_deviation_error``; rows with ``episode='*'`` pool
        all episodes (Frobenius norms over the concatenated outputs).
    predictions : dict of str to ndarray
        ``episode name -> Y_hat (p, k)`` when asked for.
    model : dict
        ``method``, ``r``, ``dt`` of the model.
    """

    rows: list[dict[str, Any]]
    predictions: dict[str, Array] = field(default_factory=dict)
    model: dict[str, Any] = field(default_factory=dict)

    def get(self, episode: str = '*', segment: str = 'all') -> dict[str, Any]:
        """The row for ``(episode, segment)``."""
        for row in self.rows:
            if row['episode'] == episode and row['segment'] == segment:
                return row
        raise KeyError(f'no row for episode {episode!r}, segment {segment!r}.')

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary (without predictions)."""
        return {'model': dict(self.model), 'rows': [dict(r) for r in self.rows]}


def _row(episode: str, segment: str, sq: dict[str, float], n: int) -> dict[str, Any]:
    return {'episode': episode, 'segment': segment, 'n_samples': int(n),
            'relative_error': relative_error_from_squares(sq['err'], sq['abs']),
            'relative_deviation_error': relative_error_from_squares(sq['err'], sq['dev'])}


def _check_split(t_split: float) -> None:
    """``t_split`` must be a positive number of seconds (as ``soft-rom evaluate --t-split``).

    NaN, a negative or a zero split left a part empty everywhere: rows of 0 samples and NaN
    errors. One past an episode's end leaves that episode's test part empty (NaN rows, null
    in the JSON summaries), as the CLI documents.
    """
    try:
        ok = math.isfinite(t_split) and t_split > 0
    except TypeError:
        ok = False
    if not ok:
        raise ConfigError(f't_split must be a positive number of seconds from each '
                          f"episode's first sample; got {t_split!r}.")


def evaluate(model: LinearROM, episodes: Episode | Sequence[Episode], *,
             t_split: float | None = None, initial: str = 'reference',
             return_predictions: bool = False) -> Evaluation:
    """Both error metrics of ``model`` on each episode and pooled.

    Each episode is simulated once, from its start (:func:`predict`); with ``t_split`` the
    errors are also computed on ``t < t_split`` and ``t >= t_split`` of that one simulation.

    Parameters
    ----------
    model : LinearROM
    episodes : Episode or sequence of Episode
    t_split : float, optional
        Split time in seconds from each episode's first sample, positive and finite (else
        :class:`~soft_rom.errors.ConfigError`); past an episode's end its test part is empty
        (NaN errors, 0 samples).
    initial : {'reference', 'output'}
        See :func:`predict`.
    return_predictions : bool
        Keep ``Y_hat`` of every episode in :attr:`Evaluation.predictions`.

    Returns
    -------
    Evaluation
    """
    eps = [episodes] if isinstance(episodes, Episode) else list(episodes)
    if not eps:
        raise DimensionError('no episodes to evaluate on.')
    if t_split is not None:
        _check_split(t_split)
    segments = ['all'] if t_split is None else ['all', 'train', 'test']
    pooled = {s: {'err': 0.0, 'abs': 0.0, 'dev': 0.0, 'n': 0} for s in segments}
    rows: list[dict[str, Any]] = []
    preds: dict[str, Array] = {}
    y_ref = model.y_ref[:, None]
    for ep in eps:
        for name, arr in (('U', ep.U), ('Y', ep.Y)):     # a NaN would make every error NaN
            check_finite(f'{name} of episode {ep.name!r}', np.asarray(arr), 'evaluating')
        Y_hat = predict(model, ep, initial=initial)
        if return_predictions:
            preds[ep.name] = Y_hat
        for seg in segments:
            sel: slice | NDArray[np.bool_]
            if seg == 'all' or t_split is None:
                sel = slice(None)
            elif seg == 'train':
                sel = ep.t - ep.t[0] < t_split - 1e-12
            else:
                sel = ep.t - ep.t[0] >= t_split - 1e-12
            Y, Yh = ep.Y[:, sel], Y_hat[:, sel]
            sq = {'err': float(np.sum((Y - Yh) ** 2)), 'abs': float(np.sum(Y ** 2)),
                  'dev': float(np.sum((Y - y_ref) ** 2))}
            n = Y.shape[1]
            rows.append(_row(ep.name, seg, sq, n))
            for key in ('err', 'abs', 'dev'):
                pooled[seg][key] += sq[key]
            pooled[seg]['n'] += n
    for seg in segments:
        rows.append(_row('*', seg, pooled[seg], int(pooled[seg]['n'])))
    info = {'method': model.method, 'r': model.r, 'dt': model.dt}
    if isinstance(model, DiscreteModel):
        info['n_states'] = model.n_states
    return Evaluation(rows=rows, predictions=preds, model=info)


def held_out_errors(fit: Any, episodes: Sequence[Episode], y_ref: Array, *,
                    tail: float = 0.2) -> dict[str, Any]:
    """How well a fit predicts data it was not fitted on: the monitor's reference error.

    With two or more training episodes each is left out in turn: ``fit`` is called on the
    others and the model it returns predicts the left-out episode whole, from the reference
    state (as a model runs on new inputs). With one, ``fit`` is called on its first
    ``1 - tail`` and the prediction of the whole episode is scored on the last ``tail``.
    The squared errors are pooled over every held-out sample.

    Parameters
    ----------
    fit : callable
        ``fit(episodes) -> model``: the same method, settings and ``r`` as the model being
        described.
    episodes : sequence of Episode
        The training episodes.
    y_ref : ndarray, shape (p,)

    Returns
    -------
    dict
        ``deviation_error`` and ``absolute_error`` (relative, as :mod:`soft_rom.metrics`),
        ``data`` (what was held out, in words) and ``samples``: what
        ``model.metadata['held_out']`` holds (:mod:`soft_rom.predictor.thresholds`).
    """
    eps = list(episodes)
    if not eps:
        raise ConfigError('held_out_errors needs at least one training episode.')
    pairs: list[tuple[Array, Array]] = []
    if len(eps) >= 2:
        for i, ep in enumerate(eps):
            model = fit(eps[:i] + eps[i + 1:])
            pairs.append((np.asarray(ep.Y), predict(model, ep)))
        data = (f'each of {", ".join(e.name for e in eps)} left out in turn, predicted by the '
                'model fitted on the others')
    else:
        ep = eps[0]
        k = int(round(ep.n_samples * (1.0 - tail)))
        head = episode_head(ep, k)          # a stored Q stays on disk
        Yh = predict(fit([head]), ep)
        pairs.append((np.asarray(ep.Y)[:, k:], Yh[:, k:]))
        data = (f'the last {tail:.0%} of {ep.name}, predicted by the model fitted on the rest')
    ref = np.asarray(y_ref, dtype=np.float64).reshape(-1, 1)
    se = sum(float(np.sum((Y - Yh) ** 2)) for Y, Yh in pairs)
    sy = sum(float(np.sum(Y ** 2)) for Y, _ in pairs)
    sd = sum(float(np.sum((Y - ref) ** 2)) for Y, _ in pairs)
    return {'deviation_error': relative_error_from_squares(se, sd),
            'absolute_error': relative_error_from_squares(se, sy),
            'data': data, 'samples': int(sum(Y.shape[1] for Y, _ in pairs))}
