"""Benchmark: LOpInf on the eel with 0.5 mm measurement noise -- derivatives, regularization.

The acceptance point measured: with white noise of ``--sigma`` (default 0.5 mm) on every
nodal coordinate and every output, ``LOpInf(r, ddt=..., regularization='auto')`` keeps the
deviation test error within 20 % of the noise-free fit (ratio <= 1.2).

Setup (the study's time extrapolation, study 1): Ep 1 of the study's default eel (2 s at
1 ms, 6 pressures, 40 centerline outputs, 5145 nodal coordinates); train on ``t < 1.5 s``,
test on 1.5-2 s. ``LOpInf(r).fit`` does its own POD of the (noisy) training states about the
*clean* reference configuration ``q_ref`` (the body at rest, known) with the clean
``y_ref``. Every fit is simulated from rest on the whole episode's inputs
(:func:`soft_rom.evaluation.predict`, as the study does) and scored with
:func:`soft_rom.metrics.relative_deviation_error` against the *clean* outputs, on the
training part (``train dev.``) and the test part (``test dev.``). The noise is drawn per seed
(``--seeds``, the same draws for every row); noisy rows show the median and range.

Rows: the repository's estimators (``FiniteDifference(8)``, the library default;
``SavitzkyGolay()``, the CLI's ``--ddt savgol`` = window 31, degree 5; ``SavitzkyGolay(41,
4)``, ``--ddt savgol:41:4``) with ``regularization=None`` and ``'auto'``, noise-free and
noisy, and ``refine='output-error'`` on the noisy Savitzky-Golay fits. The ratio column is
the test error over the same estimator's noise-free, unregularized, unrefined fit.

Data: Ep 1 with full states, cached in ``--data`` (default
``/tmp/noise_cache/eel_ep1_full.npz``: ``t``, ``U``, ``Y``, ``Q``, ``q_ref``, ``y_ref``;
never inside the repository). When missing it is read from ``--zarr`` (a training set
converted from the study's default eel, e.g. ``soft-rom study``'s ``data.zarr``) or, without
one, simulated with the study's own pipeline (minutes).

Run::

    .venv/bin/python benchmarks/bench_lopinf_noise.py [--r 10] [--sigma 5e-4] [--seeds 0 1 2]
        [--zarr /tmp/cubic/data.zarr] [--rows fd8 savgol savgol41 refine]

About 2-4 minutes on a loaded 2-core machine (the output-error refinements dominate).
"""

from __future__ import annotations

import argparse
from pathlib import Path
import tempfile
import time
from typing import Any
import warnings

import numpy as np

from soft_rom.data import Episode
from soft_rom.ddt import FiniteDifference, SavitzkyGolay
from soft_rom.evaluation import predict
from soft_rom.learners.lopinf import LOpInf
from soft_rom.metrics import relative_deviation_error

T_TRAIN = 1.5
GROUPS = ('fd8', 'savgol', 'savgol41', 'refine')


# ------------------------------------------------------------------------------ data
def _from_zarr(zarr: Path) -> dict[str, Any]:
    from soft_rom.dataset.reader import TrainingSet
    ts = TrainingSet.open(zarr)
    ep = ts['ep1']
    if ep.Q is None:
        raise SystemExit(f'{zarr}: Ep 1 has no states Q (convert the bags with the state).')
    return {'t': np.asarray(ep.t), 'U': np.asarray(ep.U), 'Y': np.asarray(ep.Y),
            'Q': np.asarray(ep.Q[:, :], dtype=np.float64),
            'q_ref': np.asarray(ts.q_ref, dtype=np.float64),
            'y_ref': np.asarray(ts.y_ref, dtype=np.float64)}


def _simulate() -> dict[str, Any]:
    from soft_rom.convert import convert
    from soft_rom.study.run import simulate_bags, StudyConfig
    work = Path(tempfile.mkdtemp(prefix='noise_eel_'))
    cfg = StudyConfig(n_episodes=2)            # Ep i is seeded by [seed, i]: Ep 1 as the study's
    bags = simulate_bags(work / 'bags', cfg, progress=True)
    convert(bags, work / 'data.zarr', overwrite=True, progress=True)
    print(f'simulated the eel (bags and zarr left in {work})')
    return _from_zarr(work / 'data.zarr')


def load(path: Path, zarr: Path | None) -> dict[str, np.ndarray]:
    """Ep 1 with full states: from the cache, else from ``zarr``, else simulated."""
    if not path.exists():
        t0 = time.perf_counter()
        d = _from_zarr(zarr) if zarr is not None else _simulate()
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, **d)
        print(f'cached Ep 1 in {path} ({time.perf_counter() - t0:.0f} s)')
    with np.load(path) as f:                   # plain arrays only (no pickle)
        return {k: np.asarray(f[k]) for k in f.files}


# ------------------------------------------------------------------------------ runs
def rows(groups: tuple[str, ...]) -> list[tuple[str, Any, bool, str | None, str]]:
    """``(label, estimator, noisy, regularization, refine)`` of the table."""
    ests = {'fd8': ('8th-order FD (library default)', FiniteDifference(8)),
            'savgol': ('Savitzky-Golay 31/5 (`--ddt savgol`)', SavitzkyGolay()),
            'savgol41': ('Savitzky-Golay 41/4 (`--ddt savgol:41:4`)', SavitzkyGolay(41, 4))}
    out: list[tuple[str, Any, bool, str | None, str]] = []
    for g in ('fd8', 'savgol', 'savgol41'):
        if g in groups:
            label, est = ests[g]
            out += [(label, est, False, None, 'none'), (label, est, True, None, 'none'),
                    (label, est, True, 'auto', 'none')]
    if 'refine' in groups:
        for g in ('savgol', 'savgol41'):
            label, est = ests[g]
            out += [(label, est, False, None, 'output-error'),
                    (label, est, True, None, 'output-error'),
                    (label, est, True, 'auto', 'output-error')]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--data', type=Path, default=Path('/tmp/noise_cache/eel_ep1_full.npz'))
    ap.add_argument('--zarr', type=Path, default=None)
    ap.add_argument('--r', type=int, default=10)
    ap.add_argument('--sigma', type=float, default=5e-4, help='noise std in metres')
    ap.add_argument('--seeds', type=int, nargs='+', default=[0, 1, 2])
    ap.add_argument('--rows', nargs='+', choices=GROUPS, default=list(GROUPS))
    args = ap.parse_args()

    d = load(args.data, args.zarr)
    t, U, Y, Q, q_ref, y_ref = (d[k] for k in ('t', 'U', 'Y', 'Q', 'q_ref', 'y_ref'))
    dt = float(t[1] - t[0])
    clean = Episode(t=t, U=U, Y=Y, Q=Q, name='ep1')
    k = int(np.searchsorted(t, T_TRAIN - 1e-12))
    dev_rms = float(np.sqrt(np.mean((Y - y_ref[:, None]) ** 2)))
    print(f'eel Ep 1: n = {Q.shape[0]}, p = {Y.shape[0]}, m = {U.shape[0]}, dt = {dt:g} s, '
          f'train t < {T_TRAIN} s ({k} samples), test {k * dt:g}-{t[-1] + dt:g} s; r = {args.r}; '
          f'noise sigma = {args.sigma:g} m on Q and Y (seeds {args.seeds}); RMS output '
          f'deviation {dev_rms:.3g} m')

    def noisy_train(seed: int) -> Episode:
        rng = np.random.default_rng(seed)
        Qn = Q + args.sigma * rng.standard_normal(Q.shape)
        Yn = Y + args.sigma * rng.standard_normal(Y.shape)
        return Episode(t=t, U=U, Y=Yn, Q=Qn, name='ep1').slice(0, k, name=f'seed {seed}')

    def run(label: str, est: Any, ep: Episode, reg: str | None, refine: str
            ) -> dict[str, Any]:
        t0 = time.perf_counter()
        learner = LOpInf(r=args.r, ddt=est, regularization=reg, refine=refine)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            learner.fit(ep, q_ref=q_ref, y_ref=y_ref)
            with np.errstate(all='ignore'):
                Yh = predict(learner.model_, clean)
        ok = bool(np.all(np.isfinite(Yh)))
        tr = relative_deviation_error(Y[:, :k], Yh[:, :k], y_ref) if ok else np.inf
        te = relative_deviation_error(Y[:, k:], Yh[:, k:], y_ref) if ok else np.inf
        diag = learner.diagnostics_
        gamma = (diag.get('regularization') or {}).get('gamma')
        ref = diag.get('refinement') or {}
        how = (f"{ref.get('status')}, {ref.get('iterations')} it., training sim. error "
               f"-{100 * ref.get('improvement', 0.0):.0f} %" if refine != 'none' else '')
        print(f'  {label:43s} {ep.name:9s} reg={reg!s:5s} refine={refine:12s} '
              f'train {tr:.4g} test {te:.4g} gamma {gamma:g} {how} '
              f'({time.perf_counter() - t0:.1f} s)', flush=True)
        return dict(train=tr, test=te, gamma=gamma)

    table: list[tuple[str, Any, bool, str | None, str, list[dict[str, Any]]]] = []
    for label, est, noisy, reg, refine in rows(tuple(args.rows)):
        if noisy:
            res = []
            for seed in args.seeds:
                ep = noisy_train(seed)
                res.append(run(label, est, ep, reg, refine))
        else:
            ep = clean.slice(0, k, name='clean')
            res = [run(label, est, ep, reg, refine)]
        table.append((label, repr(est), noisy, reg, refine, res))

    base = {est: res[0]['test'] for _l, est, noisy, reg, refine, res in table
            if not noisy and reg is None and refine == 'none'}
    many = len(args.seeds) > 1
    print()
    print('| derivatives | refine | noise | regularization | train dev. | test dev. | '
          'test / noise-free |')
    print('|---|---|---|---|---:|---:|---:|')
    for label, est, noisy, reg, refine, res in table:
        tr = np.array([x['train'] for x in res])
        te = np.array([x['test'] for x in res])
        gam = sorted({float(x['gamma']) for x in res})
        regs = 'none' if reg is None else 'auto (γ = ' + ', '.join(f'{g:g}' for g in gam) + ')'
        ratio = te / base.get(est, np.nan)

        def fmt(a: np.ndarray, digits: str = '.3f') -> str:
            if a.size == 1:
                return f'{a[0]:{digits}}'
            return f'{np.median(a):{digits}} [{a.min():{digits}}–{a.max():{digits}}]'

        print(f'| {label} | {refine} | {f"{args.sigma * 1e3:g} mm" if noisy else "none"} | '
              f'{regs} | {fmt(tr)} | {fmt(te)} | {fmt(ratio, ".2f")} |')
    print("\ntest / noise-free: over the same estimator's noise-free fit without regularization "
          'or refinement' + ('; noisy rows: median [min–max] over the seeds' if many else '')
          + '. Acceptance: noisy + auto <= 1.2.')


if __name__ == '__main__':
    from _entry import run
    run(main)
