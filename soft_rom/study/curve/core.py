"""The learning curve's computation: held-out choices on training episodes, test scores.

For each pressure amplitude (default: the study's 50 kPa, strongly nonlinear, and 5 kPa,
where the eel is within a few per cent of its linearization), the embedded FOM records
``max(sizes)`` training episodes (seed ``seed``) and ``n_test`` test episodes (seed
``seed + 1``), all of ``duration`` seconds. For every training size ``n`` (the first ``n``
training episodes) each method is fitted with its settings chosen **on the training
episodes only** and scored on the fixed test episodes:

* **LOpInf** (linear forces): ``r`` by K-fold held-out error over training episodes;
* **LOpInf cubic**: at the same ``r``, the fit pipeline's one held-out selection
  (:class:`~soft_rom.pipeline.cubic.HeldOutCubicSelection`, what ``soft-rom fit --forces
  cubic|auto`` runs) on the same folds: the best ``(reg, eps4)``, scored on the tests, and
  its verdict (what ``--forces auto`` keeps: cubic only from 4 folds on and when clearly
  better than linear held out);
* **DMDc** (paper and stable variants): ``r`` by the same folds;
* **ERA/OKID**, which fits one episode: on one episode of the same total duration
  ``n * duration`` (the first part of a long episode recorded with seed ``seed + 2``), its
  settings chosen by its own blocked cross-validation on that episode.

The test episodes reach the study only through :func:`score`: no fit, basis or selection
sees them. The summary holds every held-out table, the chosen settings, the test errors per
episode and method, the FOM's distance to its linearization at each amplitude, whether every
cubic model stays bounded on inputs ten times longer than a training episode, and the run
time and peak memory of each stage.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
import logging
import math
import time
from typing import Any, cast

import numpy as np

from soft_rom.data import Episode
from soft_rom.errors import ConfigError, SoftRomError
from soft_rom.learners.lopinf import LOpInf
from soft_rom.metrics import relative_deviation_error
from soft_rom.models import LinearROM
from soft_rom.pipeline import FitSettings, HeldOutCubicSelection, make_learner, replace_learner
from soft_rom.pipeline.cubic import CUBIC_GRID, FOLDS, MARGIN
from soft_rom.study.curve.select import _tied_pick, folds_of, held_out, Reduction

__all__ = ['CUBIC_GRID', 'CurveConfig', 'CurveData', 'METHODS', 'folds_of', 'held_out',
           'learning_curve', 'score']

LOG = logging.getLogger(__name__)

#: Methods of the curve, in plotting order.
METHODS = ('lopinf', 'lopinf_cubic', 'dmdc', 'dmdc_stable', 'era')

@dataclass(frozen=True)
class CurveConfig:
    """What the learning-curve study runs.

    Parameters
    ----------
    sizes : tuple of int
        Numbers of training episodes (each a prefix of the next: nested training sets).
    n_test : int
        Test episodes (seed ``seed + 1``), the same for every size.
    amplitudes : tuple of float
        Pressure amplitudes (Pa) of the random sequences, one curve each.
    duration, dt : float
        Episode length and time step (s).
    seed : int
        Seed of the training episodes; the test episodes use ``seed + 1``, ERA/OKID's long
        episode ``seed + 2``.
    resolution : int
        Mesh resolution of the eel.
    storage : str
        Bag storage.
    jobs : int
        Processes that simulate episodes.
    methods : tuple of str
        Subset of :data:`METHODS`.
    r_lopinf : tuple of int
        Candidate ``r`` of LOpInf (the cubic model is fitted at the ``r`` chosen for it).
    r_dmdc : tuple of int
        Candidate ``r`` of both DMDc variants.
    folds : int
        Held-out folds over the training episodes (at most ``n``; interleaved groups).
    cubic_grid : tuple of (float, float)
        Candidate ``(reg, eps4)`` of the cubic LOpInf (default the selection's,
        :data:`~soft_rom.pipeline.cubic.CUBIC_GRID`).
    dmdc_coordinates : int
        DMDc runs on this many POD coordinates of the training states (its SVDs then have
        this many rows instead of the full state's; the POD keeps the modes DMDc keeps).
    long_factor : int
        Cubic models are simulated on inputs this many times longer than a training
        episode (test inputs chained) to check they stay bounded.
    auto_margin : float
        ``forces='auto'`` keeps the cubic model only when its held-out error is at most
        ``1 - auto_margin`` times the linear model's (and there are 4 folds or more;
        :mod:`soft_rom.pipeline.cubic` says why).
    """

    sizes: tuple[int, ...] = (2, 4, 8, 16)
    n_test: int = 4
    amplitudes: tuple[float, ...] = (50e3, 5e3)
    duration: float = 2.0
    dt: float = 1e-3
    seed: int = 0
    resolution: int = 1
    storage: str = 'mcap'
    jobs: int = 2
    methods: tuple[str, ...] = METHODS
    r_lopinf: tuple[int, ...] = (4, 6, 8, 10)
    r_dmdc: tuple[int, ...] = (2, 4, 6, 8, 10, 12)
    folds: int = FOLDS
    cubic_grid: tuple[tuple[float, float], ...] = CUBIC_GRID
    dmdc_coordinates: int = 40
    long_factor: int = 10
    auto_margin: float = MARGIN

    def __post_init__(self) -> None:
        if not self.sizes or min(self.sizes) < 1 or list(self.sizes) != sorted(set(self.sizes)):
            raise ConfigError(f'sizes must be increasing positive episode counts; got '
                              f'{self.sizes}.')
        if self.n_test < 1:
            raise ConfigError(f'n_test must be at least 1; got {self.n_test}.')
        if not self.amplitudes or min(self.amplitudes) <= 0:
            raise ConfigError(f'amplitudes must be positive (Pa); got {self.amplitudes}.')
        unknown = set(self.methods) - set(METHODS)
        if unknown or not self.methods:
            raise ConfigError(f'methods must be among {", ".join(METHODS)}; got '
                              f'{sorted(unknown) or "none"}.')
        if self.folds < 2:
            raise ConfigError(f'folds must be at least 2; got {self.folds}.')


@dataclass
class CurveData:
    """The episodes of one amplitude: training (nested prefixes), test, and ERA's long one.

    Attributes
    ----------
    train : list of Episode
        With full states ``Q`` (in memory or lazy).
    test : list of Episode
        Inputs and outputs are all :func:`score` reads.
    q_ref : ndarray, shape (n,)
    y_ref : ndarray, shape (p,)
    long : Episode, optional
        One episode at least ``max(sizes) * duration`` long, for ERA/OKID.
    """

    train: list[Episode]
    test: list[Episode]
    q_ref: np.ndarray
    y_ref: np.ndarray
    long: Episode | None = None
    info: dict[str, Any] = field(default_factory=dict)


def score(model: LinearROM, episodes: Sequence[Episode], y_ref: np.ndarray) -> list[float]:
    """Relative deviation error of ``model`` on each episode (``inf`` when it fails)."""
    from soft_rom.evaluation import predict
    out = []
    for ep in episodes:
        try:
            with np.errstate(all='ignore'):
                Yh = predict(model, ep)
        except (SoftRomError, np.linalg.LinAlgError, FloatingPointError, ValueError):
            out.append(math.inf)
            continue
        e = relative_deviation_error(ep.Y, Yh, y_ref) if np.all(np.isfinite(Yh)) else math.inf
        out.append(float(e) if math.isfinite(e) else math.inf)
    return out


def _long_inputs(model: LinearROM, tests: Sequence[Episode], k_train: int, factor: int,
                 dev_train: float, y_ref: np.ndarray) -> dict[str, Any]:
    """Peak output deviation on ``factor`` x ``k_train`` samples of chained test inputs."""
    k = k_train * factor
    U = np.concatenate([tests[i % len(tests)].U for i in range(-(-k // tests[0].n_samples))],
                       axis=1)[:, :k]
    try:
        with np.errstate(all='ignore'):
            Y = np.asarray(model.simulate(U))
    except (SoftRomError, np.linalg.LinAlgError, FloatingPointError) as err:
        return {'samples': k, 'bounded': False, 'peak_ratio': None,
                'note': f'failed ({type(err).__name__})'}
    peak = float(np.max(np.abs(Y - y_ref[:, None]))) if np.all(np.isfinite(Y)) else math.inf
    ratio = peak / dev_train if dev_train > 0 else math.inf
    return {'samples': k, 'bounded': bool(ratio <= 10.0), 'peak_ratio': ratio}


# ------------------------------------------------------------------------- one size
def _point(data: CurveData, n: int, cfg: CurveConfig) -> dict[str, Any]:
    """Every method fitted on the first ``n`` training episodes, scored on the tests."""
    train = data.train[:n]
    y_ref = data.y_ref
    folds = folds_of(n, cfg.folds)
    t0 = time.perf_counter()
    need_pod = {'lopinf', 'lopinf_cubic', 'dmdc', 'dmdc_stable'} & set(cfg.methods)
    red = (Reduction(train, data.q_ref, y_ref, max(max(cfg.r_lopinf), cfg.dmdc_coordinates))
           if need_pod else None)
    out: dict[str, Any] = {'n': n, 'seconds': {'reduce': time.perf_counter() - t0},
                           'folds': folds}
    if red is not None and {'lopinf', 'lopinf_cubic'} & set(cfg.methods):
        t0 = time.perf_counter()
        table = held_out(lambda idx: red.lopinf(idx, cfg.r_lopinf), train, folds, y_ref)
        r_lin = _tied_pick(table, prefer=lambda r: -r)
        if r_lin is None:
            r_lin = min(cfg.r_lopinf)
        linear = red.lopinf(range(n), [r_lin])[r_lin]
        out['lopinf'] = {'r': r_lin, 'held_out': {str(r): e for r, e in table.items()},
                         'test': score(linear, data.test, y_ref)}
        out['seconds']['lopinf'] = time.perf_counter() - t0
        if 'lopinf_cubic' in cfg.methods:
            t0 = time.perf_counter()
            out['lopinf_cubic'] = _cubic_point(red, data, n, r_lin, linear, cfg)
            out['seconds']['lopinf_cubic'] = time.perf_counter() - t0
    for variant in ('paper', 'stable'):
        key = 'dmdc' if variant == 'paper' else 'dmdc_stable'
        if red is None or key not in cfg.methods:
            continue
        t0 = time.perf_counter()

        def fit_dmdc(idx: list[int], v: str = variant) -> dict[int, LinearROM]:
            try:
                return red.dmdc(idx, cfg.r_dmdc, v, cfg.dmdc_coordinates)
            except (SoftRomError, np.linalg.LinAlgError) as err:
                LOG.info('DMDc %s failed: %s', v, err)
                return {}

        table = held_out(fit_dmdc, train, folds, y_ref)
        r_d = _tied_pick(table, prefer=lambda r: -r)
        models = fit_dmdc(list(range(n))) if r_d is not None else {}
        out[key] = {'r': r_d, 'held_out': {str(r): e for r, e in table.items()},
                    'test': (score(models[r_d], data.test, y_ref) if r_d in models
                             else [math.inf] * len(data.test))}
        out['seconds'][key] = time.perf_counter() - t0
    if 'era' in cfg.methods and data.long is not None:
        t0 = time.perf_counter()
        out['era'] = _era_point(data, n, cfg)
        out['seconds']['era'] = time.perf_counter() - t0
    return out


def _cubic_point(red: Reduction, data: CurveData, n: int, r: int, linear: LinearROM,
                 cfg: CurveConfig) -> dict[str, Any]:
    """The cubic LOpInf at the linear model's ``r``: the CLI's selection, test, fallback."""
    y_ref = data.y_ref
    train = data.train[:n]
    reduced = red.reduced(range(n), r)
    cubic = cast(LOpInf, make_learner('lopinf', FitSettings(forces='cubic'), 'state'))
    selection = HeldOutCubicSelection(cfg.cubic_grid, folds=cfg.folds, margin=cfg.auto_margin)
    verdict = selection.select(reduced, cubic, r)
    pick = verdict.choice
    res: dict[str, Any] = {
        'r': r, 'held_out': verdict.candidates, 'held_out_linear': verdict.linear_error,
        'choice': None, 'forces_auto': verdict.forces, 'reason': verdict.reason(),
        'verdict': verdict.as_dict()}
    lin_test = score(linear, data.test, y_ref)
    model = None
    if pick is not None:
        res['choice'] = pick
        try:
            model = replace_learner(cubic, r=r, cubic_options=verdict.cubic_options).fit(
                reduced).model_
        except (SoftRomError, np.linalg.LinAlgError) as err:
            LOG.info('the chosen cubic fit failed: %s', err)
    if model is None:
        res.update(test=[math.inf] * len(data.test), test_auto=lin_test,
                   ratio=[math.inf] * len(lin_test), ratio_auto=[1.0] * len(lin_test),
                   long_inputs=None, note=('every cubic candidate failed or blew up'
                                           if pick is None else 'the chosen cubic fit failed'))
        return res
    test = score(model, data.test, y_ref)
    keep = verdict.forces == 'cubic'
    res['test'] = test
    res['test_auto'] = test if keep else lin_test
    res['ratio'] = [c / lo if lo > 0 else math.inf for c, lo in zip(test, lin_test)]
    res['ratio_auto'] = [c / lo if lo > 0 else math.inf
                         for c, lo in zip(res['test_auto'], lin_test)]
    dev_train = max(float(np.max(np.abs(ep.Y - y_ref[:, None]))) for ep in train)
    res['long_inputs'] = _long_inputs(model, data.test, train[0].n_samples, cfg.long_factor,
                                      dev_train, y_ref)
    return res


def _era_point(data: CurveData, n: int, cfg: CurveConfig) -> dict[str, Any]:
    """ERA/OKID (its own held-out selection) on one episode of ``n * duration`` seconds."""
    from soft_rom.learners.era import ERAOKID
    assert data.long is not None
    k = sum(ep.n_samples for ep in data.train[:n])
    ep = data.long
    part = Episode(t=ep.t[:k], U=ep.U[:, :k], Y=ep.Y[:, :k], name=f'{ep.name}[:{k}]')
    try:
        era = ERAOKID().fit(part, data.y_ref)
    except (SoftRomError, np.linalg.LinAlgError) as err:
        return {'r': None, 'test': [math.inf] * len(data.test), 'note': str(err),
                'samples': k}
    model = era.model_
    return {'r': int(model.r), 'dt': float(model.dt), 'samples': k,
            'test': score(model, data.test, data.y_ref)}


def learning_curve(data: CurveData, cfg: CurveConfig,
                   tick: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The curve of one amplitude: :func:`_point` for every size of ``cfg``."""
    if max(cfg.sizes) > len(data.train):
        raise ConfigError(f'the largest size ({max(cfg.sizes)}) needs that many training '
                          f'episodes; {len(data.train)} given.')
    if min(cfg.sizes) < 2:
        raise ConfigError('the held-out choices need at least 2 training episodes per size.')
    points = []
    for n in cfg.sizes:
        points.append(_point(data, n, cfg))
        if tick:
            tick(f'n={n}')
    return {'points': points, 'test_names': [ep.name for ep in data.test], **data.info}
