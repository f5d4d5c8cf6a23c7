"""The closed-loop study: the follow-up's experiments 1 and 2 on the embedded eel.

Adibnazari, Sharma et al., *Dynamic Shape Control of Soft Robots Enabled by Data-Driven
Model Reduction* (arXiv 2511.03931) ran MPC on LOpInf, DMDc and ERA models of the eel at a
10 ms control step and tracked (1) feasible references -- the FOM's response to other inputs
-- and (2) a biological travelling wave. Here, with the embedded FOM as the plant
(:func:`soft_rom.control.run_closed_loop`) and every controller built the same way:

* same horizon, bounds (each model's training range: the same data), sensor (120 Hz,
  0.5 mm) and estimator settings;
* the weight (``rate_weight``) chosen once, on a training reference (the FOM's response to
  the training episode's pressures), as the one with the lowest geometric mean tracking
  error over the methods (each method's relative change counts the same);
* experiment 1: references = the FOM's responses to random pressures of a held-out seed
  (episodes 1..n); per reference the closed-loop tracking deviation error and, for
  comparison, the same model's open-loop prediction deviation error on that episode;
* experiment 2: the travelling wave scaled into the robot's reach measured from the
  training data; per method closed loop, the same controller run open loop (its pressures
  planned on the ROM alone, then applied to the FOM), and the part of the wave out of the
  model's reach (the same MPC on the model itself with unbounded pressures);
* the offset-free check: a static bend from the FOM's own steady state; the error after
  1 s relative to the commanded deviation.

The result is a table (``report.md``), figures and ``summary.json``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
import json
import math
from pathlib import Path
import time
from typing import Any
import warnings

import numpy as np

from soft_rom.control.loop import (
    FOMPlant,
    open_loop_plan,
    ROMPlant,
    run_closed_loop,
    Sensor,
    simulate_inputs,
)
from soft_rom.control.mpc import MPCConfig
from soft_rom.control.reference import parse_reference, Reference, step_reference
from soft_rom.errors import UntrustedModelWarning
from soft_rom.metrics import relative_deviation_error

__all__ = ['ControlStudyConfig', 'run_control_study']


@dataclass(frozen=True)
class ControlStudyConfig:
    """What the closed-loop study runs.

    Parameters
    ----------
    duration : float
        Seconds per closed loop (experiments 1 and 2).
    n_references : int
        Feasible references (experiment 1).
    seed : int
        Seed of their random pressures (not a training seed).
    train_seed, train_episode : int
        The training reference that chooses the weight (the training data's seed/episode).
    amplitude : float
        Pressure amplitude of the references' random inputs (Pa).
    rate_weights : tuple of float
        Candidates for the weight.
    wave : str
        The travelling-wave reference (``wave:…``).
    bend : tuple of float
        Pressures (Pa) of the static bend.
    mpc : MPCConfig
        Horizon, step, bounds; ``rate_weight`` is chosen.
    """

    duration: float = 2.0
    n_references: int = 4
    seed: int = 100
    train_seed: int = 0
    train_episode: int = 1
    amplitude: float = 50e3
    rate_weights: tuple[float, ...] = (1e-4, 1e-3, 1e-2)
    wave: str = 'wave:f=2,wavelength=0.8,reach=0.1'
    bend: tuple[float, ...] = (20e3, -20e3, 15e3, -15e3, 10e3, -10e3)
    mpc: MPCConfig = MPCConfig()


_EEL: dict[str, Any] = {}


def _task(args: tuple) -> tuple[float, dict[str, Any], Any]:
    """One closed loop (in a worker process): ``(error, summary, result or None)``."""
    from soft_rom.models import load_model
    from soft_rom.sim import EelModel
    path, t, Y, label, mpc, duration, keep = args
    eel = _EEL.setdefault('eel', EelModel())
    model = load_model(path)
    ref = Reference(t=t, Y=Y, label=label)
    with warnings.catch_warnings():      # an untrusted model: the study says it once
        warnings.simplefilter('ignore', UntrustedModelWarning)
        res = run_closed_loop(model, ref, plant=FOMPlant(model, eel), mpc=mpc, sensor=Sensor(),
                              duration=duration)
    return res.tracking_error(), res.summary(), res if keep else None


def _open_loop_task(args: tuple) -> Any:
    from soft_rom.models import load_model
    from soft_rom.sim import EelModel
    path, t, Y, mpc, duration = args
    eel = _EEL.setdefault('eel', EelModel())
    model = load_model(path)
    with warnings.catch_warnings():
        warnings.simplefilter('ignore', UntrustedModelWarning)
        U = open_loop_plan(model, Reference(t=t, Y=Y), mpc=mpc, duration=duration)
    return simulate_inputs(model, U, eel=eel)


def _feasible(model: Any, eel: Any, seed: int, episode: int, duration: float,
              amplitude: float, horizon: float) -> Reference:
    from soft_rom.sim import random_pressures
    k = int(round((duration + horizon) / 1e-3))
    U = random_pressures(k, 1e-3, seed=seed, episode=episode, amplitude=amplitude)
    Y = simulate_inputs(model, U, eel=eel)
    return Reference(t=np.asarray(np.arange(k) * 1e-3, dtype=np.float64), Y=Y, U=U,
                     label=f'seed {seed} Ep {episode}')


def run_control_study(out: str | Path, models: dict[str, Any],
                      cfg: ControlStudyConfig | None = None, *, jobs: int = 1,
                      log: Callable[[str], None] = print) -> dict[str, Any]:
    """Run the study for ``models`` (``{label: model file}``); writes OUT, returns the summary.

    Every model must have the eel's output layout (``x1..x20``, ``z1..z20``). ``jobs``
    closed loops run at once (spawned worker processes; each loads the model file and its
    FOM).
    """
    from concurrent.futures import ProcessPoolExecutor
    import multiprocessing

    from soft_rom.models import load_model
    from soft_rom.sim import EelModel
    cfg = cfg or ControlStudyConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    eel = EelModel()
    loaded = {k: load_model(p) for k, p in models.items()}
    t_start = time.perf_counter()
    summary: dict[str, Any] = {'config': {
        'duration_s': cfg.duration, 'n_references': cfg.n_references, 'seed': cfg.seed,
        'train_seed': cfg.train_seed, 'train_episode': cfg.train_episode,
        'rate_weights': list(cfg.rate_weights), 'wave': cfg.wave, 'bend_pa': list(cfg.bend),
        'step_s': cfg.mpc.step, 'horizon_s': cfg.mpc.horizon, 'jobs': jobs},
        'models': {k: {'method': m.method, 'r': int(m.r), 'file': str(models[k]),
                       'trust': m.trust_issues()} for k, m in loaded.items()}}
    for k, m in loaded.items():      # said once here; the closed loops' own warnings are not
        if m.trust_issues():
            log(f'  {k}: model NOT TRUSTED ({"; ".join(m.trust_issues())}); controlled all '
                'the same')
    # spawned, not forked: the parent has threads by now (the FOM's solver, the pool's own),
    # and a forked worker can inherit a lock held by one of them and wait on it forever
    pool = ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context(
        'spawn')) if jobs > 1 else None
    st = _Study(out, models, loaded, cfg, eel, log, pool)
    try:
        best, tuning = _choose_weight(st)
        mpc = replace(cfg.mpc, rate_weight=best)
        summary['weight'] = {'chosen_rate_weight': best, 'training_reference_errors': tuning}
        summary['experiment1'] = _feasible_references(st, mpc)
        wave, exp2 = _travelling_wave(st, mpc)
        summary['wave'] = wave
        summary['experiment2'] = exp2
        summary['offset_free'] = _static_bend(st, mpc)
    finally:
        if pool is not None:
            pool.shutdown()
    summary['wall_s'] = time.perf_counter() - t_start
    _figures(out, summary)
    (out / 'summary.json').write_text(json.dumps(_clean(summary), indent=2, allow_nan=False),
                                      encoding='utf-8')
    (out / 'report.md').write_text(_report(summary), encoding='utf-8')
    return summary


@dataclass
class _Study:
    """What the stages of :func:`run_control_study` share: the models, the FOM, the pool."""

    out: Path
    models: dict[str, Any]          # label -> model file
    loaded: dict[str, Any]          # label -> model
    cfg: ControlStudyConfig
    eel: Any
    log: Callable[[str], None]
    pool: Any                       # a process pool, or None: in this process

    @property
    def first(self) -> Any:
        """The first model (references and the wave are built on its outputs)."""
        return next(iter(self.loaded.values()))

    def run_all(self, tasks: list[tuple]) -> list[Any]:
        """Closed loops (:func:`_task`), in the pool if there is one."""
        if self.pool is None:
            return [_task(t) for t in tasks]
        return list(self.pool.map(_task, tasks))

    def open_loops(self, tasks: list[tuple]) -> list[Any]:
        """Open loops (:func:`_open_loop_task`), in the pool if there is one."""
        if self.pool is None:
            return [_open_loop_task(a) for a in tasks]
        return list(self.pool.map(_open_loop_task, tasks))


def _choose_weight(st: _Study) -> tuple[float, dict[str, dict[str, float]]]:
    """The rate weight, chosen once on a training reference; with every weight's errors."""
    cfg, models = st.cfg, st.models
    train = _feasible(st.first, st.eel, cfg.train_seed, cfg.train_episode, 1.0, cfg.amplitude,
                      cfg.mpc.horizon)
    grid = [(w, lab) for w in cfg.rate_weights for lab in models]
    errs = st.run_all([(str(models[lab]), train.t, train.Y, train.label,
                        replace(cfg.mpc, rate_weight=w), 1.0, False) for w, lab in grid])
    tuning: dict[str, dict[str, float]] = {}
    for (w, lab), (e, _s, _r) in zip(grid, errs):
        tuning.setdefault(f'{w:g}', {})[lab] = e
    for text, row in tuning.items():
        st.log(f'  weight {text} on the training reference: '
               + ', '.join(f'{lab} {v:.3f}' for lab, v in row.items()))
    # the geometric mean: each controller's relative change counts the same (the
    # arithmetic mean follows the controllers with the largest errors only)
    best = min(cfg.rate_weights,
               key=lambda w: float(np.mean(np.log(list(tuning[f'{w:g}'].values())))))
    st.log(f'  chosen weight {best:g}')
    return best, tuning


def _feasible_references(st: _Study, mpc: MPCConfig) -> dict[str, dict[str, Any]]:
    """Experiment 1: feasible references, closed loop against the open-loop prediction."""
    from soft_rom.control.figures import closed_loop_figure
    cfg, models = st.cfg, st.models
    refs = [_feasible(st.first, st.eel, cfg.seed, e, cfg.duration, cfg.amplitude,
                      cfg.mpc.horizon) for e in range(1, cfg.n_references + 1)]
    k = int(round(cfg.duration / 1e-3))
    pairs = [(ref, lab) for ref in refs for lab in models]
    results = st.run_all([(str(models[lab]), ref.t, ref.Y, ref.label, mpc, cfg.duration,
                           ref is refs[0]) for ref, lab in pairs])
    exp1: dict[str, dict[str, Any]] = {lab: {} for lab in models}
    for (ref, lab), (closed, s, res) in zip(pairs, results):
        model = st.loaded[lab]
        U = ref.U if ref.U is not None else np.zeros((model.n_inputs, ref.t.size))
        open_loop = relative_deviation_error(ref.Y[:, :k], model.simulate(U[:, :k]),
                                             model.y_ref)
        exp1[lab][ref.label] = {'closed_loop': closed, 'open_loop_prediction': open_loop,
                                'ratio': closed / open_loop,
                                'solve_p99_ms': s['solve']['p99_ms'],
                                'saturated_fraction': s['saturated_fraction']}
        st.log(f'  {lab} on {ref.label}: closed loop {closed:.3f}, open-loop prediction '
               f'{open_loop:.3f} (ratio {closed / open_loop:.2f})')
        if res is not None:
            closed_loop_figure(st.out / f'feasible_{_slug(lab)}.png', res,
                               list(model.output_names),
                               title=f'{lab}: feasible reference {ref.label}')
    return exp1


def _travelling_wave(st: _Study, mpc: MPCConfig) -> tuple[str, dict[str, Any]]:
    """Experiment 2: the travelling wave, closed loop and open loop applied; its label."""
    from soft_rom.control.figures import closed_loop_figure
    cfg, models = st.cfg, st.models
    wave = parse_reference(cfg.wave, st.first, duration=cfg.duration + cfg.mpc.horizon)
    labels = list(models)
    closed_w = st.run_all([(str(models[lab]), wave.t, wave.Y, wave.label, mpc, cfg.duration,
                            True) for lab in labels])
    Y_ols = st.open_loops([(str(models[lab]), wave.t, wave.Y, mpc, cfg.duration)
                           for lab in labels])
    exp2: dict[str, Any] = {}
    for lab, (closed, s, res), Y_ol in zip(labels, closed_w, Y_ols):
        model = st.loaded[lab]
        ol = relative_deviation_error(wave.at(res.t), Y_ol, model.y_ref)
        floor = _reach_floor(model, wave, mpc, cfg.duration)
        exp2[lab] = {'closed_loop': closed, 'open_loop_applied': ol, 'ratio': closed / ol,
                     'model_floor': floor,
                     'saturated_fraction': s['saturated_fraction'],
                     'solve_p99_ms': s['solve']['p99_ms']}
        st.log(f'  {lab} on the wave: closed loop {closed:.3f}, open loop applied {ol:.3f} '
               f'(ratio {closed / ol:.2f}), inputs at a bound '
               f'{100 * s["saturated_fraction"]:.0f} %; the same MPC with the model as the '
               f'plant and no input bounds: {floor:.3f}')
        closed_loop_figure(st.out / f'wave_{_slug(lab)}.png', res, list(model.output_names),
                           title=f'{lab}: {wave.label}', open_loop=Y_ol)
    return wave.label, exp2


def _static_bend(st: _Study, mpc: MPCConfig) -> dict[str, Any]:
    """The offset-free check: a static bend from the FOM's own steady state."""
    first, models = st.first, st.models
    bend = step_reference(first, np.array(st.cfg.bend), 2.0, at=0.05, plant=st.eel)
    target = bend.Y[:, -1]
    commanded = float(np.linalg.norm(target - first.y_ref))
    labels = list(models)
    bend_res = st.run_all([(str(models[lab]), bend.t, bend.Y, bend.label, mpc, 2.0, True)
                           for lab in labels])
    offset: dict[str, Any] = {}
    for lab, (_e, _s, res) in zip(labels, bend_res):
        after = res.t >= 1.0
        err = np.linalg.norm(res.Y[:, after] - target[:, None], axis=0) / commanded
        every = np.linalg.norm(res.Y - target[:, None], axis=0) / commanded
        above = np.flatnonzero(every > 0.02)
        within = float(res.t[above[-1] + 1]) if above.size and above[-1] + 1 < res.t.size \
            else (None if above.size else 0.0)
        offset[lab] = {'max_error_after_1s': float(err.max()),
                       'mean_error_after_1s': float(err.mean()),
                       'final_error': float(err[-1]),
                       'within_2pct_from_s': within}
        st.log(f'  {lab} static bend: error after 1 s at most {100 * err.max():.2f} % of the '
               f'commanded deviation (final {100 * err[-1]:.2f} %; '
               + ('not within 2 % by the end' if within is None
                  else f'within 2 % from {within:.2f} s') + ')')
    return {'reference': bend.label, 'commanded_deviation_m': commanded, 'per_model': offset}


def _reach_floor(model: Any, ref: Reference, mpc: MPCConfig, duration: float) -> float:
    """Tracking error of the MPC on its own model with practically unbounded inputs.

    The part of ``ref`` that the model cannot produce with any pressures (its shape is out
    of the model's reach at the reference's frequencies): no controller built on the model
    tracks better, closed loop or open loop.
    """
    free = replace(mpc, u_min=(-1e7,), u_max=(1e7,), rate_max=1e12)
    with warnings.catch_warnings():      # said once by run_control_study
        warnings.simplefilter('ignore', UntrustedModelWarning)
        res = run_closed_loop(model, ref, plant=ROMPlant(model), mpc=free,
                              sensor=Sensor(noise=0.0), duration=duration)
    return res.tracking_error()


def _slug(label: str) -> str:
    return label.replace(' r=', '_r').replace(' ', '_')


def _clean(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _figures(out: Path, s: dict[str, Any]) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    labels = list(s['experiment1'])
    refs = list(next(iter(s['experiment1'].values())))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), constrained_layout=True,
                             gridspec_kw={'width_ratios': [len(refs) + 1, 2.5]})
    ax = axes[0]
    w = 0.8 / len(labels)
    x = np.arange(len(refs))
    for i, lab in enumerate(labels):
        vals = [s['experiment1'][lab][r]['closed_loop'] for r in refs]
        ol = [s['experiment1'][lab][r]['open_loop_prediction'] for r in refs]
        ax.bar(x + i * w, vals, w, label=f'{lab} closed loop', color=f'C{i}')
        ax.scatter(x + i * w, ol, marker='_', s=200, color=f'C{i}', zorder=3)
    ax.set_xticks(x + w * (len(labels) - 1) / 2, refs)
    ax.set_ylabel('tracking deviation error')
    ax.set_yscale('log')
    ax.set_title('Experiment 1: feasible references\n(bars: closed loop; dashes: open-loop '
                 'prediction error of the model)', fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis='y')
    ax = axes[1]
    x = np.arange(len(labels))
    ax.bar(x - 0.2, [s['experiment2'][lab]['closed_loop'] for lab in labels], 0.4,
           label='closed loop', color='C0')
    ax.bar(x + 0.2, [s['experiment2'][lab]['open_loop_applied'] for lab in labels], 0.4,
           label='open loop (planned on the ROM)', color='C7')
    floors = [s['experiment2'][lab].get('model_floor') for lab in labels]
    if all(f is not None for f in floors):
        ax.scatter(x, floors, marker='_', s=900, linewidths=2, color='k', zorder=3,
                   label="out of the model's reach (no loop goes below)")
    ax.set_xticks(x, [lab.replace(' r=', '\nr=') for lab in labels])
    ax.set_ylabel('tracking deviation error')
    ax.set_title('Experiment 2: travelling wave', fontsize=9)
    top = max(max(e['closed_loop'], e['open_loop_applied']) for e in s['experiment2'].values())
    ax.set_ylim(0, 1.35 * top)
    ax.legend(fontsize=7, loc='upper left', markerscale=0.3)
    ax.grid(alpha=0.3, axis='y')
    fig.savefig(out / 'errors.png', dpi=110)
    plt.close(fig)


def _report(s: dict[str, Any]) -> str:
    labels = list(s['experiment1'])
    refs = list(next(iter(s['experiment1'].values())))
    names = ', '.join(f'{k}' + (' (NOT TRUSTED: ' + '; '.join(v['trust']) + ')'
                                 if v.get('trust') else '') for k, v in s['models'].items())
    lines = ['# Closed-loop study on the embedded eel', '',
             f'Controllers: {names}; control step {s["config"]["step_s"] * 1e3:g} ms, horizon '
             f'{s["config"]["horizon_s"]:g} s, rate weight {s["weight"]["chosen_rate_weight"]:g} '
             '(chosen on the training reference), sensor 120 Hz / 0.5 mm.', '',
             '## Experiment 1: feasible references (tracking deviation error)', '',
             '| reference | ' + ' | '.join(f'{lab} closed | {lab} open-loop pred. | ratio'
                                          for lab in labels) + ' |',
             '|---|' + '---|---|---|' * len(labels)]
    for r in refs:
        lines.append(f'| {r} | ' + ' | '.join(
            f'{s["experiment1"][lab][r]["closed_loop"]:.3f} | '
            f'{s["experiment1"][lab][r]["open_loop_prediction"]:.3f} | '
            f'{s["experiment1"][lab][r]["ratio"]:.2f}' for lab in labels) + ' |')
    lines += ['', f'## Experiment 2: {s["wave"]}', '',
              '| controller | closed loop | open loop (planned on the ROM) | ratio | inputs at a '
              "bound | out of the model's reach |", '|---|---|---|---|---|---|']
    for lab in labels:
        e = s['experiment2'][lab]
        lines.append(f'| {lab} | {e["closed_loop"]:.3f} | {e["open_loop_applied"]:.3f} | '
                     f'{e["ratio"]:.2f} | {100 * e["saturated_fraction"]:.0f} % | '
                     f'{e["model_floor"]:.3f} |')
    lines += ['', "Out of the model's reach: the tracking error of the same MPC with the model "
              'itself as the plant and no input bounds (the part of the wave that no pressures '
              'produce in the model; neither loop can track it).']
    lines += ['', f'## Offset-free: {s["offset_free"]["reference"]}', '',
              '| controller | max error after 1 s | final error | within 2 % from |',
              '|---|---|---|---|']
    for lab, v in s['offset_free']['per_model'].items():
        w = v.get('within_2pct_from_s')
        lines.append(f'| {lab} | {100 * v["max_error_after_1s"]:.2f} % | '
                     f'{100 * v["final_error"]:.2f} % | '
                     + ('not within 2 s' if w is None else f'{w:.2f} s') + ' |')
    mean1 = {lab: float(np.mean([s['experiment1'][lab][r]['closed_loop'] for r in refs]))
             for lab in labels}
    lop = [lab for lab in labels if s['models'][lab]['method'] == 'lopinf']
    lines += ['', "## Does the follow-up's ordering (LOpInf best) hold here?", '']
    for lab in lop:
        others = [o for o in labels if o not in lop]
        e1 = all(mean1[lab] < mean1[o] for o in others)
        e2 = all(s['experiment2'][lab]['closed_loop'] < s['experiment2'][o]['closed_loop']
                 for o in others)
        lines.append(f'- {lab}: experiment 1 mean {mean1[lab]:.3f} vs '
                     + ', '.join(f'{o} {mean1[o]:.3f}' for o in others)
                     + f' -> {"holds" if e1 else "does NOT hold"}; experiment 2 '
                     f'{s["experiment2"][lab]["closed_loop"]:.3f} vs '
                     + ', '.join(f'{o} {s["experiment2"][o]["closed_loop"]:.3f}' for o in others)
                     + f' -> {"holds" if e2 else "does NOT hold"}.')
    lines += ['', '![errors](errors.png)', '']
    for lab in labels:
        lines.append(f'![wave {lab}](wave_{_slug(lab)}.png)')
    lines.append('')
    lines.append(f'Wall time {s["wall_s"]:.0f} s.')
    return '\n'.join(lines) + '\n'


def load_models(paths: Sequence[str | Path]) -> dict[str, Path]:
    """``{label: path}`` for model files, labelled ``<method> r=<r>`` (each is loaded once)."""
    from soft_rom.models import load_model
    out: dict[str, Path] = {}
    for p in paths:
        m = load_model(p)
        out[f'{m.method} r={m.r}'] = Path(p)
    return out
