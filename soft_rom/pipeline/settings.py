"""The settings of a fit and their defaults: one source for the CLI, the Python API and the study.

:class:`FitSettings` holds every choice ``soft-rom fit`` offers; :func:`make_learner` turns it
into a configured learner, with the defaults that depend on the data:

* coordinates: the full states ``Q`` when every episode has them, else the measured outputs
  (a recording of a real robot);
* LOpInf derivatives: eighth-order differences on states, Savitzky-Golay on (noisy) measured
  outputs;
* LOpInf mass: learned on outputs (``y = T q`` of a mechanical system has a non-symmetric
  stiffness with identity mass), identity on states and with cubic forces;
* LOpInf refinement by the simulation error: on outputs with linear forces (the equation
  error is biased by noise on the coordinates), none on states.

:func:`fit_method` runs one method of ``soft-rom fit``: training data in the chosen
coordinates, the reducer, the learner and, for cubic forces whose settings are not given and
for ``forces='auto'``, the one held-out selection of :mod:`soft_rom.pipeline.cubic`.
"""

from __future__ import annotations

from collections.abc import Sequence
import copy
from dataclasses import dataclass, field, replace
import sys
import time
from typing import Any

from soft_rom.ddt import parse_estimator
from soft_rom.errors import ConfigError
from soft_rom.learners.dmdc import DMDc
from soft_rom.learners.era import ERAOKID
from soft_rom.learners.lopinf import LOpInf
from soft_rom.learners.lopinf.solvers import CvxpySolver, FastSPDSolver
from soft_rom.learners.registry import Learner, learner_class
from soft_rom.pipeline.cubic import HeldOutCubicSelection
from soft_rom.pipeline.data import choose_coordinates, output_coordinates
from soft_rom.pipeline.fit import finalize_model, fit_models, FittedModel, Reducer
from soft_rom.reduce import InMemoryPOD, TrainingData

__all__ = ['FitSettings', 'fit_method', 'make_learner', 'replace_learner']


@dataclass(frozen=True)
class FitSettings:
    """Every choice of a fit (``soft-rom fit`` flags); ``None`` means the default.

    Attributes
    ----------
    energy : float, optional
        POD energy fraction when no ``r`` is given (0.95).
    solver : {'fast', 'cvxpy'}
        LOpInf operator solver (``--solver``).
    ddt : str, optional
        LOpInf derivative estimator (``--ddt``); default ``fd<ddt_order>`` on states,
        ``savgol`` on outputs.
    ddt_order : int
        ``--ddt-order`` (8).
    coordinates : {'state', 'outputs'}, optional
        ``--coordinates``; default states when every episode has them.
    forces : {'linear', 'cubic', 'auto'}
        ``--forces``: ``'cubic'`` fits the best cubic candidate of the held-out selection
        (unless ``cubic_options`` are given), ``'auto'`` keeps linear or cubic forces as the
        selection's verdict says (:mod:`soft_rom.pipeline.cubic`).
    mass, refine : str, optional
        ``--mass``, ``--refine`` (defaults in the module docstring).
    cubic_options : dict, optional
        ``reg`` and ``eps4`` of the cubic forces, fixed; default chosen on held-out training
        data (:class:`~soft_rom.pipeline.cubic.HeldOutCubicSelection`).
    cubic_selection : HeldOutCubicSelection, optional
        The selection used when ``cubic_options`` is not given (default grid and rule).
    lopinf : dict
        More LOpInf keywords (``regularization``, ``min_damping_ratio``).
    dmdc_p : int, optional
        ``--p``.
    dmdc_variant : {'paper', 'stable'}
        ``--dmdc-variant``.
    era : dict
        ERA/OKID keywords (``decimation``, ``n_markov``, ``observer_order``, ``output_rank``,
        ``okid_rcond``, ``okid_ridge``, ``hsv_tol``, ``episode``, ...); ``None`` values are
        the learner's defaults.
    held_out : bool
        Record each model's held-out error (``metadata['held_out']``, from which the
        predictor sets its monitor thresholds): the fit is repeated on part of the training
        data (:func:`~soft_rom.pipeline.fit.held_out_by_order`). In memory only, and not
        for LOpInf with ``forces='auto'`` or cubic forces chosen on held-out data (their
        selection already refits).
    """

    energy: float | None = None
    solver: str = 'fast'
    ddt: str | None = None
    ddt_order: int = 8
    coordinates: str | None = None
    forces: str = 'linear'
    mass: str | None = None
    refine: str | None = None
    cubic_options: dict[str, Any] | None = None
    cubic_selection: HeldOutCubicSelection | None = None
    lopinf: dict[str, Any] = field(default_factory=dict)
    dmdc_p: int | None = None
    dmdc_variant: str = 'paper'
    era: dict[str, Any] = field(default_factory=dict)
    held_out: bool = True


def make_learner(method: str, settings: FitSettings | None = None,
                 coordinates: str = 'state') -> Learner:
    """The learner of ``method`` with ``settings`` and the defaults for ``coordinates``."""
    s = settings or FitSettings()
    cls = learner_class(method)
    energy = 0.95 if s.energy is None else s.energy
    if cls is LOpInf:
        ddt = s.ddt if s.ddt is not None else (
            'savgol' if coordinates == 'outputs' else f'fd{s.ddt_order}')
        linear = s.forces == 'linear'
        mass = s.mass if s.mass is not None else (
            'learned' if coordinates == 'outputs' and linear else 'identity')
        refine = s.refine if s.refine is not None else (
            'output-error' if coordinates == 'outputs' and linear else 'none')
        if mass not in ('identity', 'learned'):
            raise ConfigError(f"--mass must be 'identity' or 'learned'; got {mass!r}.")
        if refine not in ('none', 'output-error') or (refine != 'none' and not linear):
            raise ConfigError(f"--refine must be 'none' or 'output-error' (linear forces "
                              f'only); got {refine!r} with --forces {s.forces}.')
        if s.forces not in ('linear', 'cubic'):
            raise ConfigError(f"--forces must be 'linear', 'cubic' or 'auto'; got "
                              f'{s.forces!r}.')
        if mass == 'learned' and not linear:
            raise ConfigError('--mass learned goes with --forces linear only; drop --mass or '
                              'use --forces linear.')
        solver = FastSPDSolver() if s.solver == 'fast' else CvxpySolver()
        return LOpInf(energy=energy, ddt=parse_estimator(ddt), solver=solver, forces=s.forces,
                      cubic_options=s.cubic_options, mass=mass, refine=refine, **s.lopinf)
    if cls is DMDc:
        return DMDc(p=s.dmdc_p, energy=energy, variant=s.dmdc_variant or 'paper')
    return ERAOKID(**{k: v for k, v in s.era.items() if v is not None})


def fit_method(data: TrainingData, method: str, r_values: Sequence[int] | None,
               settings: FitSettings | None = None, reducer: Reducer | None = None, *,
               layout: dict[str, Any] | None = None, progress: bool = False,
               notes: bool = True) -> list[FittedModel]:
    """Fit ``method`` for each ``r`` as ``soft-rom fit`` does (module docstring).

    Parameters
    ----------
    data : TrainingData
    method : {'lopinf', 'dmdc', 'era'}
    r_values : sequence of int, optional
    settings : FitSettings, optional
    reducer : InMemoryPOD or StreamingReducer, optional
    layout : dict, optional
        The output layout recorded in every model.
    progress : bool
        Progress bars on stderr.
    notes : bool
        Say on stderr which coordinates, derivatives and mass LOpInf uses when not the
        plain defaults.
    """
    s = settings or FitSettings()
    coords = 'state'
    if method in ('lopinf', 'dmdc'):
        coords = choose_coordinates(data.episodes, s.coordinates)
        if coords == 'outputs':
            data = output_coordinates(data)
    data.provenance.setdefault('coordinates', coords)
    selected = method == 'lopinf' and (s.forces == 'auto' or (
        s.forces == 'cubic' and s.cubic_options is None))
    if method == 'lopinf' and s.forces == 'auto' and s.cubic_options is not None:
        raise ConfigError('--cubic-reg and --cubic-eps4 need --forces cubic')
    if selected and s.forces == 'auto':     # the cubic candidates: their own defaults
        learner = make_learner(method, replace(s, forces='cubic', mass=None, refine=None),
                               coords)
    else:
        learner = make_learner(method, s, coords)
    if notes:
        _say_choices(method, learner, coords, s)
    extra = {'coordinates': coords}
    if selected:
        linear = make_learner(method, replace(s, forces='linear'), coords)
        return _fit_selected(data, learner, linear, r_values, s, reducer, layout, extra)
    if method == 'era' and len(data.episodes) > 1 and s.era.get('episode') is None and notes:
        print(f'note: ERA/OKID fits one episode; using {data.episodes[0].name!r} '
              '(choose with --era-episode).', file=sys.stderr)
    held_out = s.held_out and (reducer is None or isinstance(reducer, InMemoryPOD))
    return fit_models(data, learner, r_values, reducer, progress=progress, layout=layout,
                      extra=extra, held_out=held_out)


def _say_choices(method: str, learner: Any, coords: str, s: FitSettings) -> None:
    if coords == 'outputs':
        why = ' (the training set has no Q)' if s.coordinates is None else ''
        how = ''
        if method == 'lopinf':
            how = (f', derivatives by --ddt {learner.ddt}, {learner.mass} mass'
                   + (', refined by output error' if learner.refine != 'none' else ''))
        print(f'note: {method} uses the measured outputs (deviations from y_ref) as its '
              f'coordinates{why}{how}; --coordinates to choose.', file=sys.stderr)
    elif method == 'lopinf' and learner.mass == 'learned':
        print('note: lopinf learns an SPD mass matrix (--mass learned).', file=sys.stderr)


def _fit_selected(data: TrainingData, cubic: Any, linear: Any,
                  r_values: Sequence[int] | None, s: FitSettings, reducer: Reducer | None,
                  layout: dict[str, Any] | None, extra: dict[str, Any]) -> list[FittedModel]:
    """``forces='cubic'`` (the best cubic candidate) or ``'auto'`` (the verdict), per ``r``.

    The verdict of the held-out selection is recorded in ``metadata['forces_selection']``
    (with ``asked`` and ``kept``) and said in the fit table's notes.
    """
    reducer = reducer if reducer is not None else InMemoryPOD()
    selection = s.cubic_selection or HeldOutCubicSelection()
    rs = list(r_values) if r_values else None
    t0 = time.perf_counter()
    reduced = reducer.reduce(data, basis='pod', r=max(rs) if rs else None, what='LOpInf')
    shared = (time.perf_counter() - t0) / len(rs or [1])
    out = []
    for r in rs or [reduced.n_coordinates]:
        t1 = time.perf_counter()
        verdict = selection.select(reduced, cubic, int(r), linear=linear)
        kept = verdict.forces if s.forces == 'auto' else (
            'cubic' if verdict.choice is not None else 'linear')
        final = (replace_learner(cubic, r=int(r), cubic_options=verdict.cubic_options)
                 if kept == 'cubic' else replace_learner(linear, r=int(r)))
        model = final.fit(reduced).model_
        model.metadata['forces_selection'] = {**verdict.as_dict(), 'asked': s.forces,
                                              'kept': kept}
        finalize_model(model, reduced, reducer, layout=layout, extra=extra)
        out.append(FittedModel(model, shared + time.perf_counter() - t1,
                               verdict.lines(s.forces), data_dt=reduced.dt))
    return out


def replace_learner(learner: Any, **changes: Any) -> Any:
    """A copy of ``learner`` with some hyperparameters changed."""
    out = copy.copy(learner)
    for key, value in changes.items():
        setattr(out, key, value)
    return out

