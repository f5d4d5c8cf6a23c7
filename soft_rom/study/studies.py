"""The paper's two studies: fit through the pipeline, predict, score, plot.

Study 1 (time extrapolation, paper section 3.2): train on Ep 1 up to ``t_train`` = 1.5 s,
test on the rest of Ep 1; errors against ``r``; traces of two outputs.
Study 2 (unseen inputs, paper section 3.3): train on Ep 1 + Ep 2, test on Ep 3 – Ep 6; ROMs
chosen by training error; ERA/OKID from the better single episode; bar chart and centerline
shapes.

Every model comes from :func:`soft_rom.pipeline.fit_method`, the pipeline ``soft-rom fit``
runs, with the study's settings (:mod:`soft_rom.study.presets`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import logging
import math
from pathlib import Path
import time
from typing import Any

import numpy as np

from soft_rom.data import Episode
from soft_rom.errors import DatasetError
from soft_rom.metrics import relative_deviation_error, relative_error
from soft_rom.models import LinearROM
from soft_rom.models.labels import model_label
from soft_rom.study import figures, paper
from soft_rom.study.config import StudyConfig
from soft_rom.study.fits import (
    _choose_models,
    _head,
    _in_memory,
    _predict,
    _record_held_out,
    failure_text,
    HELD_OUT_METHODS,
    sweep,
)

__all__ = ['study_time_extrapolation', 'study_unseen_inputs', 'sweep']

LOG = logging.getLogger(__name__)
METHODS = ('lopinf', 'dmdc', 'era', 'lopinf_cubic')


def _errors(Y: np.ndarray, Yh: np.ndarray, y_ref: np.ndarray) -> tuple[float, float]:
    return relative_error(Y, Yh), relative_deviation_error(Y, Yh, y_ref)


def _layout_index(ts: Any) -> dict[tuple[str, int], int]:
    """``{(component, 0-based point): row}`` from the training set's stored output layout."""
    layout = ts.output_layout
    if layout is None or not {'x', 'z'} <= set(layout.components):
        raise DatasetError(f'{ts.path}: the study needs x and z centerline outputs; the '
                           f'training set has {ts.output_names[:4]}...')
    return dict(layout.index())


def _shape(index: dict[tuple[str, int], int], y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    points = sorted({p for (_c, p) in index})
    x = np.array([y[index[('x', p)]] for p in points])
    z = np.array([y[index[('z', p)]] for p in points])
    return x, z


# ----------------------------------------------------------------------------- studies
def study_time_extrapolation(ts: Any, cfg: StudyConfig, out: Path,
                             tick: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Study 1: fit on Ep 1 up to ``t_train``, test on the rest; errors vs r; traces."""
    ep1 = _in_memory(ts['ep1'])
    train = _head(ep1, cfg.t_train)
    k_train = train.n_samples
    y_ref = ts.y_ref
    curves: dict[str, dict[str, list[float]]] = {}
    predictions: dict[str, dict[int, np.ndarray]] = {}
    labels: dict[tuple[str, int], str] = {}
    grids = {'lopinf': cfg.r_lopinf, 'dmdc': cfg.r_dmdc, 'era': cfg.r_era,
             'lopinf_cubic': cfg.r_cubic}
    for method in METHODS:
        if not grids[method]:
            continue
        c: dict[str, list[Any]] = {k: [] for k in (
            'r', 'train', 'test', 'train_dev', 'test_dev', 'stability_margin', 'fit_seconds')}
        predictions[method] = {}
        t0 = time.perf_counter()
        try:
            models = sweep(method, grids[method], [train], ts,
                           era_options=cfg.era_options, cubic_options=cfg.cubic_options,
                           streaming=cfg.streaming)
        except Exception as err:  # a failed fit is a result to report, not a crash
            LOG.warning('study 1: %s failed: %s', method, failure_text(method, err))
            models = {}
        fit_s = (time.perf_counter() - t0) / max(len(models), 1)
        for r, model in models.items():
            Yh = _predict(model, ep1)
            tr = _errors(ep1.Y[:, :k_train], Yh[:, :k_train], y_ref)
            te = _errors(ep1.Y[:, k_train:], Yh[:, k_train:], y_ref)
            for key, v in zip(('r', 'train', 'test', 'train_dev', 'test_dev', 'stability_margin',
                               'fit_seconds'),
                              (r, tr[0], te[0], tr[1], te[1], model.stability_margin(), fit_s)):
                c[key].append(v)
            predictions[method][r] = Yh
            labels[(method, r)] = _slot_label(method, model)
            if tick:
                tick(f'{method} r={r}')
        curves[method] = c
    best: dict[str, dict[str, Any]] = {}
    for method, c in curves.items():
        if not c['r']:
            continue
        i = int(np.nanargmin(c['train']))
        best[method] = {k: c[k][i] for k in ('r', 'train', 'test', 'train_dev', 'test_dev')}
        best[method]['label'] = labels[(method, int(c['r'][i]))]
    split = (f'Ep 1, trained on t < {cfg.t_train:g} s, tested on {cfg.t_train:g}–'
             f'{float(ep1.t[-1] + ep1.dt):g} s')
    figures.errors_vs_r(out / 'errors_vs_r.png', curves, paper=paper.TIME_EXTRAPOLATION,
                        title=f'Study 1, time extrapolation: {split}; relative output error '
                              '(ours in colour, the paper in grey)', y_max=1.0)
    figures.errors_vs_r(out / 'errors_vs_r_deviation.png',
                        {m: {'r': c['r'], 'train': c['train_dev'], 'test': c['test_dev']}
                         for m, c in curves.items()},
                        metric_label='Relative error on deviations', y_max=10.0,
                        title=f'Study 1, time extrapolation: {split}; relative error on '
                              'deviations from y_ref')
    # The paper's y10 and y20 "at different scales": z of the mid-body point and of the tail.
    names = ts.output_names
    index = _layout_index(ts)
    n_pts = max((p for (_c, p) in index), default=0)
    rows = [index.get(('z', n_pts // 2), min(9, len(names) - 1)),
            index.get(('z', n_pts), min(19, len(names) - 1))]
    figures.output_traces(out / 'traces.png', ep1.t, ep1.Y,
                          {m: predictions[m][int(b['r'])] for m, b in best.items()}, rows,
                          [names[i] for i in rows], t_split=cfg.t_train,
                          rom_labels={m: str(b['label']) for m, b in best.items()},
                          title=f'Study 1, time extrapolation: {split}; mid-body and tail '
                                'height of the FOM and of the ROM of each method with the '
                                'lowest training error')
    return {'t_train': cfg.t_train, 't_end': float(ep1.t[-1] + ep1.dt), 'curves': curves,
            'best': best, 'trace_names': [names[i] for i in rows]}


def study_unseen_inputs(ts: Any, cfg: StudyConfig, out: Path,
                        tick: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Study 2: fit on Ep 1 + Ep 2, test on Ep 3 … Ep N; bars and centerline shapes."""
    train_eps = [_in_memory(ts['ep1']), _in_memory(ts['ep2'])]
    tests = [ts[n] for n in ts.episode_names if n not in ('ep1', 'ep2')]
    y_ref = ts.y_ref
    fit_seconds: dict[str, float] = {}
    chosen, models, swept, era_episode = _choose_models(ts, cfg, train_eps, tests, tick,
                                                        fit_seconds)
    for method, model in models.items():
        chosen[method]['label'] = _slot_label(method, model)
    test: dict[str, dict[str, float]] = {}
    test_dev: dict[str, dict[str, float]] = {}
    preds: dict[str, dict[str, np.ndarray]] = {}
    for method, model in models.items():
        test[method], test_dev[method], preds[method] = {}, {}, {}
        for ep in tests:
            Yh = _predict(model, ep)
            preds[method][ep.name] = Yh
            test[method][ep.name], test_dev[method][ep.name] = _errors(ep.Y, Yh, y_ref)
    labels = {m: c['label'] + (f' (fit on {_ep(c["episode"])})' if 'episode' in c else '')
              for m, c in chosen.items()}
    split = (f'trained on Ep 1 + Ep 2, tested on {_ep(tests[0].name)}–{_ep(tests[-1].name)}'
             if len(tests) > 1 else f'trained on Ep 1 + Ep 2, tested on {_ep(tests[0].name)}')
    figures.error_bars(out / 'bars.png', test, paper=paper.UNSEEN_INPUTS, rom_labels=labels,
                       title=f'Study 2, unseen inputs: {split}; relative output error (black '
                             'ticks: the paper)')
    figures.error_bars(out / 'bars_deviation.png', test_dev, rom_labels=labels,
                       metric_label='Relative error on deviations',
                       title=f'Study 2, unseen inputs: {split}; relative error on deviations '
                             'from y_ref')
    shapes_png = _shapes_figure(ts, cfg, out, tests[0], preds, labels)
    for method, model in models.items():
        if method in HELD_OUT_METHODS and 'held_out' not in model.metadata:
            _record_held_out(method, model, chosen[method], train_eps, ts, cfg)
        model.save(out / 'models' / f'eel_{method}_r{chosen[method]["r"]}.npz')
    result = {'chosen': chosen, 'era_episode': era_episode, 'test': test, 'test_dev': test_dev,
              'shape_episode': tests[0].name, 'shape_times': list(cfg.shape_times),
              'shapes_png': shapes_png, 'fit_seconds': fit_seconds}
    scale = models['lopinf'].metadata.get('scale') if 'lopinf' in models else None
    if scale:                                    # the streamed POD (the paper-scale run)
        result['streaming_pod'] = {k: scale.get(k) for k in ('pod_method', 'passes', 'seconds')}
    if 'lopinf_cubic' in models:
        result['cubic_vs_linear'] = _cubic_vs_linear(models['lopinf_cubic'], swept, tests,
                                                     train_eps, ts, y_ref, cfg.streaming)
        selection = models['lopinf_cubic'].metadata.get('forces_selection')
        if selection is not None:
            result['forces_selection'] = selection
    result['long_inputs'] = {m: _long_inputs(models[m], tests, train_eps, y_ref)
                             for m in ('lopinf', 'lopinf_cubic') if m in models}
    return result


def _shapes_figure(ts: Any, cfg: StudyConfig, out: Path, shape_ep: Episode,
                   preds: dict[str, dict[str, np.ndarray]], labels: dict[str, str]) -> str:
    """The centerline shapes of the first test episode at ``cfg.shape_times``; its file name."""
    index = _layout_index(ts)
    cols = [min(int(round(tt / shape_ep.dt)), shape_ep.n_samples - 1) for tt in cfg.shape_times]
    shapes: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {
        'fom': [_shape(index, shape_ep.Y[:, j]) for j in cols]}
    for method, pred in preds.items():
        shapes[method] = [_shape(index, pred[shape_ep.name][:, j]) for j in cols]
    shapes_png = f'centerline_{shape_ep.name}.png'
    if index:
        figures.centerline_shapes(
            out / shapes_png, cfg.shape_times, shapes, rom_labels=labels,
            title=f'Study 2, unseen inputs: centerline of test episode {_ep(shape_ep.name)} '
                  f'(trained on Ep 1 + Ep 2), FOM and ROMs at t = '
                  f'{", ".join(f"{t:g}" for t in cfg.shape_times)} s')
    return shapes_png


def _ep(name: str) -> str:
    """``'ep3'`` -> ``'Ep 3'`` (the paper's spelling); other names as they are."""
    return f'Ep {name[2:]}' if name.startswith('ep') and name[2:].isdigit() else name


def _cubic_vs_linear(cubic: LinearROM, swept: dict[str, dict[int, LinearROM]],
                     tests: Sequence[Episode], train: Sequence[Episode], ts: Any,
                     y_ref: np.ndarray, streaming: bool = False) -> dict[str, Any]:
    """Deviation errors of the cubic and the linear LOpInf at the same ``r`` per test episode."""
    r = cubic.r
    linear = swept.get('lopinf', {}).get(r)
    if linear is None:
        linear = sweep('lopinf', [r], train, ts, streaming=streaming)[r]
    lin = {ep.name: relative_deviation_error(ep.Y, _predict(linear, ep), y_ref) for ep in tests}
    cub = {ep.name: relative_deviation_error(ep.Y, _predict(cubic, ep), y_ref) for ep in tests}
    ratio = {e: cub[e] / lin[e] if lin[e] > 0 else float('inf') for e in lin}
    return {'r': r, 'linear': lin, 'cubic': cub, 'ratio': ratio,
            'wins': int(sum(v <= 0.5 for v in ratio.values()))}


def _long_inputs(model: LinearROM, tests: Sequence[Episode], train: Sequence[Episode],
                 y_ref: np.ndarray, factor: int = 10) -> str:
    """Whether ``factor`` x a training episode's length of chained test inputs stays bounded."""
    k = train[0].n_samples * factor
    U = np.concatenate([tests[i % len(tests)].U for i in range(-(-k // tests[0].n_samples))],
                       axis=1)[:, :k]
    dev_train = max(float(np.max(np.abs(ep.Y - y_ref[:, None]))) for ep in train)
    try:
        Y = np.asarray(model.simulate(U))
    except Exception as err:      # a failed simulation is the result
        return f'failed ({type(err).__name__})'
    if not np.all(np.isfinite(Y)):
        return 'NOT finite (blow-up)'
    peak = float(np.max(np.abs(Y - y_ref[:, None])))
    verdict = 'bounded' if peak <= 10 * dev_train else 'BLOW-UP'
    return (f'{verdict}: {k} steps, max |y - y_ref| = {peak * 1e3:.1f} mm '
            f'({peak / dev_train:.2f} x the training maximum)')


def _conclusions(s1: dict[str, Any] | None, s2: dict[str, Any] | None) -> list[str]:
    out = []
    if s1 and {'lopinf', 'dmdc'} <= set(s1['best']):
        lo, dm = s1['best']['lopinf'], s1['best']['dmdc']
        verdict = 'holds' if lo['test'] < dm['test'] else 'does NOT hold'
        out.append(f'Time extrapolation, LOpInf vs DMDc (best-on-training ROMs): test error '
                   f'{lo["test"]:.4f} (r={lo["r"]}) vs {dm["test"]:.4f} (r={dm["r"]}); '
                   f'on deviations {lo["test_dev"]:.3f} vs {dm["test_dev"]:.3f}. '
                   f'"LOpInf generalizes better than DMDc" {verdict} here.')
        if 'era' in s1['best']:
            er = s1['best']['era']
            out.append(f'ERA/OKID (r={er["r"]}): train {er["train"]:.4f}, test {er["test"]:.4f} '
                       f'(dev. {er["test_dev"]:.3f}). The paper finds ERA/OKID best on training '
                       f'and LOpInf best on test: here ERA/OKID is '
                       f'{"better" if er["train"] < lo["train"] else "worse"} than LOpInf on '
                       f'training and {"better" if er["test"] < lo["test"] else "worse"} on test.')
    if s2 and s2['test']:
        eps = list(next(iter(s2['test'].values())).keys())
        if {'lopinf', 'dmdc'} <= set(s2['test']):
            wins = sum(s2['test']['lopinf'][e] < s2['test']['dmdc'][e] for e in eps)
            out.append(f'Unseen inputs: LOpInf beats DMDc on {wins} of {len(eps)} test episodes '
                       f'(paper: 4 of 4); mean test error LOpInf '
                       f'{np.mean([s2["test"]["lopinf"][e] for e in eps]):.4f}, DMDc '
                       f'{np.mean([s2["test"]["dmdc"][e] for e in eps]):.4f}.')
        if {'lopinf', 'era'} <= set(s2['test']):
            wins = sum(s2['test']['lopinf'][e] < s2['test']['era'][e] for e in eps)
            out.append(f'Unseen inputs: LOpInf beats ERA/OKID on {wins} of {len(eps)} test '
                       f'episodes (paper: 4 of 4); mean ERA/OKID '
                       f'{np.mean([s2["test"]["era"][e] for e in eps]):.4f}.')
        cub = s2.get('cubic_vs_linear')
        if cub:
            out.append(f'Cubic LOpInf (r={cub["r"]}) vs linear LOpInf at the same r, deviation '
                       f'error ratio per test episode '
                       + ', '.join(f'{e} {v:.2f}' for e, v in cub['ratio'].items())
                       + f': <= 0.5 on {cub["wins"]} of {len(cub["ratio"])} (target: >= 3).')
    return out


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None                      # strict JSON: an error that blew up is null
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _slot_label(method: str, model: Any) -> str:
    """The model's exact label; the cubic slot says when its selection kept linear forces."""
    label = model_label(model)
    if method == 'lopinf_cubic' and 'cubic' not in label.lower():
        label += ' (cubic slot: linear kept)'
    return label
