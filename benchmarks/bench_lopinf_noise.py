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
training part (``train dev.``) and the test part (``test dev.``). The noise is drawn once
(``--seed``) and is the same for every row.

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

    .venv/bin/python benchmarks/bench_lopinf_noise.py [--r 10] [--sigma 5e-4] [--seed 0]
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
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--rows', nargs='+', choices=GROUPS, default=list(GROUPS))
    args = ap.parse_args()

    d = load(args.data, args.zarr)
    t, U, Y, Q, q_ref, y_ref = (d[k] for k in ('t', 'U', 'Y', 'Q', 'q_ref', 'y_ref'))
    dt = float(t[1] - t[0])
    rng = np.random.default_rng(args.seed)
    Qn = Q + args.sigma * rng.standard_normal(Q.shape)
    Yn = Y + args.sigma * rng.standard_normal(Y.shape)
    clean = Episode(t=t, U=U, Y=Y, Q=Q, name='ep1')
    k = int(np.searchsorted(t, T_TRAIN - 1e-12))
    train = {False: clean.slice(0, k),
             True: Episode(t=t, U=U, Y=Yn, Q=Qn, name='ep1').slice(0, k)}
    dev_rms = float(np.sqrt(np.mean((Y - y_ref[:, None]) ** 2)))
    print(f'eel Ep 1: n = {Q.shape[0]}, p = {Y.shape[0]}, m = {U.shape[0]}, dt = {dt:g} s, '
          f'train t < {T_TRAIN} s ({k} samples), test {k * dt:g}-{t[-1] + dt:g} s; r = {args.r}; '
          f'noise sigma = {args.sigma:g} m on Q and Y (seed {args.seed}); RMS output '
          f'deviation {dev_rms:.3g} m')

    results: list[dict[str, Any]] = []
    for label, est, noisy, reg, refine in rows(tuple(args.rows)):
        t0 = time.perf_counter()
        learner = LOpInf(r=args.r, ddt=est, regularization=reg, refine=refine)
        with warnings.catch_warnings():
            warnings.simplefilter('ignore')
            learner.fit(train[noisy], q_ref=q_ref, y_ref=y_ref)
            with np.errstate(all='ignore'):
                Yh = predict(learner.model_, clean)
        seconds = time.perf_counter() - t0
        ok = bool(np.all(np.isfinite(Yh)))
        tr = relative_deviation_error(Y[:, :k], Yh[:, :k], y_ref) if ok else np.inf
        te = relative_deviation_error(Y[:, k:], Yh[:, k:], y_ref) if ok else np.inf
        diag = learner.diagnostics_.get('regularization') or {}
        gamma = diag.get('gamma') if isinstance(diag, dict) else None
        results.append(dict(label=label, noisy=noisy, reg=reg, refine=refine, train=tr,
                            test=te, gamma=gamma, seconds=seconds, est=repr(est)))
        print(f'  fitted {label:45s} noisy={noisy!s:5s} reg={reg!s:5s} refine={refine:12s} '
              f'train {tr:.4g} test {te:.4g} gamma {gamma} ({seconds:.1f} s)', flush=True)

    base = {(r['est'], r['refine']): r['test'] for r in results
            if not r['noisy'] and r['reg'] is None}
    base_plain = {r['est']: r['test'] for r in results
                  if not r['noisy'] and r['reg'] is None and r['refine'] == 'none'}
    print()
    print('| derivatives | refine | noise | regularization | train dev. | test dev. | '
          'test / noise-free |')
    print('|---|---|---|---|---:|---:|---:|')
    for r in results:
        reg = 'none' if r['reg'] is None else (
            f'auto (γ = {r["gamma"]:g})' if isinstance(r['gamma'], (int, float))
            else str(r['reg']))
        ref = base_plain.get(r['est'], np.nan)
        ratio = r['test'] / ref
        also = ''
        if r['refine'] != 'none' and (r['est'], r['refine']) in base:
            also = f' ({r["test"] / base[(r["est"], r["refine"])]:.2f} of refined)'
        print(f'| {r["label"]} | {r["refine"]} | '
              f'{f"{args.sigma * 1e3:g} mm" if r["noisy"] else "none"} | {reg} | '
              f'{r["train"]:.3f} | {r["test"]:.3f} | {ratio:.2f}{also} |')
    print('\nratio: test error over the same estimator\'s noise-free fit without regularization '
          'or refinement; acceptance: noisy + auto <= 1.2')


if __name__ == '__main__':
    main()
