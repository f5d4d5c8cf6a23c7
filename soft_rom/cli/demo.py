"""``soft-rom demo``: the whole chain on the embedded eel in one command."""

from __future__ import annotations

import argparse
from pathlib import Path
import time

from soft_rom.cli.study import add_study_options, study_output

__all__ = ['add_parser', 'run']

# Coarser r grids than ``study`` so that the demo stays within a few minutes on 2 cores.
DEMO_R_LOPINF = (4, 8, 12, 16, 20)
DEMO_R_DMDC = (4, 8, 12, 16, 20)
DEMO_R_ERA = (20, 28, 36)


def add_parser(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        'demo', help='everything on the embedded eel in one command',
        description='Simulate the default eel mesh (6 episodes as bags), convert, fit the three '
                    'methods, evaluate both studies, replay a test bag through the predictor '
                    'core, and write a report.')
    add_study_options(parser, default_output=Path('soft_rom_demo'))
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from soft_rom.study.run import run_study, StudyConfig

    cfg = StudyConfig(resolution=args.resolution, n_episodes=args.episodes, seed=args.seed,
                      storage=args.storage, r_lopinf=DEMO_R_LOPINF, r_dmdc=DEMO_R_DMDC,
                      r_era=DEMO_R_ERA, jobs=args.jobs)
    t0 = time.perf_counter()
    with study_output(args) as out:
        summary = run_study(out, cfg, progress=not args.quiet, replay=True, bag_dir=args.bags)
    elapsed = time.perf_counter() - t0
    print(f'\nsoft-rom demo finished in {elapsed:.0f} s')
    print(f'report: {out / "report.md"} (figures beside it)')
    s1, s2 = summary.get('study1', {}), summary.get('study2', {})
    for method, b in s1.get('best', {}).items():
        print(f'  time extrapolation  {method:7s} r={b["r"]:<3d} train {b["train"]:.4f}  '
              f'test {b["test"]:.4f}  (deviations: {b["train_dev"]:.3f} / {b["test_dev"]:.3f})')
    for method, per_ep in s2.get('test', {}).items():
        errs = '  '.join(f'{ep} {e:.4f}' for ep, e in per_ep.items())
        print(f'  unseen inputs       {method:7s} r={s2["chosen"][method]["r"]:<3d} {errs}')
    if summary.get('replay'):
        print(f'  replay: {summary["replay"]}')
    return 0
