"""``soft-rom fit``: training set -> model files, one per (method, r).

Examples::

    soft-rom fit eel.zarr --method lopinf --r 2:22:2 -o models/
    soft-rom fit eel.zarr --method dmdc --r 12 --episodes ep1,ep2 --t-max 2 -o models/
    soft-rom fit eel.zarr --method era --r 20:40:2 --era-episode ep2 --decimation 5 -o models/

Several ``r`` values in one call reuse the expensive part: the POD basis and projections
(LOpInf), the two SVDs (DMDc), the OKID Markov parameters (ERA).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np

from soft_rom.cli._common import parse_r_list
from soft_rom.data import Episode
from soft_rom.errors import ConfigError, DatasetError
from soft_rom.models import LinearROM

__all__ = ['add_parser', 'fit_models', 'open_training_set', 'run', 'select_episodes']

METHODS = ('lopinf', 'dmdc', 'era')


def _methods(text: str) -> tuple[str, ...]:
    out = tuple(m.strip().lower() for m in text.split(',') if m.strip())
    bad = [m for m in out if m not in METHODS]
    if not out or bad:
        raise argparse.ArgumentTypeError(
            f'--method must be one or more of {", ".join(METHODS)} (comma-separated); '
            f'got {text!r}')
    return out


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``fit``."""
    parser = subparsers.add_parser(
        'fit', help='fit LOpInf / DMDc / ERA-OKID ROMs on a training set',
        description='Fit reduced-order models on a training set and write one model file per '
                    '(method, r), named PREFIX_METHOD_rR.npz. Prints a summary table '
                    '(r, training errors, stability margin, time).')
    parser.add_argument('training_set', metavar='TRAINING_SET',
                        help='training set directory (.zarr) written by soft-rom convert')
    parser.add_argument('--method', type=_methods, default=('lopinf',),
                        help='lopinf, dmdc, era, or several comma-separated (default lopinf)')
    size = parser.add_mutually_exclusive_group()
    size.add_argument('--r', type=parse_r_list, default=None, metavar='R',
                      help='reduced dimension(s): 16, 4,8,16 or START:STOP[:STEP] (inclusive)')
    size.add_argument('--energy', type=float, default=None,
                      help='choose r by POD energy fraction (default 0.95 when --r is not '
                           'given; ERA then uses its Hankel singular value rule)')
    parser.add_argument('--solver', choices=('fast', 'cvxpy'), default='fast',
                        help='LOpInf operator solver (default fast)')
    parser.add_argument('--ddt-order', type=int, choices=(2, 4, 6, 8), default=8,
                        help='finite-difference order for LOpInf derivatives (default 8)')
    parser.add_argument('--episodes', default=None,
                        help='comma-separated episode names to train on (default all)')
    parser.add_argument('--t-max', type=float, default=None,
                        help='train on samples with t - t_start < T_MAX seconds of each episode')
    parser.add_argument('--p', type=int, default=None, dest='dmdc_p',
                        help='DMDc truncation of the SVD of [Q; U] (default r + m)')
    era = parser.add_argument_group('ERA/OKID')
    era.add_argument('--era-episode', default=None,
                     help='the one episode ERA/OKID is fitted on (default the first selected)')
    era.add_argument('--decimation', type=int, default=None,
                     help='fit at DECIMATION x the data sample time (default 5)')
    era.add_argument('--n-markov', type=int, default=None,
                     help='number of Markov parameters in the Hankel matrices (default 100)')
    era.add_argument('--observer-order', type=int, default=None,
                     help='OKID observer order (default: automatic, at most 10)')
    era.add_argument('--output-rank', type=int, default=None,
                     help='identify on this many principal components of the outputs '
                          '(fewer OKID unknowns; e.g. 4 for a centerline)')
    era.add_argument('--okid-rcond', type=float, default=None,
                     help='relative cut-off of the OKID least-squares solve')
    era.add_argument('--hsv-tol', type=float, default=None,
                     help='relative Hankel singular value threshold when r is automatic')
    parser.add_argument('-o', '--output', required=True, metavar='OUTDIR',
                        help='directory for the model files (created if missing)')
    parser.add_argument('--prefix', default=None,
                        help='file-name prefix (default: the training set name, e.g. eel)')
    parser.add_argument('--json', default=None, metavar='FILE',
                        help='also write the summary table as JSON')
    parser.add_argument('--no-progress', action='store_true', help='no progress bar')
    parser.set_defaults(func=run)
    return parser


def open_training_set(path: str | Path) -> Any:
    """Open a training set (:class:`soft_rom.dataset.TrainingSet`); clear error if missing."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f'training set {p} does not exist; create it with '
                                '`soft-rom convert BAG... -o OUT.zarr`.')
    from soft_rom.dataset import TrainingSet
    return TrainingSet.open(p)


def select_episodes(ts: Any, names: str | list[str] | None,
                    t_max: float | None = None) -> list[Episode]:
    """Episodes ``names`` (comma-separated or list; default all), cut at ``t_max`` seconds."""
    available = list(ts.episode_names)
    if names is None:
        wanted = available
    else:
        wanted = [n.strip() for n in (names.split(',') if isinstance(names, str) else names)
                  if n.strip()]
    missing = [n for n in wanted if n not in available]
    if missing:
        raise DatasetError(f'unknown episode(s) {missing} in {getattr(ts, "path", "")}; '
                           f'available: {available}.')
    if not wanted:
        raise DatasetError('no episodes selected.')
    eps = [ts[n] for n in wanted]
    if t_max is not None:
        if t_max <= 0:
            raise ConfigError(f'--t-max must be positive; got {t_max}.')
        eps = [ep.time_slice(None, ep.t[0] + t_max) if ep.n_samples else ep for ep in eps]
        short = [ep.name for ep in eps if ep.n_samples < 3]
        if short:
            raise DatasetError(f'episodes {short} have fewer than 3 samples before t_max = '
                               f'{t_max} s.')
    return eps


def _names(ts: Any) -> dict[str, Any]:
    return dict(input_names=list(ts.input_names), output_names=list(ts.output_names),
                input_units=list(ts.input_units), output_units=list(ts.output_units))


def fit_models(ts: Any, method: str, *, r_values: tuple[int, ...] | None,
               energy: float | None, episodes: list[Episode], provenance: dict[str, Any],
               solver: str = 'fast', ddt_order: int = 8, dmdc_p: int | None = None,
               era_options: dict[str, Any] | None = None,
               progress: bool = True) -> list[tuple[LinearROM, float]]:
    """Fit ``method`` for each r; returns ``[(model, seconds), ...]``.

    The expensive step is shared between the r values (module docstring).
    """
    names = _names(ts)
    out: list[tuple[LinearROM, float]] = []
    bar = _progress(len(r_values) if r_values else 1, f'fit {method}', progress)
    q_ref = getattr(ts, 'q_ref', None)
    y_ref = ts.y_ref
    try:
        if method == 'lopinf':
            from soft_rom.basis import POD, project
            from soft_rom.learners.lopinf import LOpInf
            from soft_rom.learners.lopinf_solvers import CvxpySolver, FastSPDSolver
            _need_states(episodes, 'LOpInf')
            t0 = time.perf_counter()
            q_ref = _q_ref(q_ref, episodes)
            r_max = max(r_values) if r_values else None
            pod = POD(r=r_max, energy=0.95 if energy is None else energy).fit(
                [ep.Q for ep in episodes], q_ref)
            Qhat = [project(ep.Q, pod.basis_, q_ref) for ep in episodes]
            t_basis = time.perf_counter() - t0
            dt = episodes[0].dt
            for r in (r_values or (pod.r_,)):
                t1 = time.perf_counter()
                slv = FastSPDSolver() if solver == 'fast' else CvxpySolver()
                learner = LOpInf(r=r, ddt=ddt_order, solver=slv)
                learner.fit_reduced(
                    [q[:r] for q in Qhat], [ep.U for ep in episodes],
                    [ep.Y for ep in episodes], dt, y_ref, names=[ep.name for ep in episodes],
                    energy_captured=float(pod.energy_[r - 1]),
                    time_ranges=[[float(ep.t[0]), float(ep.t[-1])] for ep in episodes],
                    metadata={'training': provenance,
                              'pod_singular_values': pod.singular_values_[:100].tolist()},
                    **names)
                out.append((learner.model_, t_basis / len(r_values or (1,))
                            + time.perf_counter() - t1))
                bar.update(1)
        elif method == 'dmdc':
            from soft_rom.learners.dmdc import DMDc
            _need_states(episodes, 'DMDc')
            t0 = time.perf_counter()
            r0 = r_values[0] if r_values else None
            learner = DMDc(r=r0, p=dmdc_p, energy=0.95 if energy is None else energy).fit(
                episodes, _q_ref(q_ref, episodes), y_ref, metadata={'training': provenance},
                **names)
            t_svd = time.perf_counter() - t0
            for r in (r_values or (None,)):
                t1 = time.perf_counter()
                model = learner.model_ if r == r0 else learner.model_for(r, dmdc_p)
                out.append((model, t_svd / len(r_values or (1,)) + time.perf_counter() - t1))
                bar.update(1)
        elif method == 'era':
            from soft_rom.learners.era import ERAOKID
            opts = {k: v for k, v in (era_options or {}).items() if v is not None}
            ep_name = opts.pop('episode', None)
            if ep_name is None:
                ep = episodes[0]
                if len(episodes) > 1:
                    print(f'note: ERA/OKID fits one episode; using {ep.name!r} '
                          '(choose with --era-episode).', file=sys.stderr)
            else:
                match = [e for e in episodes if e.name == ep_name]
                if not match:
                    raise DatasetError(f'--era-episode {ep_name!r} is not among the selected '
                                       f'episodes {[e.name for e in episodes]}.')
                ep = match[0]
            t0 = time.perf_counter()
            r0 = r_values[0] if r_values else None
            learner = ERAOKID(r=r0, **opts).fit(
                ep, y_ref, metadata={'training': {**provenance, 'episodes': [ep.name]}},
                **names)
            t_okid = time.perf_counter() - t0
            for r in (r_values or (None,)):
                t1 = time.perf_counter()
                model = learner.model_ if r == r0 else learner.model_for(r)
                out.append((model, t_okid / len(r_values or (1,)) + time.perf_counter() - t1))
                bar.update(1)
        else:  # pragma: no cover - argparse restricts the choices
            raise ConfigError(f'unknown method {method!r}.')
    finally:
        bar.close()
    return out


def _need_states(episodes: list[Episode], what: str) -> None:
    missing = [ep.name for ep in episodes if ep.Q is None]
    if missing:
        raise DatasetError(f'{what} needs full states Q but episodes {missing} have none '
                           '(converted with --no-state?). ERA/OKID needs inputs/outputs only.')


def _q_ref(q_ref: Any, episodes: list[Episode]) -> np.ndarray:
    if q_ref is not None:
        return np.asarray(q_ref, dtype=np.float64)
    return np.asarray(episodes[0].Q[:, 0:1], dtype=np.float64)[:, 0]


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


def run(args: argparse.Namespace) -> int:
    """Execute ``soft-rom fit``."""
    from soft_rom.evaluation import evaluate

    ts = open_training_set(args.training_set)
    episodes = select_episodes(ts, args.episodes, args.t_max)
    outdir = Path(args.output)
    outdir.mkdir(parents=True, exist_ok=True)
    prefix = args.prefix or Path(str(args.training_set).rstrip('/')).stem or 'model'
    provenance = {'training_set': str(Path(args.training_set).resolve()),
                  'episodes': [ep.name for ep in episodes], 't_max': args.t_max,
                  'source': ts.provenance if hasattr(ts, 'provenance') else {}}
    try:
        json.dumps(provenance)
    except TypeError:
        provenance['source'] = str(provenance['source'])
    era_options = {'episode': args.era_episode, 'decimation': args.decimation,
                   'n_markov': args.n_markov, 'observer_order': args.observer_order,
                   'hsv_tol': args.hsv_tol, 'output_rank': args.output_rank,
                   'okid_rcond': args.okid_rcond}
    rows: list[dict[str, Any]] = []
    for method in args.method:
        fitted = fit_models(ts, method, r_values=args.r, energy=args.energy,
                            episodes=episodes, provenance=provenance, solver=args.solver,
                            ddt_order=args.ddt_order, dmdc_p=args.dmdc_p,
                            era_options=era_options, progress=not args.no_progress)
        for model, seconds in fitted:
            path = model.save(outdir / f'{prefix}_{method}_r{model.r}.npz')
            train_eps = episodes
            if method == 'era':
                train_eps = [e for e in episodes
                             if e.name in model.metadata['training']['episodes']]
            ev = evaluate(model, train_eps).get()
            rows.append({'method': method, 'r': model.r, 'dt': model.dt,
                         'train_relative_error': ev['relative_error'],
                         'train_relative_deviation_error': ev['relative_deviation_error'],
                         'stability_margin': model.stability_margin(),
                         'seconds': seconds, 'path': str(path)})
    print(format_table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + '\n')
    return 0


def format_table(rows: list[dict[str, Any]]) -> str:
    """Summary table of :func:`run`."""
    head = f'{"method":<7} {"r":>4} {"dt [s]":>8} {"err":>10} {"dev err":>10} ' \
           f'{"margin":>10} {"time [s]":>9}  file'
    lines = [head, '-' * len(head)]
    for r in rows:
        lines.append(f'{r["method"]:<7} {r["r"]:>4d} {r["dt"]:>8.4g} '
                     f'{r["train_relative_error"]:>10.3e} '
                     f'{r["train_relative_deviation_error"]:>10.3e} '
                     f'{r["stability_margin"]:>10.3e} {r["seconds"]:>9.2f}  '
                     f'{Path(r["path"]).name}')
    return '\n'.join(lines)
