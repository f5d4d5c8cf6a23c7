"""One pipeline: reduce once, fit a learner, one model per ``r``, metadata finalized in one place.

:func:`fit_models` is what ``soft-rom fit``, the Python API and the studies call:

1. the reducer (:class:`~soft_rom.reduce.InMemoryPOD` or
   :class:`~soft_rom.reduce.StreamingReducer`) reduces the training data once, as the learner
   needs (POD coordinates for LOpInf, snapshot coordinates for DMDc, nothing for ERA/OKID);
2. the learner fits on the reduced data (the expensive part, shared by every ``r``);
3. each ``r`` gets its model from that fit (``model_for``);
4. with ``held_out``, the same learner and orders are fitted again on part of the training
   data, and each model's error on the rest is measured (:func:`held_out_by_order`);
5. :func:`finalize_model` writes what every model file records about its fit.
"""

from __future__ import annotations

from collections.abc import Sequence
import copy
from dataclasses import dataclass, field
import logging
import sys
import time
from typing import Any, Protocol

from soft_rom.errors import ConfigError
from soft_rom.learners.registry import Learner
from soft_rom.models import LinearROM
from soft_rom.models.labels import model_kind, model_label, model_stem
from soft_rom.reduce import InMemoryPOD, ReducedData, TrainingData

__all__ = ['FittedModel', 'Reducer', 'finalize_model', 'fit_models', 'for_orders',
           'held_out_by_order']

LOG = logging.getLogger(__name__)


class Reducer(Protocol):
    """What the pipeline needs from a reducer (:mod:`soft_rom.reduce`)."""

    name: str

    def reduce(self, data: TrainingData, *, basis: str = 'pod', r: int | None = None,
               n_coordinates: int | None = None, what: str = 'the POD') -> ReducedData:
        """The reduced data of ``data``."""
        ...


@dataclass
class FittedModel:
    """One fitted model, the seconds it cost, and what the fit table should say about it.

    Attributes
    ----------
    model : LinearROM
    seconds : float
        Its share of the reduction and of the fit, plus its own model time.
    notes : list of str
        Remarks for the fit table (e.g. a cubic model that fell back to linear forces).
    data_dt : float
        The training data's sample time (a model at another step is named with its step).
    learner : object
        The fitted learner the model came from (for companions: another variant, another r).
    """

    model: LinearROM
    seconds: float
    notes: list[str] = field(default_factory=list)
    data_dt: float | None = None
    learner: Any = None

    @property
    def label(self) -> str:
        """``'LOpInf cubic r=4'``, ``'DMDc stable r=8'``, ... (:func:`model_label`)."""
        return model_label(self.model, data_dt=self.data_dt)

    @property
    def stem(self) -> str:
        """File-name stem: ``'lopinf_cubic_r4'``, ``'dmdc-stable_r8'``, ..."""
        return model_stem(self.model, data_dt=self.data_dt)


def for_orders(learner: Learner, r_values: Sequence[int] | None) -> Learner:
    """A copy of ``learner`` set up to serve every order of ``r_values`` from one fit.

    LOpInf fits the largest ``r`` (the smaller ones reuse its leading coordinates); DMDc and
    ERA/OKID fit the first and realize the others from the same factors; ERA/OKID also gets
    the whole list (``orders``), so that its decimation serves them all.
    """
    out = copy.copy(learner)
    if not r_values:
        return out
    rs = [int(r) for r in r_values]
    if any(r < 1 for r in rs):
        raise ConfigError(f'--r values must be positive integers; got {rs}.')
    if learner.method == 'lopinf':
        out.r = max(rs)
    else:
        out.r = rs[0]
    if hasattr(out, 'orders'):
        out.orders = tuple(rs)
    return out


def fit_models(data: TrainingData, learner: Learner, r_values: Sequence[int] | None = None,
               reducer: Reducer | None = None, *, progress: bool = False,
               layout: dict[str, Any] | None = None,
               extra: dict[str, Any] | None = None,
               held_out: bool = False) -> list[FittedModel]:
    """Reduce ``data`` once, fit ``learner`` on it, and return one model per ``r``.

    Parameters
    ----------
    data : TrainingData
        The training episodes and references (:func:`~soft_rom.pipeline.open_training_data`).
    learner : LOpInf, DMDc or ERAOKID
        A configured learner (:func:`~soft_rom.pipeline.make_learner` builds one with the
        defaults of ``soft-rom fit``); it is copied, not changed.
    r_values : sequence of int, optional
        The orders; default the learner's own rule (POD energy, Hankel singular values).
    reducer : InMemoryPOD or StreamingReducer, optional
        Default :class:`~soft_rom.reduce.InMemoryPOD`.
    progress : bool
        A progress bar on stderr (several ``r``).
    layout : dict, optional
        The training set's output layout, recorded in every model.
    extra : dict, optional
        More metadata for every model.
    held_out : bool
        Also record each model's error on training data it was not fitted on
        (``metadata['held_out']``, the predictor's monitor thresholds;
        :func:`held_out_by_order`).

    Returns
    -------
    list of FittedModel
    """
    reducer = reducer if reducer is not None else InMemoryPOD()
    rs = tuple(int(r) for r in r_values) if r_values else None
    fitter = for_orders(learner, rs)
    r_max = max(rs) if rs else None
    m = data.episodes[0].U.shape[0]
    t0 = time.perf_counter()
    reduced = reducer.reduce(data, basis=fitter.reduction, r=r_max if
                             fitter.reduction == 'pod' else None,
                             n_coordinates=fitter.coordinates_needed(r_max, m),
                             what=_NAMES.get(fitter.method, fitter.method))
    fitter.fit(reduced)
    shared = time.perf_counter() - t0
    out: list[FittedModel] = []
    bar = _progress(len(rs) if rs else 1, f'fit {fitter.method}', progress)
    try:
        for r in (rs or (None,)):
            t1 = time.perf_counter()
            model = fitter.model_ if r is None or r == fitter.r else fitter.model_for(r)
            seconds = shared / len(rs or (1,)) + time.perf_counter() - t1
            out.append(FittedModel(model, seconds, data_dt=reduced.dt, learner=fitter))
            bar.update(1)
    finally:
        bar.close()
    held = (held_out_by_order(data, learner, out, reducer) if held_out
            else [None] * len(out))
    for fitted, errors in zip(out, held):
        finalize_model(fitted.model, reduced, reducer, layout=layout, extra=extra,
                       held_out=errors)
    return out


def held_out_by_order(data: TrainingData, learner: Learner, fitted: Sequence[FittedModel],
                      reducer: Reducer | None = None) -> list[dict[str, Any] | None]:
    """Each model's error on training data it was not fitted on, as the study records it.

    :func:`soft_rom.evaluation.held_out_errors` with the same learner and the same orders:
    with two or more training episodes each is left out in turn, with one (ERA/OKID fits
    one) its last fifth is predicted by the model fitted on the rest. The orders share each
    refit, as in :func:`fit_models`. A model whose refit fails gets ``None`` (the monitor's
    default thresholds), logged.
    """
    from soft_rom.evaluation import held_out_errors

    if not fitted:
        return []
    rs = tuple(int(model_kind(f.model)['r']) for f in fitted)
    used = fitted[0].model.metadata.get('training', {}).get('episodes')
    eps = [ep for ep in data.episodes if not used or ep.name in used]
    refits: dict[tuple[tuple[str, int], ...], list[LinearROM] | Exception] = {}

    def refit(subset: Sequence[Any], i: int) -> LinearROM:
        key = tuple((ep.name, ep.n_samples) for ep in subset)
        if key not in refits:             # one refit serves every order (a failure too)
            part = TrainingData(episodes=list(subset), q_ref=data.q_ref, y_ref=data.y_ref,
                                names=data.names)
            try:
                refits[key] = [f.model for f in fit_models(part, learner, rs, reducer)]
            except Exception as err:  # noqa: BLE001 -- raised again for every order below
                refits[key] = err
        done = refits[key]
        if isinstance(done, Exception):
            raise done
        return done[i]

    out: list[dict[str, Any] | None] = []
    for i, f in enumerate(fitted):
        try:
            out.append(held_out_errors(lambda subset, i=i: refit(subset, i), eps, data.y_ref))
        except Exception as err:  # noqa: BLE001 -- no held-out error: the monitor's defaults
            LOG.info('held-out error of %s not recorded: %s', f.label, err)
            out.append(None)
    return out


_NAMES = {'lopinf': 'LOpInf', 'dmdc': 'DMDc', 'era': 'ERA/OKID'}


def finalize_model(model: LinearROM, reduced: ReducedData, reducer: Reducer, *,
                   layout: dict[str, Any] | None = None,
                   extra: dict[str, Any] | None = None,
                   held_out: dict[str, Any] | None = None) -> None:
    """Record in ``model.metadata`` what its file says about the fit: the one place.

    Training provenance (set, episodes, time ranges), the coordinates, the reducer, the
    output layout, the label (method, variant, forces, r), the held-out error
    (:mod:`soft_rom.predictor.thresholds` reads it) and ``extra``.
    """
    meta = model.metadata
    training = dict(reduced.metadata.get('training', {}))
    training.setdefault('episodes', list(reduced.names))
    training.setdefault('time_ranges', reduced.time_ranges)
    meta['training'] = {**training, **meta.get('training', {})}
    meta.setdefault('coordinates', reduced.metadata.get('coordinates', 'state'))
    meta['reducer'] = getattr(reducer, 'name', type(reducer).__name__)
    if 'scale' in reduced.metadata:
        meta['scale'] = dict(reduced.metadata['scale'])
    if layout is not None:
        meta['output_layout'] = layout
    meta['label'] = model_label(model, data_dt=reduced.dt)
    if held_out is not None:
        meta['held_out'] = held_out
    meta.update(extra or {})


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int, desc: str, enabled: bool) -> Any:
    if not enabled or total <= 1:
        return _NoBar()
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover
        return _NoBar()
    return tqdm(total=total, desc=desc, unit='model', file=sys.stderr, leave=False)
