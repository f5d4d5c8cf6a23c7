"""``soft-rom study``: the paper's two studies end to end on the embedded eel FOM."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
import contextlib
import functools
import os
from pathlib import Path
import shutil
from typing import Any

from soft_rom.cli._common import (
    a_path,
    add_output,
    add_quiet,
    available_memory,
    check_writable_folder,
    enclosing_data,
    finite_float,
    int_range,
    list_items,
    parse_r_list,
)

__all__ = ['add_parser', 'add_study_options', 'prepare_study', 'print_failures',
           'print_timings', 'run', 'study_output']


def add_study_options(parser: argparse.ArgumentParser, *, default_output: Path) -> None:
    """Options shared by ``study`` and ``demo`` (each with its own default folder)."""
    from soft_rom.cli.simulate import MAX_RESOLUTION

    add_output(parser, help='report folder', default=default_output, old=True)
    parser.add_argument('--overwrite', action='store_true',
                        help='replace the report folder if a soft-rom study or demo wrote it '
                             '(its recorded episodes are reused when the settings match)')
    parser.add_argument('--resolution', type=int_range(1, MAX_RESOLUTION), default=1,
                        help='eel mesh resolution (1 = fast default; 4 = paper size)')
    parser.add_argument('--episodes', type=int_range(2, 1000), default=6,
                        help='episodes to simulate, at least 2, 6 for study 2 (default 6)')
    parser.add_argument('--seed', type=int_range(0, 2**63 - 1), default=0,
                        help='seed of the pressure sequences (default: %(default)s)')
    parser.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap',
                        help='bag storage format (default: %(default)s)')
    parser.add_argument('--bags', type=a_path, default=None,
                        help='reuse (or write) the episode bags in this folder')
    parser.add_argument('--jobs', type=int_range(1, 512), default=2,
                        help='processes for simulating episodes, and for study 2 (DMDc beside '
                             'the other methods from 2 on) (default: %(default)s)')
    add_quiet(parser)


def _check_study_folder(out: Path, overwrite: bool) -> None:
    """A study never writes into a folder that is not a study's, nor over one unasked.

    Refused: an existing folder without ``--overwrite``; with it, one that is not marked
    as a soft_rom study and is not one a study wrote before the marker existed
    (``summary.json`` and ``report.md``).
    """
    from soft_rom.errors import OutputExistsError
    from soft_rom.outputs import is_marked, mark, refuse_foreign
    from soft_rom.outputs_inplace import restore_interrupted

    restore_interrupted(out)
    if not out.exists() and not out.is_symlink():
        return
    if not overwrite:
        raise OutputExistsError(f'{out} exists already; pass --overwrite to replace it, or '
                                'choose another -o folder')
    if out.is_dir() and not out.is_symlink():
        if is_marked(out, ('study',)):
            refuse_foreign(out)
            return
        if (out / 'summary.json').is_file() and (out / 'report.md').is_file():
            # written by a study before the marker existed (what else is in it: not known)
            mark(out, 'study', manifest=False)
            return
    raise OutputExistsError(f'{out} is not a soft_rom study folder (it holds other files); '
                            '--overwrite replaces only a study or demo folder: choose a new '
                            '-o folder')


#: Shortest training window of study 1 (32 samples of 1 ms, as convert's shortest episode).
_MIN_TRAIN_S = 0.032


def check_bag_folder(bags: Path) -> None:
    """``--bags``: a folder of episode bags, not a bag, nor inside a training set or a bag."""
    from soft_rom.errors import ConfigError

    inside = enclosing_data(bags)
    if inside is not None:
        raise ConfigError(f'--bags {bags} is, or is inside, the {inside[0]} {inside[1]}; give '
                          'the folder the episode bags are (or go) in')
    check_writable_folder(bags, 'bags')


def prepare_study(args: argparse.Namespace) -> None:
    """Check the folders and resources of a study before any work.

    Refused: an existing output folder without ``--overwrite`` or that is not a study's,
    a simulation that cannot fit in memory or on disk (with the estimate).
    """
    from soft_rom.cli.simulate import estimate_resources
    from soft_rom.errors import ResourceError
    from soft_rom.outputs import check_free_space

    check_writable_folder(Path(args.output), 'report')
    _check_study_folder(Path(args.output), args.overwrite)
    if args.bags is not None:
        check_bag_folder(Path(args.bags))
    n_dof, memory, disk = estimate_resources(args.resolution, jobs=args.jobs,
                                             episodes=args.episodes, steps=2000, state=True)
    free = available_memory()
    if memory > free:
        raise ResourceError(
            f'--resolution {args.resolution} ({n_dof:,} DOF) with {args.jobs} job(s) needs '
            f'about {memory / 1e9:.3g} GB of memory; {free / 1e9:.3g} GB available. Use a '
            'lower --resolution or fewer --jobs')
    check_free_space(Path(args.bags or args.output), disk,
                     f'the study bags at --resolution {args.resolution}')


def _reuse_bags(parked: Path, dest: Path, *, cfg: Any) -> None:
    """Hard links to the previous folder's recorded episodes (``bags/ep<i>`` and sidecars).

    Only episodes the study will use, recorded with the same settings (their sidecar says
    so), are carried over; the study records the others. Bags are never written after they
    are closed, so the links leave the previous folder as it is.
    """
    from soft_rom.errors import BagError
    from soft_rom.study.run import _read_sidecar, _same_recording

    old = parked / 'bags'
    if not old.is_dir() or old.is_symlink():
        return
    wanted = dict(seed=cfg.seed, storage=cfg.storage, n_steps=int(round(cfg.duration / cfg.dt)),
                  dt=cfg.dt)
    for i in range(1, cfg.n_episodes + 1):
        sidecar, bag = old / f'ep{i}.json', old / f'ep{i}'
        if not sidecar.is_file() or not bag.is_dir() or bag.is_symlink():
            continue
        try:
            if not _same_recording(_read_sidecar(sidecar), wanted, cfg.resolution):
                continue
        except BagError:
            continue
        try:
            (dest / 'bags').mkdir(exist_ok=True)
            shutil.copytree(bag, dest / 'bags' / bag.name, copy_function=os.link)
            os.link(sidecar, dest / 'bags' / sidecar.name)
        except OSError:                     # no hard links here: record them again
            shutil.rmtree(dest / 'bags', ignore_errors=True)
            return


@contextlib.contextmanager
def study_output(args: argparse.Namespace, cfg: Any) -> Iterator[Path]:
    """:func:`prepare_study`, then the run in the output folder (yielded).

    The folder is built in place (its training set and models record their paths); a
    previous study there is parked until the run ends and comes back if it stops
    (:func:`soft_rom.outputs_inplace.rebuilt_dir`): an interrupted run leaves the previous folder,
    or none, never a mix. The previous folder's recorded episodes are reused when ``cfg``
    records them the same way (none are when ``cfg`` is None: the learning curve keeps its
    recordings in its own layout).
    """
    from soft_rom.outputs_inplace import rebuilt_dir

    prepare_study(args)
    reuse = (None if args.bags is not None or cfg is None
             else functools.partial(_reuse_bags, cfg=cfg))
    with rebuilt_dir(args.output, overwrite=args.overwrite, kind='study', what='study folder',
                     carry_over=reuse) as out:
        yield out


def print_failures(summary: dict[str, Any]) -> None:
    """The fits that failed (they are missing from the report's tables), one line each."""
    for line in summary.get('failures', []):
        print(f'  warning: {line}')


def print_timings(summary: dict[str, Any]) -> None:
    """The stage times and the machine they were measured on, one line each."""
    timings = summary.get('timings', {})
    if timings:
        print('stage times: ' + ', '.join(f'{k} {v:.0f} s' for k, v in timings.items()))
    machine = summary.get('machine')
    if machine:
        print(f'machine: {machine["description"]}')


def add_parser(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        'study', help="reproduce the paper's two studies (report with figures)",
        description="Simulate the eel FOM, record bags, convert, fit LOpInf / DMDc / ERA-OKID "
                    "over ranges of r, and write a Markdown report with the paper's figures "
                    "(errors vs r, output traces, test-error bars, centerline shapes).")
    add_study_options(parser, default_output=Path('soft_rom_study'))
    parser.add_argument('--only', type=int, choices=(1, 2), default=None,
                        help='run only study 1 (time extrapolation) or 2 (unseen inputs)')
    # None: not given (refused with --learning-curve, which does not use them); run() fills in
    parser.set_defaults(episodes=None)
    parser.add_argument('--r-lopinf', type=parse_r_list, default=None,
                        help='r values for LOpInf, e.g. 2:22:2 or 4,8,16 (default 2:22:2)')
    parser.add_argument('--r-dmdc', type=parse_r_list, default=None,
                        help='r values for DMDc (default 2:22:2)')
    parser.add_argument('--r-era', type=parse_r_list, default=None,
                        help='r values for ERA/OKID (default 20:42:2)')
    parser.add_argument('--t-train', type=finite_float(0.0, 1.999, lo_open=True), default=None,
                        help='end of training in study 1, seconds, below the episode length '
                             '(default 1.5, or 3/4 of --duration)')
    parser.add_argument('--duration', type=finite_float(0.005, 60.0), default=2.0,
                        help='episode length in seconds (default: %(default)s, as the paper)')
    parser.add_argument('--staged', action='store_true',
                        help='run in resumable stages with streaming fits (the default from '
                             '--resolution 3 on; see soft_rom.study.paper_scale)')
    curve = parser.add_argument_group(
        'learning curve', 'soft-rom study --learning-curve: test error against the number of '
        'training episodes, per method, at each pressure amplitude (the cubic LOpInf against '
        'the linear one; every setting chosen on held-out training episodes)')
    curve.add_argument('--learning-curve', action='store_true',
                       help='run the learning-curve study instead of studies 1 and 2')
    curve.add_argument('--sizes', type=_sizes, default=None,
                       help='training sizes in episodes, e.g. 2,4,8,16 (default) or 2:8:2')
    curve.add_argument('--test-episodes', type=int_range(1, 100), default=None,
                       help='test episodes, seed SEED+1 (default 4)')
    curve.add_argument('--amplitudes', type=_amplitudes, default=None,
                       help='pressure amplitudes in Pa, one curve each (default 50000,5000: '
                            'strongly nonlinear and nearly linear)')
    curve.add_argument('--curve-methods', type=_curve_methods, default=None,
                       metavar='METHODS',
                       help='subset of lopinf,lopinf_cubic,dmdc,dmdc_stable,era (default all)')
    parser.set_defaults(func=run)


def _sizes(text: str) -> tuple[int, ...]:
    """``--sizes``: training sizes in episodes, written as r lists are."""
    return parse_r_list(text, 'training size')


def _amplitudes(text: str) -> tuple[float, ...]:
    """``'50000,5000'`` -> amplitudes in Pa (positive, at most 1e7 as simulate allows)."""
    parse = finite_float(0.0, 1e7, lo_open=True)
    values = tuple(parse(v) for v in list_items(text, '--amplitudes'))
    if not values:
        raise argparse.ArgumentTypeError(f'expected amplitudes in Pa, e.g. 50000,5000; got '
                                         f'{text!r}')
    return values


def _curve_methods(text: str) -> tuple[str, ...]:
    from soft_rom.study.curve.core import METHODS
    values = tuple(list_items(text, '--curve-methods'))
    bad = [v for v in values if v not in METHODS]
    if not values or bad:
        raise argparse.ArgumentTypeError(f'--curve-methods must be among {",".join(METHODS)}; '
                                         f'got {text!r}')
    return values


_STUDY_ONLY = ('only', 'episodes', 'r_lopinf', 'r_dmdc', 'r_era', 't_train', 'staged')
_CURVE_ONLY = ('sizes', 'test_episodes', 'amplitudes', 'curve_methods')


def _refuse_given(args: argparse.Namespace, names: tuple[str, ...], why: str) -> None:
    """Refuse the options of ``names`` the user gave (not None or False): they would do nothing."""
    from soft_rom.errors import ConfigError

    given = [f'--{n.replace("_", "-")}' for n in names if getattr(args, n) not in (None, False)]
    if given:
        it = 'it' if len(given) == 1 else 'them'
        raise ConfigError(f'{", ".join(given)} {"is" if len(given) == 1 else "are"} '
                          + why.format(it=it))


def _run_curve(args: argparse.Namespace) -> int:
    """``--learning-curve``: simulate, fit and score per size and amplitude; the report."""
    from soft_rom.errors import ConfigError
    from soft_rom.study.curve import CurveConfig, run_learning_curve

    _refuse_given(args, _STUDY_ONLY, 'for studies 1 and 2; the learning curve does not '
                  'use {it} (its options: --sizes, --test-episodes, --amplitudes, '
                  '--curve-methods)')
    sizes = args.sizes if args.sizes is not None else (2, 4, 8, 16)
    if min(sizes) < 2:
        raise ConfigError('--sizes must be at least 2 episodes each (the settings are chosen '
                          'on held-out training episodes)')
    kw = {} if args.curve_methods is None else {'methods': args.curve_methods}
    cfg = CurveConfig(sizes=tuple(sorted(set(sizes))),
                      n_test=4 if args.test_episodes is None else args.test_episodes,
                      amplitudes=args.amplitudes or (50e3, 5e3), seed=args.seed,
                      resolution=args.resolution,
                      storage=args.storage, jobs=args.jobs, duration=args.duration, **kw)
    # The resource check counts every recording: training, test and ERA's long episode.
    args.episodes = len(cfg.amplitudes) * (2 * max(cfg.sizes) + cfg.n_test)
    with study_output(args, None) as out:
        summary = run_learning_curve(out, cfg, progress=not args.quiet,
                                     bag_root=args.bags)
    print(f'report: {out / "report.md"}')
    for line in summary.get('verdict', []):
        print(f'  - {line}')
    return 0


def _run_staged(args: argparse.Namespace, cfg: Any) -> int:
    """The paper-scale run: resumable stages, its own disk and memory check."""
    from soft_rom.outputs import is_marked
    from soft_rom.study.paper_scale import run_paper_scale

    out = Path(args.output)
    check_writable_folder(out, 'report')
    # A staged run resumes in its own folder (same command again); any other existing folder
    # is refused without --overwrite, as for every study.
    if not ((out / 'stages').is_dir() and is_marked(out, ('study',))):
        _check_study_folder(out, args.overwrite)
    if args.bags is not None:
        check_bag_folder(Path(args.bags))
    summary = run_paper_scale(out, cfg, bag_dir=args.bags, progress=not args.quiet,
                              echo=print)
    print(f'report: {out / "report.md"}')
    for line in summary.get('conclusions', []):
        print(f'  - {line}')
    return 0


def run(args: argparse.Namespace) -> int:
    from soft_rom.errors import ConfigError
    from soft_rom.study.run import run_study, StudyConfig

    if args.learning_curve:
        return _run_curve(args)
    _refuse_given(args, _CURVE_ONLY, 'for the learning curve; add --learning-curve, or drop '
                  '{it}')
    if args.episodes is None:
        args.episodes = 6
    defaults = {'r_lopinf': range(2, 23, 2), 'r_dmdc': range(2, 23, 2), 'r_era': range(20, 43, 2)}
    for name, values in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, tuple(values))
    t_train = args.t_train if args.t_train is not None else min(1.5, 0.75 * args.duration)
    if not t_train < args.duration:
        raise ConfigError(f'--t-train {t_train:g} must be below --duration {args.duration:g}')
    if args.only in (None, 1) and t_train < _MIN_TRAIN_S:
        raise ConfigError(f'--t-train {t_train:g} s leaves study 1 fewer than '
                          f'{int(_MIN_TRAIN_S * 1e3)} samples to train on; give at least '
                          f'{_MIN_TRAIN_S:g} s (a longer --duration sets a longer default)')
    if args.only == 2 and args.episodes < 3:
        raise ConfigError(f'study 2 trains on Ep 1 + Ep 2 and tests on the others: --episodes '
                          f'{args.episodes} leaves none to test (6 as the paper)')
    staged = args.staged or args.resolution >= 3
    cfg = StudyConfig(resolution=args.resolution, n_episodes=args.episodes, seed=args.seed,
                      storage=args.storage, t_train=t_train, r_lopinf=args.r_lopinf,
                      r_dmdc=args.r_dmdc, r_era=args.r_era, jobs=args.jobs,
                      duration=args.duration, r_cubic=() if staged else (4,))
    if staged:
        if args.only:
            raise ConfigError('--only is not available with --staged (or --resolution >= 3): '
                             'the staged run does both studies')
        return _run_staged(args, cfg)
    studies = (args.only,) if args.only else (1, 2)
    with study_output(args, cfg) as out:
        summary = run_study(out, cfg, progress=not args.quiet, studies=studies,
                            bag_dir=args.bags)
    print_timings(summary)
    print(f'report: {out / "report.md"}')
    for line in summary.get('conclusions', []):
        print(f'  - {line}')
    print_failures(summary)
    return 0
