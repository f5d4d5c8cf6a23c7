"""Study 2's and study 1's fits: sweeps of ``r`` through the pipeline, and the choice of models.

:func:`sweep` fits one method at several ``r`` as ``soft-rom fit`` does, with the study's
settings (:mod:`soft_rom.study.presets`). :func:`_choose_models` picks study 2's ROMs: linear
and cubic LOpInf on one shared POD, and DMDc in a second process when ``jobs`` allows.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
import contextlib
import logging
from pathlib import Path
import time
from typing import Any

import numpy as np

from soft_rom.data import Episode
from soft_rom.errors import ConfigError
from soft_rom.metrics import relative_error
from soft_rom.models import LinearROM
from soft_rom.pipeline import fit_method, FitSettings, open_training_data
from soft_rom.pipeline.data import CHANNEL_KEYS
from soft_rom.pipeline.fit import Reducer
from soft_rom.reduce import episode_head, InMemoryPOD
from soft_rom.study.config import blas_threads, StudyConfig

__all__ = ['HELD_OUT_METHODS', 'sweep']

LOG = logging.getLogger(__name__)


def sweep(method: str, rs: Sequence[int], episodes: Sequence[Episode], ts: Any, *,
          era_options: dict[str, Any] | None = None,
          cubic_options: dict[str, Any] | None = None,
          streaming: bool = False, reducer: Reducer | None = None
          ) -> dict[int, LinearROM]:
    """ROMs of one method for several ``r``: the pipeline of ``soft-rom fit``.

    ``method`` is ``'lopinf'``, ``'dmdc'``, ``'era'`` or ``'lopinf_cubic'`` (LOpInf with cubic
    forces: ``cubic_options`` fixed, or ``None`` for the held-out selection). The expensive
    part is shared: one POD (LOpInf), one pair of SVDs (DMDc), one OKID and Hankel SVD
    (ERA/OKID, one episode). With ``streaming``, the snapshots of the stored episodes (the
    ``episodes`` are their heads) are streamed from disk by
    :class:`~soft_rom.reduce.StreamingReducer` (bounded memory: the paper-scale run);
    otherwise by ``reducer`` (default a new :class:`~soft_rom.reduce.InMemoryPOD`: give one
    with ``share_svd`` to several sweeps of the same episodes and they take one POD).
    """
    era = dict(era_options or {})
    if method == 'era':
        if len(episodes) != 1:
            raise ConfigError('ERA/OKID fits one episode.')
        era['episode'] = episodes[0].name
    cubic = method == 'lopinf_cubic'
    settings = FitSettings(forces='cubic' if cubic else 'linear',
                           cubic_options=cubic_options if cubic else None, era=era,
                           held_out=False)         # recorded for the chosen models only
    provenance = {'training_set': str(getattr(ts, 'path', '')),
                  'time_ranges': [[float(ep.t[0]), float(ep.t[-1])] for ep in episodes]}
    if streaming and method != 'era':
        from soft_rom.reduce import StreamingReducer
        first = ts[episodes[0].name]
        t_max = (None if all(ep.n_samples == ts[ep.name].n_samples for ep in episodes)
                 else float(max(ep.t[-1] for ep in episodes) - first.t[0]
                            + 0.5 * episodes[0].dt))
        data = open_training_data(ts, episodes=[ep.name for ep in episodes], t_max=t_max,
                                  provenance=provenance)
        reducer = StreamingReducer()
    else:
        data = open_training_data(
            list(episodes), q_ref=ts.q_ref, y_ref=ts.y_ref,
            channels={key: getattr(ts, key, None) for key in CHANNEL_KEYS},
            provenance=provenance)
    fitted = fit_method(data, 'lopinf' if cubic else method,
                        tuple(sorted(set(int(r) for r in rs))), settings, reducer,
                        notes=False)
    return {fit.model.r: fit.model for fit in fitted}


def _in_memory(ep: Episode, limit_bytes: float = 2e9) -> Episode:
    """Load a lazy ``Q`` into memory when it is small (the default mesh): fits read it often."""
    if ep.Q is None or isinstance(ep.Q, np.ndarray):
        return ep
    n, k = ep.Q.shape
    if n * k * 8 > limit_bytes:
        return ep
    return Episode(t=ep.t, U=ep.U, Y=ep.Y, Q=np.asarray(ep.Q[:, :], dtype=np.float64),
                   name=ep.name, metadata=ep.metadata)


def _head(ep: Episode, t_stop: float) -> Episode:
    """``ep.time_slice(None, t_stop)`` that keeps a stored ``Q`` on disk (study 1's head)."""
    return episode_head(ep, int(np.searchsorted(ep.t, t_stop - 1e-12, 'left')))


def _predict(model: LinearROM, episode: Episode) -> np.ndarray:
    from soft_rom.evaluation import predict
    return predict(model, episode)


def _choose_models(ts: Any, cfg: StudyConfig, train_eps: list[Episode], tests: list[Episode],
                   tick: Callable[[str], None] | None, fit_seconds: dict[str, float]
                   ) -> tuple[dict[str, dict[str, Any]], dict[str, LinearROM],
                              dict[str, dict[int, LinearROM]], str | None]:
    """Each method's ROM with the lowest training error; ERA/OKID from the better episode.

    ``fit_seconds`` receives each method's fitting time (all its sweeps). Linear and cubic
    LOpInf share one POD. With ``cfg.jobs`` >= 2, DMDc (its sweep and its held-out error,
    more than half of the study's SVD time) runs in a second process beside the others
    (:func:`_dmdc_beside`); its model comes back as a model file, never as a pickle.
    """
    grids = _grids(cfg)
    swept: dict[str, dict[int, LinearROM]] = {}
    chosen: dict[str, dict[str, Any]] = {}
    models: dict[str, LinearROM] = {}
    pod = InMemoryPOD(share_svd=True)
    with _dmdc_beside(ts, cfg, train_eps) as dmdc:
        for method in ('lopinf', 'dmdc', 'lopinf_cubic'):
            if not grids[method] or (method == 'dmdc' and dmdc.running):
                continue
            best = _pick(method, train_eps, ts, cfg, tick, fit_seconds, swept, pod)
            if best is not None:
                chosen[method] = {'r': best[1], 'train': best[0]}
                models[method] = best[2]
        del pod                                    # the shared SVD's memory
        era_candidates = {}
        for ep in train_eps:
            best = _pick('era', [ep], ts, cfg, tick, fit_seconds, swept)
            if best is not None:
                test_err = relative_error(
                    np.concatenate([t.Y for t in tests], axis=1),
                    np.concatenate([_predict(best[2], t) for t in tests], 1))
                era_candidates[ep.name] = (test_err, best)
        if dmdc.running:
            done = dmdc.result(tick)
            if done is not None:
                chosen['dmdc'], models['dmdc'], fit_seconds['dmdc'] = done
    era_episode = None
    if era_candidates:
        era_episode = min(era_candidates, key=lambda k: era_candidates[k][0])
        _e, (e_train, r, model) = era_candidates[era_episode]
        chosen['era'] = {'r': r, 'train': e_train, 'episode': era_episode}
        models['era'] = model
    order = ('lopinf', 'dmdc', 'lopinf_cubic', 'era')      # the figures' and tables' order
    return ({m: chosen[m] for m in order if m in chosen},
            {m: models[m] for m in order if m in models}, swept, era_episode)


def _grids(cfg: StudyConfig) -> dict[str, tuple[int, ...]]:
    return {'lopinf': cfg.r_lopinf, 'dmdc': cfg.r_dmdc, 'era': cfg.r_era,
            'lopinf_cubic': cfg.r_cubic}


def failure_text(method: str, err: BaseException) -> str:
    """Why a study's fit failed, in the study's terms (its ERA preset is not an option)."""
    text = str(err)
    if method == 'era' and '--n-markov' in text:
        text += (' (the study sets the Markov horizon with its ERA/OKID preset, not with '
                 '--n-markov: give it longer training data, a longer --duration or, for study '
                 '1, --t-train)')
    return text


def _pick(method: str, eps: Sequence[Episode], ts: Any, cfg: StudyConfig,
          tick: Callable[[str], None] | None, fit_seconds: dict[str, float],
          swept: dict[str, dict[int, LinearROM]], reducer: Reducer | None = None
          ) -> tuple[float, int, LinearROM] | None:
    """The swept ROM of ``method`` with the lowest training error: (error, r, model)."""
    t0 = time.perf_counter()
    try:
        models = sweep(method, _grids(cfg)[method], eps, ts, era_options=cfg.era_options,
                       cubic_options=cfg.cubic_options, streaming=cfg.streaming,
                       reducer=reducer)
        fit_seconds[method] = fit_seconds.get(method, 0.0) + time.perf_counter() - t0
    except Exception as err:
        LOG.warning('study 2: %s on %s failed: %s', method, [e.name for e in eps],
                    failure_text(method, err))
        return None
    swept[method] = models
    best = None
    Y = np.concatenate([e.Y for e in eps], axis=1)
    for r, model in models.items():
        e = relative_error(Y, np.concatenate([_predict(model, e) for e in eps], axis=1))
        if tick:
            tick(f'{method} r={r}')
        if np.isfinite(e) and (best is None or e < best[0]):
            best = (e, r, model)
    return best


class _DMDcBeside:
    """DMDc of study 2 in a spawned process (:func:`_dmdc_beside`); ``running`` if started."""

    def __init__(self, future: Any, grid: Sequence[int]) -> None:
        self.future, self.grid = future, grid

    @property
    def running(self) -> bool:
        return self.future is not None

    def result(self, tick: Callable[[str], None] | None
               ) -> tuple[dict[str, Any], LinearROM, float] | None:
        """The chosen DMDc (its slot of ``chosen``, the model, the fit seconds), or ``None``."""
        from soft_rom.models import load_model

        done = self.future.result()
        for r in self.grid:
            if tick:
                tick(f'dmdc r={r}')
        if 'error' in done:
            LOG.warning('study 2: dmdc failed: %s', done['error'])
            return None
        model = load_model(done['path'])
        return {'r': done['r'], 'train': done['train']}, model, done['seconds']


@contextlib.contextmanager
def _dmdc_beside(ts: Any, cfg: StudyConfig, train_eps: Sequence[Episode]
                 ) -> Iterator[_DMDcBeside]:
    """Start study 2's DMDc in a second process when ``cfg.jobs`` >= 2 and it pays.

    Spawned, not forked (a fork of a multi-threaded process can inherit a held lock). The
    process opens the training set itself and writes the chosen model to a temporary model
    file. Not started for streamed or on-disk episodes, nor without a DMDc grid.
    """
    path = getattr(ts, 'path', None)
    if (cfg.jobs < 2 or cfg.streaming or not cfg.r_dmdc or path is None
            or not all(isinstance(ep.Q, np.ndarray) for ep in train_eps)):
        yield _DMDcBeside(None, ())
        return
    from concurrent.futures import ProcessPoolExecutor
    import multiprocessing
    import tempfile

    with tempfile.TemporaryDirectory(prefix='soft_rom_study_') as folder, \
            ProcessPoolExecutor(max_workers=1,
                                mp_context=multiprocessing.get_context('spawn')) as pool:
        future = pool.submit(_dmdc_job, str(path), cfg, [ep.name for ep in train_eps],
                             str(Path(folder) / 'dmdc.npz'))
        try:
            yield _DMDcBeside(future, cfg.r_dmdc)
        except BaseException:
            future.cancel()
            raise


def _dmdc_job(path: str, cfg: StudyConfig, names: list[str], out: str) -> dict[str, Any]:
    """The second process: DMDc's sweep, choice and held-out error; the model to ``out``."""
    from soft_rom.dataset import TrainingSet

    with blas_threads(cfg.blas_threads):
        try:
            ts = TrainingSet.open(path)
            eps = [_in_memory(ts[n]) for n in names]
            seconds: dict[str, float] = {}
            best = _pick('dmdc', eps, ts, cfg, None, seconds, {})
            if best is None:
                return {'error': 'no DMDc model (see the warning above)'}
            train, r, model = best
            _record_held_out('dmdc', model, {'r': r}, eps, ts, cfg)
            model.save(out)
        except Exception as err:  # noqa: BLE001 -- reported by the study, as in-process
            return {'error': f'{type(err).__name__}: {err}'}
    return {'r': int(r), 'train': float(train), 'seconds': seconds['dmdc'], 'path': out}


#: Methods whose saved study models record their held-out error (the predictor's monitor
#: thresholds; :func:`soft_rom.evaluation.held_out_errors`). The cubic fit is left out: its
#: conic refits would double its cost.
HELD_OUT_METHODS = ('lopinf', 'dmdc', 'era')


def _record_held_out(method: str, model: LinearROM, chosen: dict[str, Any],
                     train_eps: Sequence[Episode], ts: Any, cfg: StudyConfig) -> None:
    """``model.metadata['held_out']``: the same fit, on held-out training data."""
    from soft_rom.evaluation import held_out_errors

    r = int(chosen['r'])
    eps = [e for e in train_eps if e.name == chosen['episode']] if 'episode' in chosen \
        else list(train_eps)

    def refit(episodes: Sequence[Episode]) -> LinearROM:
        return sweep(method, [r], episodes, ts, era_options=cfg.era_options,
                     cubic_options=cfg.cubic_options, streaming=cfg.streaming)[r]

    try:
        model.metadata['held_out'] = held_out_errors(refit, eps, ts.y_ref)
    except Exception as err:  # noqa: BLE001 -- no held-out error: the monitor's defaults
        LOG.warning('study 2: held-out error of %s r=%d not recorded: %s', method, r, err)
