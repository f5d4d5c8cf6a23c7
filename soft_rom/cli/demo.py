"""``soft-rom demo``: the whole chain on the embedded eel in one command."""

from __future__ import annotations

import argparse
from pathlib import Path
import time
from typing import Any

from soft_rom.cli.study import add_study_options, print_failures, print_timings, study_output

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
    with study_output(args, cfg) as out:
        summary = run_study(out, cfg, progress=not args.quiet, replay=True, bag_dir=args.bags)
    elapsed = time.perf_counter() - t0
    print(f'\nsoft-rom demo finished in {elapsed:.0f} s')
    print_timings(summary)
    figures = sorted(p.name for p in Path(out).glob('*.png'))
    print(f'report: {out / "report.md"} ({len(figures)} figures beside it)')
    s1, s2 = summary.get('study1', {}), summary.get('study2', {})
    if s1.get('best'):
        print(f'study 1, time extrapolation (train Ep 1 t < {s1["t_train"]:g} s, test the rest; '
              'the r best on training):')
    for b in s1.get('best', {}).values():
        print(f'  {b.get("label", ""):<18s} train {b["train"]:.4f}  test {b["test"]:.4f}  '
              f'(deviations: {b["train_dev"]:.3f} / {b["test_dev"]:.3f})')
    if s2.get('test'):
        print('study 2, unseen inputs (train Ep 1 + Ep 2; relative output error per test '
              'episode):')
    order = list(s1.get('best', {}))           # study 2 in study 1's order of methods
    tests = s2.get('test', {})
    for method in sorted(tests, key=lambda m: order.index(m) if m in order else len(order)):
        per_ep = tests[method]
        errs = '  '.join(f'{ep} {e:.4f}' for ep, e in per_ep.items())
        print(f'  {s2["chosen"][method].get("label", method):<18s} {errs}')
    if summary.get('replay'):
        print(replay_lines(summary['replay']))
    print_failures(summary)
    return 0


def replay_lines(rep: dict[str, Any]) -> str:
    """What the demo's replay found, in the words the report uses."""
    if 'error' in rep:
        return f'replay: {rep["error"]}'
    lines = [f'replay of {rep["bag"]} through {rep["model"]} (the predictor core, open loop) '
             f'-> {rep["output bag"]}:',
             f'  relative deviation error {rep["relative_deviation_error"]:.3f}; final status '
             f'{rep["final_status"]}: {rep["final_message"]}']
    if 'kalman' in rep:
        k = rep['kalman']
        lines.append(f'  with Kalman correction (measurements with {k["noise_mm"]:g} mm noise): '
                     f'{k["open_loop"]:.3f} -> {k["kalman"]:.3f} (ratio {k["ratio"]:.2f})')
    return '\n'.join(lines)
