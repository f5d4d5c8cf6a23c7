"""Offline use of the predictor: run it over an episode, compare open loop and Kalman."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import as_signal, Episode, MAX_STEP_RATIO, step_ratio_problem
from soft_rom.errors import DimensionError, SoftRomWarning, warn
from soft_rom.metrics import relative_deviation_error, relative_error
from soft_rom.predictor.config import PredictorConfig
from soft_rom.predictor.core import Predictor
from soft_rom.predictor.loop import Publish

__all__ = ['ReplayResult', 'kalman_vs_open_loop', 'replay_episode']

Array = NDArray[np.float64]

@dataclass(frozen=True)
class ReplayResult:
    """Predictions of a :class:`Predictor` run over an episode.

    Attributes
    ----------
    t : ndarray, shape (k,)
    Y : ndarray, shape (p, k)
        Predicted absolute outputs (before any Kalman correction at each sample).
    errors : ndarray, shape (k,)
        Windowed relative error after each sample (``nan`` without measurements).
    levels : ndarray of int, shape (k,), or None
        Health level after each sample (only with ``track_health``).
    summary : dict
        ``relative_error`` and ``relative_deviation_error`` over the whole episode
        (``nan`` without measurements, for an empty episode, and where the measured
        outputs, or their deviations, are all zero but the predictions are not), counters,
        config.
    """

    t: Array
    Y: Array
    errors: Array
    levels: NDArray[np.int64] | None
    summary: dict[str, Any]


def replay_episode(predictor: Predictor, episode: Episode, *, measured: bool = True,
                   callback: Any = None, track_health: bool = False,
                   t0_ns: int = 0, loop: Any = None,
                   publish: Callable[[Publish, int], Any] | None = None) -> ReplayResult:
    """Run ``predictor`` over an episode's inputs (and measured outputs), sample by sample.

    For each sample ``j``: (clocked stepping: advance to ``t_j``), take ``U[:, j]`` at
    ``t_j``, predict ``ŷ_j``, then (``measured``) hand ``Y[:, j]`` to
    :meth:`Predictor.measure`. With uniform samples at the model's ``dt`` and no Kalman
    filter this equals ``model.simulate(U)``.

    Parameters
    ----------
    predictor : Predictor
        Used as is (call :meth:`Predictor.reset` first for a fresh run).
    episode : Episode
    measured : bool
        Feed the episode's outputs as measurements.
    callback : callable, optional
        ``callback(j, t_j, yhat_j, predictor)`` after each sample (e.g. to write messages).
    track_health : bool
        Record :meth:`Predictor.health` level after each sample (costs ~50 µs a sample).
    t0_ns : int
        Absolute time of ``t = 0`` in nanoseconds (e.g. the recording's epoch start); the
        stamps fed are ``t0_ns + round(t_j * 1e9)``, so the model steps exactly as live.
    loop : RuntimeLoop, optional
        Feed through this loop (around ``predictor``) instead of the bare predictor;
        ``publish(pub, t_ns)`` then receives what is due after each sample, the
        measurement of the sample included (its marker and the error go with it).

    A median step over :data:`~soft_rom.data.MAX_STEP_RATIO` x the model's (or under its
    inverse) warns (:class:`~soft_rom.errors.SoftRomWarning`): times in ms? It is replayed.
    """
    if loop is not None and loop.predictor is not predictor:
        raise ValueError('the loop must run the predictor given.')
    t = np.asarray(episode.t, dtype=np.float64)
    U = as_signal('U', episode.U, rows=predictor.model.n_inputs)
    Y = as_signal('Y', episode.Y, cols=t.size)
    p = predictor.model.n_outputs
    if measured and Y.shape[0] != p:
        raise DimensionError(f'episode {episode.name!r} has {Y.shape[0]} outputs; the model '
                             f'predicts {p}. Check the output mapping/components.')
    k = t.size
    _warn_step_ratio(episode.name, t, predictor.model)
    Yhat = np.empty((p, k))
    errors = np.full(k, np.nan)
    levels = np.zeros(k, dtype=np.int64) if track_health else None
    ybuf = np.empty(p)
    Ut = np.ascontiguousarray(U.T)          # one contiguous row per sample
    Yt = np.ascontiguousarray(Y.T) if measured else None
    stamps = (int(t0_ns) + np.round(t * 1e9).astype(np.int64)).tolist()
    clocked = predictor.config.stepping != 'event'
    for j, (tj, sj) in enumerate(zip(t.tolist(), stamps)):
        if loop is not None:
            errors[j] = _loop_sample(loop, Ut[j], None if Yt is None else Yt[j], sj, clocked,
                                     publish)
            Yhat[:, j] = predictor.output(ybuf)
        else:
            if clocked:
                predictor.advance_to_ns(sj)
            predictor.set_input_ns(Ut[j], sj)
            Yhat[:, j] = predictor.output(ybuf)
            if Yt is not None:
                e = predictor.measure_ns(Yt[j], sj)
                errors[j] = math.nan if e is None else e
        if levels is not None:
            levels[j] = int(predictor.health(sj).level)
        if callback is not None:
            callback(j, tj, Yhat[:, j], predictor)
    rel, dev = _errors(Y, Yhat, predictor.model.y_ref) if measured else (math.nan, math.nan)
    summary: dict[str, Any] = {
        'episode': episode.name,
        'samples': k,
        'relative_error': rel,
        'relative_deviation_error': dev,
        'counters': dict(predictor.counters),
        'config': asdict(predictor.config),
        'model': predictor.info,
    }
    return ReplayResult(t, Yhat, errors, levels, summary)


def _errors(Y: Array, Yhat: Array, y_ref: Array) -> tuple[float, float]:
    """Relative errors, absolute and on deviations.

    Over all-zero outputs (deviations): 0 where matched exactly, else undefined (NaN); an
    empty episode is undefined too (it must not read as a perfect prediction).
    """
    if_zero = 0.0 if Y.size and np.array_equal(Y, Yhat) else math.nan
    return (relative_error(Y, Yhat, if_zero=if_zero),
            relative_deviation_error(Y, Yhat, y_ref, if_zero=if_zero))


def _warn_step_ratio(name: str, t: Array, model: Any) -> None:
    """Warn where the median step is :data:`MAX_STEP_RATIO` off the model's (units?)."""
    d = np.diff(t)
    h = float(np.median(d)) if d.size else 0.0
    problem = step_ratio_problem(name, h, model.dt, getattr(model, 'method', 'the')) \
        if math.isfinite(h) and h > 0 else ''
    if problem:
        warn(f'{problem} Replayed as given: right for data sampled that slowly, wrong for '
             f'times in other units (steps over {MAX_STEP_RATIO:g} x apart).', SoftRomWarning)


def _loop_sample(loop: Any, u: Array, y: Array | None, t_ns: int, clocked: bool,
                 publish: Callable[[Publish, int], Any] | None) -> float:
    """One sample through a runtime loop; returns the windowed error after it."""
    if clocked:
        pub = loop.tick(t_ns)
        if publish is not None and pub:
            publish(pub, t_ns)
    pub = loop.on_array(u, t_ns, t_ns)
    if y is not None:
        after = loop.on_measured(y, t_ns, t_ns)
        pub.outputs.extend(after.outputs)
        if after.centerline is not None and pub.centerline is None:
            pub.centerline = after.centerline
        if pub.centerline is not None:
            pub.measured_points = after.measured_points if after.measured_points is not None \
                else loop.measured_points()
            err = loop.predictor.windowed_error(t_ns)
            pub.error = err if math.isfinite(err) else None
        pub.diagnostics_due = pub.diagnostics_due or after.diagnostics_due
    if publish is not None and pub:
        publish(pub, t_ns)
    return loop.predictor.windowed_error(t_ns)


def kalman_vs_open_loop(model: Any, episode: Episode, *,
                        config: PredictorConfig | None = None,
                        Y_true: ArrayLike | None = None) -> dict[str, float]:
    """Prediction errors of ``model`` on ``episode`` open loop and with the Kalman filter.

    Both runs see the episode's (possibly noisy) outputs as measurements; errors are
    measured against ``Y_true`` (default the episode's outputs) with the prediction taken
    *before* each correction, so the Kalman figure is an honest one-step-ahead error.

    Returns
    -------
    dict
        ``open_loop`` and ``kalman`` relative errors on deviations, ``open_loop_abs`` and
        ``kalman_abs`` absolute relative errors, and ``ratio`` = kalman / open_loop.
    """
    base = PredictorConfig() if config is None else config
    Yt = as_signal('Y_true', episode.Y if Y_true is None else Y_true)
    out: dict[str, float] = {}
    for key, kal in (('open_loop', False), ('kalman', True)):
        cfg = base.replace(kalman=kal, rate_hz=0.0)
        res = replay_episode(Predictor(model, cfg), episode, measured=True)
        out[key], out[f'{key}_abs'] = _errors(Yt, res.Y, model.y_ref)[::-1]
    out['ratio'] = out['kalman'] / out['open_loop'] if out['open_loop'] > 0 else math.nan
    return out

