"""``soft-rom study``: the paper's two studies end to end on the embedded eel FOM."""

from __future__ import annotations

import argparse
from pathlib import Path

from soft_rom.cli._common import parse_r_list

__all__ = ['add_parser', 'run']


def add_study_options(parser: argparse.ArgumentParser) -> None:
    """Options shared by ``study`` and ``demo``."""
    parser.add_argument('--out', type=Path, default=Path('soft_rom_study'),
                        help='report folder (default: %(default)s)')
    parser.add_argument('--resolution', type=int, default=1,
                        help='eel mesh resolution (1 = fast default; 4 = paper size)')
    parser.add_argument('--episodes', type=int, default=6, help='episodes to simulate (6)')
    parser.add_argument('--seed', type=int, default=0, help='seed of the pressure sequences')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                        help='bag storage format (default: %(default)s)')
    parser.add_argument('--bags', type=Path, default=None,
                        help='reuse (or write) the episode bags in this folder')
    parser.add_argument('--jobs', type=int, default=2,
                        help='processes for simulating episodes (default: %(default)s)')
    parser.add_argument('--no-progress', action='store_true', help='hide progress bars')


def add_parser(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        'study', help="reproduce the paper's two studies (report with figures)",
        description="Simulate the eel FOM, record bags, convert, fit LOpInf / DMDc / ERA-OKID "
                    "over ranges of r, and write a Markdown report with the paper's figures "
                    "(errors vs r, output traces, test-error bars, centerline shapes).")
    add_study_options(parser)
    parser.add_argument('--only', type=int, choices=(1, 2), default=None,
                        help='run only study 1 (time extrapolation) or 2 (unseen inputs)')
    parser.add_argument('--r-lopinf', type=parse_r_list, default=tuple(range(2, 23, 2)),
                        help='r values for LOpInf, e.g. 2:22:2 or 4,8,16 (default 2:22:2)')
    parser.add_argument('--r-dmdc', type=parse_r_list, default=tuple(range(2, 23, 2)),
                        help='r values for DMDc (default 2:22:2)')
    parser.add_argument('--r-era', type=parse_r_list, default=tuple(range(20, 43, 2)),
                        help='r values for ERA/OKID (default 20:42:2)')
    parser.add_argument('--t-train', type=float, default=1.5,
                        help='end of training in study 1, seconds (default 1.5)')
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from soft_rom.study.run import run_study, StudyConfig
    cfg = StudyConfig(resolution=args.resolution, n_episodes=args.episodes, seed=args.seed,
                      storage=args.storage, t_train=args.t_train, r_lopinf=args.r_lopinf,
                      r_dmdc=args.r_dmdc, r_era=args.r_era, jobs=args.jobs)
    studies = (args.only,) if args.only else (1, 2)
    summary = run_study(args.out, cfg, progress=not args.no_progress, studies=studies,
                        bag_dir=args.bags)
    print(f'report: {args.out / "report.md"}')
    for line in summary.get('conclusions', []):
        print(f'  - {line}')
    return 0
