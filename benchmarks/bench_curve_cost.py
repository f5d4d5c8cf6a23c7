"""Cost of the cubic LOpInf at the learning curve's largest training set.

The issue's cost targets: the cubic fit at ``r = 10`` on the largest training set (16
episodes of 2 s at 1 ms, the eel at 50 kPa) within 60 s on the 2-core machine, and the
predictor step of such a model within 50 us. Timed A/B in one process: the linear LOpInf fit
on the same reduced coordinates is the baseline of the fit; the predictor step of the linear
model is the baseline of the step. Also timed: the whole held-out verdict of
``soft-rom fit --forces auto`` at that ``r`` (the pipeline's ``HeldOutCubicSelection``: 4
folds x the cubic grid, each candidate simulated on the episodes left out), which is what a
user waits for.

The training set is the study's (``soft-rom study --learning-curve`` writes
``data/50kPa_train.zarr`` in its folder). Run::

    .venv/bin/python benchmarks/bench_curve_cost.py STUDY/data/50kPa_train.zarr \\
        [--episodes 16] [--r 10] [--verdict]
"""

# ruff: noqa: E402  (thread settings must precede the numpy import)
from __future__ import annotations

import os

# The study machine has 2 cores; one BLAS thread keeps the figures comparable under load.
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import argparse
import time

import numpy as np

from soft_rom.dataset import TrainingSet
from soft_rom.errors import SoftRomError
from soft_rom.pipeline import (
    CUBIC_GRID,
    FitSettings,
    HeldOutCubicSelection,
    make_learner,
    replace_learner,
)
from soft_rom.predictor import Predictor
from soft_rom.study.curve.run import _episodes
from soft_rom.study.curve.select import Reduction


def _load() -> str:
    one, five, fifteen = os.getloadavg()
    return f'load average {one:.2f} {five:.2f} {fifteen:.2f} on {os.cpu_count()} cores'


def _step_us(model, u: np.ndarray, n: int = 2000) -> float:
    pred = Predictor(model)
    pred.set_input(u, 0.0)
    for _ in range(200):                        # leave the rest state (real Newton work)
        pred.step()
    best = np.inf
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(n):
            pred.step()
        best = min(best, (time.perf_counter() - t0) / n)
    return best * 1e6


def _along_us(model, U: np.ndarray) -> float:
    """``set_input`` + ``step`` per sample along recorded inputs (a new input every step)."""
    pred = Predictor(model)
    t0 = time.perf_counter()
    for j in range(U.shape[1]):
        pred.set_input(U[:, j], j * model.dt)
        pred.step()
    return (time.perf_counter() - t0) / U.shape[1] * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument('training_set')
    ap.add_argument('--episodes', type=int, default=16)
    ap.add_argument('--r', type=int, default=10)
    ap.add_argument('--verdict', action='store_true',
                    help='also time the held-out verdict of fit --forces auto (the longest '
                         'part: 4 folds x the cubic grid)')
    args = ap.parse_args()
    print(_load())
    t0 = time.perf_counter()
    eps, q_ref, y_ref = _episodes(args.training_set)
    eps = eps[:args.episodes]
    k = sum(ep.n_samples for ep in eps)
    ts = TrainingSet.open(args.training_set)
    print(f'{len(eps)} episodes, {k} samples, state {eps[0].Q.shape[0]}, from '
          f'{ts.path} ({time.perf_counter() - t0:.1f} s to load)')
    assert q_ref is not None
    t0 = time.perf_counter()
    red = Reduction(eps, q_ref, y_ref, args.r)
    print(f'POD r={args.r}: {time.perf_counter() - t0:.1f} s')
    idx = list(range(len(eps)))
    t0 = time.perf_counter()
    lin = red.lopinf(idx, [args.r])[args.r]
    t_lin = time.perf_counter() - t0
    print(f'linear LOpInf fit r={args.r}: {t_lin:.2f} s (baseline)')
    cubic = {}
    learner = make_learner('lopinf', FitSettings(forces='cubic'), 'state')
    reduced = red.reduced(idx, args.r)
    for reg, eps4 in CUBIC_GRID:
        t0 = time.perf_counter()
        c0 = time.process_time()
        fit = replace_learner(learner, r=args.r, cubic_options={'reg': reg, 'eps4': eps4})
        try:
            fitted = {(reg, eps4): fit.fit(reduced).model_}
        except (SoftRomError, np.linalg.LinAlgError):
            fitted = {}
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        status = 'fitted' if fitted else 'failed'
        print(f'cubic LOpInf fit r={args.r} reg={reg:g} eps4={eps4:g}: {wall:.1f} s wall, '
              f'{cpu:.1f} s CPU ({wall / t_lin:.0f}x linear; target <= 60 s) {status}')
        cubic.update(fitted)
    U = eps[0].U
    t_l, a_l = _step_us(lin, U[:, 300]), _along_us(lin, U)
    for key, model in cubic.items():
        t_c, a_c = _step_us(model, U[:, 300]), _along_us(model, U)
        print(f'predictor step r={args.r}, input held: cubic (reg={key[0]:g}) {t_c:.1f} us, '
              f'linear {t_l:.1f} us, ratio {t_c / t_l:.1f}x (target <= 50 us)')
        print(f'set_input + step r={args.r}, a new input every step (episode 1): cubic '
              f'{a_c:.1f} us, linear {a_l:.1f} us, ratio {a_c / a_l:.1f}x')
        break
    if args.verdict:
        t0 = time.perf_counter()
        v = HeldOutCubicSelection().select(reduced, learner, args.r)
        print(f'held-out verdict (fit --forces auto) r={args.r}: '
              f'{time.perf_counter() - t0:.0f} s; ' + ' '.join(v.lines('auto')))
    print(_load())


if __name__ == '__main__':
    from _entry import run
    run(main)
