"""Benchmark: the DMDc fit on the eel's snapshots, on their range against the full SVDs.

DMDc takes two thin SVDs of the centred snapshots (``Ω = [Q; U]`` and ``Q'``, paper sec.
2.3). On the default eel they are 5,151 × 3,998 and 5,145 × 3,998 for two 2-s episodes,
and ``soft-rom fit --method dmdc`` takes three fits (the model and the held-out choice of
the order), six such SVDs. The snapshots of a smooth body have a fast-decaying spectrum
(numerical rank 229 of 4,000 at 1e-10), so the learner first finds an orthonormal basis
of their range to 1e-13 relative (:func:`soft_rom.basis.snapshot_range`) and takes
the SVDs on a few hundred coordinates.

The baseline is the same learner with the range step switched off (the full SVDs, as
before), in the same process on the same episodes. The script prints, for the paper and
the stable variants at ``--r``, each side's fit time (best of ``--repeat``, wall and CPU),
the ratio, and how far the two models' outputs are apart on random pressures (relative,
2 s). Episodes: a training set written by ``soft-rom convert`` (``--training-set``), or
``--episodes`` simulated ones of the default eel (seed 0, as ``soft-rom simulate``).

Run::

    .venv/bin/python benchmarks/bench_dmdc.py [--training-set SET.zarr] [--repeat 3]

BLAS threads: one (``OPENBLAS_NUM_THREADS=1`` unless set), as ``soft-rom demo`` runs.
"""

from __future__ import annotations

import argparse
import json
import os

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')

import time  # noqa: E402

import numpy as np  # noqa: E402

import soft_rom.learners.dmdc as dmdc_module  # noqa: E402
from soft_rom.learners.dmdc import DMDc  # noqa: E402


def episodes(args: argparse.Namespace) -> list:
    """The training episodes: from a training set, or simulated (seed 0)."""
    if args.training_set:
        from soft_rom.dataset import TrainingSet
        return TrainingSet.open(args.training_set).episodes()[:args.episodes]
    from soft_rom.sim import EelModel
    from soft_rom.sim.inputs import random_pressures
    eel = EelModel()
    out = []
    for i in range(1, args.episodes + 1):
        U = random_pressures(2000, 1e-3, seed=0, episode=i)
        out.append(eel.simulate(U, 2000, store_states=True).to_episode(f'ep{i}'))
    return out


def timed(eps: list, variant: str, r: int, repeat: int, full: bool) -> tuple[float, float, DMDc]:
    """Best wall and CPU seconds of ``repeat`` fits, and the last learner."""
    real = dmdc_module.snapshot_range
    if full:
        dmdc_module.snapshot_range = lambda arrays, tol: None      # type: ignore[assignment]
    try:
        wall = cpu = np.inf
        for _ in range(repeat):
            c0, t0 = time.process_time(), time.perf_counter()
            learner = DMDc(r=r, variant=variant).fit(eps)
            wall = min(wall, time.perf_counter() - t0)
            cpu = min(cpu, time.process_time() - c0)
    finally:
        dmdc_module.snapshot_range = real
    return wall, cpu, learner


def main() -> None:
    """Run the benchmark and print a table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--training-set', default=None, help='a .zarr of soft-rom convert')
    ap.add_argument('--episodes', type=int, default=2, help='episodes to fit on (default 2)')
    ap.add_argument('--r', type=int, default=12, help="order (default 12, the study's)")
    ap.add_argument('--repeat', type=int, default=3, help='fits per side (best of)')
    ap.add_argument('--json-out', default=None, metavar='FILE',
                    help='also write the figures as JSON')
    args = ap.parse_args()
    if args.episodes < 1 or args.r < 1 or args.repeat < 1:
        ap.error('--episodes, --r and --repeat must be at least 1')
    t0 = time.perf_counter()
    eps = episodes(args)
    n, K = eps[0].Q.shape[0], sum(ep.n_samples for ep in eps)
    print(f'{len(eps)} episodes, n = {n} states, {K} snapshots ({time.perf_counter() - t0:.0f} '
          f's to load); BLAS threads {os.environ["OPENBLAS_NUM_THREADS"]}; load '
          f'{os.getloadavg()[0]:.2f}', flush=True)
    U = np.random.default_rng(1).uniform(-5e4, 5e4, (eps[0].U.shape[0], 2000))
    figures: dict[str, float] = {}
    print(f'{"variant":>8} {"r":>3} {"full SVDs [s]":>14} {"on the range [s]":>17} '
          f'{"cpu full/range [s]":>19} {"ratio":>6} {"outputs apart":>13}')
    for variant in ('paper', 'stable'):
        base = timed(eps, variant, args.r, args.repeat, full=True)
        new = timed(eps, variant, args.r, args.repeat, full=False)
        ya, yb = (side[2].model_.simulate(U) for side in (base, new))
        apart = float(np.linalg.norm(ya - yb) / np.linalg.norm(ya))
        print(f'{variant:>8} {args.r:>3} {base[0]:>14.2f} {new[0]:>17.2f} '
              f'{base[1]:>9.2f}/{new[1]:<9.2f} {base[0] / new[0]:>6.1f} {apart:>13.1e}',
              flush=True)
        figures[f'{variant} full wall'], figures[f'{variant} range wall'] = base[0], new[0]
        figures[f'{variant} apart'] = apart
    print(f'load after: {os.getloadavg()[0]:.2f}')
    if args.json_out:
        with open(args.json_out, 'w', encoding='utf-8') as fh:
            json.dump(figures, fh, indent=1)


if __name__ == '__main__':
    from _entry import run
    run(main)
