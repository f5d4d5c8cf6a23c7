"""``soft-rom fit``: training set -> model files, one per (method, r).

Examples::

    soft-rom fit eel.zarr --method lopinf --r 2:22:2 -o models/
    soft-rom fit eel.zarr --method dmdc --r 12 --episodes ep1,ep2 --t-max 2 -o models/
    soft-rom fit eel.zarr --method era --r 20:40:2 --era-episode ep2 --decimation 5 -o models/

Several ``r`` values in one call reuse the expensive part: the POD basis and projections
(LOpInf), the two SVDs (DMDc), the OKID Markov parameters (ERA).

The model files (and the ``--json`` summary) appear all together or not at all: nothing is
written until every method and r has been fitted, and existing files are replaced only
with ``--overwrite`` and only if soft_rom wrote them.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from soft_rom.cli._common import (
    a_path,
    add_json,
    add_quiet,
    check_apart,
    check_writable_folder,
    dumps_strict,
    enclosing_data,
    finite_float,
    int_range,
    is_model_file,
    is_summary_json,
    list_items,
    parse_r_list,
)
from soft_rom.errors import ConfigError
from soft_rom.learners.registry import LEARNERS
from soft_rom.pipeline import fit_method, FitSettings, FittedModel, open_training_data

__all__ = ['add_parser', 'run']

METHODS = tuple(LEARNERS)


def _prefix(text: str) -> str:
    """``--prefix``: a file-name start, not blank, no folder in it."""
    if not text.strip() or text != text.strip() or '/' in text or '\\' in text:
        raise argparse.ArgumentTypeError(f'{text!r} is not a file-name prefix (no blanks at '
                                         'its ends, no folder)')
    return text


def _address(text: str) -> str:
    """``--dask``: a scheduler address, ``[scheme://]host:port``."""
    import re
    if not (text.strip().startswith('inproc://') or re.fullmatch(
            r'([a-z][a-z0-9+.-]*://)?(\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]]+):\d{1,5}', text.strip())):
        raise argparse.ArgumentTypeError(f'{text!r} is not a scheduler address; give '
                                         '[tcp://]HOST:PORT, e.g. tcp://127.0.0.1:8786')
    return text.strip()


def _ddt(text: str) -> str:
    """``--ddt``: checked when given, whatever the method (it was ignored for DMDc/ERA)."""
    from soft_rom.ddt import parse_estimator
    from soft_rom.errors import ConfigError
    try:
        parse_estimator(text)
    except ConfigError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def _methods(text: str) -> tuple[str, ...]:
    out = tuple(m.lower() for m in list_items(text, '--method'))
    bad = [m for m in out if m not in METHODS]
    if not out or bad:
        raise argparse.ArgumentTypeError(
            f'--method must be one or more of {", ".join(METHODS)} (comma-separated); '
            f'got {text!r}')
    return out


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``fit``: the training set and methods, then the options by concern."""
    parser = subparsers.add_parser(
        'fit', help='fit LOpInf / DMDc / ERA-OKID ROMs on a training set',
        description='Fit reduced-order models on a training set and write one model file per '
                    '(method, r), named PREFIX_METHOD_rR.npz. Prints a summary table '
                    '(r, training errors, stability margin, time).')
    parser.add_argument('training_set', metavar='TRAINING_SET',
                        help='training set directory (.zarr) written by soft-rom convert (a bag '
                             'is converted first: soft-rom convert BAG -o SET.zarr)')
    parser.add_argument('--method', type=_methods, default=('lopinf',),
                        help='lopinf, dmdc, era, or several comma-separated (default lopinf)')
    _add_size_and_lopinf_options(parser)
    _add_era_options(parser.add_argument_group('ERA/OKID'))
    _add_variant_options(parser.add_argument_group('LOpInf / DMDc variants'))
    _add_run_options(parser)
    parser.set_defaults(func=run)
    return parser


def _add_size_and_lopinf_options(parser: argparse.ArgumentParser) -> None:
    """``--r`` / ``--energy``, the LOpInf solver, forces and derivatives, the data used."""
    size = parser.add_mutually_exclusive_group()
    size.add_argument('--r', type=parse_r_list, default=None, metavar='R',
                      help='reduced dimension(s): 16, 4,8,16 or START:STOP[:STEP] (inclusive)')
    size.add_argument('--energy', type=finite_float(0.0, 1.0, lo_open=True), default=None,
                      help='choose r by POD energy fraction (default 0.95 when --r is not '
                           'given; ERA then uses its Hankel singular value rule)')
    parser.add_argument('--solver', choices=('fast', 'cvxpy'), default='fast',
                        help='LOpInf operator solver (default fast)')
    parser.add_argument('--forces', choices=('linear', 'cubic', 'auto'), default='linear',
                        help='LOpInf restoring force: linear (K q); cubic (quartic potential, '
                             'energy-consistent integrator; the best of a grid of --cubic-reg '
                             'on held-out training episodes, compared with linear); or auto '
                             '(cubic only when at least 10 %% better than linear held out, on 4 '
                             'or more folds of training episodes, else linear); default linear')
    parser.add_argument('--cubic-reg', type=finite_float(0.0, lo_open=True), default=None,
                        help='cubic forces: Tikhonov weight of the nonlinear tensors, fixed '
                             '(with --cubic-eps4; default chosen on held-out data)')
    parser.add_argument('--cubic-eps4', type=finite_float(0.0, lo_open=True), default=None,
                        help='cubic forces: relative floor of the quartic potential, fixed '
                             '(with --cubic-reg; default chosen on held-out data)')
    parser.add_argument('--mass', choices=('identity', 'learned'), default=None,
                        help='LOpInf mass matrix: identity, or learned (SPD, exact in any '
                             'coordinates); default learned on outputs, identity on states')
    parser.add_argument('--refine', choices=('none', 'output-error'), default=None,
                        help='LOpInf: refine K, C, B by the simulation error of the training '
                             'episodes (constraints kept; unbiased for measurement noise); '
                             'default output-error on outputs, none on states')
    parser.add_argument('--ddt-order', type=int, choices=(2, 4, 6, 8), default=8,
                        help='finite-difference order for LOpInf derivatives (default 8)')
    parser.add_argument('--coordinates', choices=('state', 'outputs'), default=None,
                        help='LOpInf/DMDc coordinates: full states Q, or the measured outputs '
                             '(deviations from y_ref); default state when the set has Q, '
                             'else outputs')
    parser.add_argument('--ddt', type=_ddt, default=None, metavar='ESTIMATOR',
                        help='LOpInf derivatives: fd2, fd4, fd6, fd8, savgol, '
                             'savgol:WINDOW[:POLYORDER] (default fd8 on states, savgol on '
                             'outputs); overrides --ddt-order')
    parser.add_argument('--episodes', default=None,
                        help='comma-separated episode names to train on (default all)')
    parser.add_argument('--t-max', type=finite_float(0.0, lo_open=True), default=None,
                        help='train on samples with t - t_start < T_MAX seconds of each episode')
    parser.add_argument('--p', type=int_range(1), default=None, dest='dmdc_p',
                        help='DMDc truncation of the SVD of [Q; U] (default r + m)')


def _add_era_options(era: Any) -> None:
    """The ERA/OKID option group."""
    era.add_argument('--era-episode', default=None,
                     help='the one episode ERA/OKID is fitted on (default the first selected)')
    era.add_argument('--decimation', type=int_range(1, 100_000), default=None,
                     help='fit at DECIMATION x the data sample time (default: selected, 1 or '
                          '5, one that serves every --r at the data sample time)')
    era.add_argument('--n-markov', type=int_range(1, 1_000_000), default=None,
                     help='number of Markov parameters in the Hankel matrices (default: a '
                          'third of the samples, at most 500); at most the samples of the ERA '
                          'episode after decimation minus 1, else refused')
    era.add_argument('--observer-order', type=int_range(1, 100_000), default=None,
                     help='OKID observer order (default: selected by cross-validation); one '
                          'the episode cannot fit (two equations per unknown in each training '
                          'fold) is refused, never replaced')
    era.add_argument('--output-rank', type=int_range(1), default=None,
                     help='identify on this many principal components of the outputs '
                          '(fewer OKID unknowns; e.g. 4 for a centerline)')
    era.add_argument('--okid-rcond', type=finite_float(0.0, 1.0, lo_open=True, hi_open=True),
                     default=None,
                     help='relative cut-off of the OKID least-squares solve')
    era.add_argument('--hsv-tol', type=finite_float(0.0, 1.0, lo_open=True, hi_open=True),
                     default=None,
                     help='relative Hankel singular value threshold when r is automatic')
    era.add_argument('--era-preset', default=None, choices=('auto', 'eel'),
                     help='named ERA/OKID settings (auto: data-driven defaults; eel: the '
                          "study's hand-tuned settings); the options above override it")
    era.add_argument('--okid-ridge', type=finite_float(0.0), default=None,
                     help='relative ridge weight of OKID (default: selected on a held-out '
                          'tail)')


def _add_variant_options(variants: Any) -> None:
    """The LOpInf / DMDc variants option group."""
    variants.add_argument('--regularization', default=None, metavar='GAMMA|auto',
                          help="LOpInf Tikhonov weight (dimensionless), or 'auto' to select it "
                               'on held-out episode tails (default none)')
    variants.add_argument('--min-damping-ratio', type=finite_float(0.0, 1.0), default=None,
                          help='LOpInf: every mode has at least this damping ratio (default '
                               '0.01; 0 for the absolute margin only)')
    variants.add_argument('--dmdc-variant', choices=('paper', 'stable'), default=None,
                          help='DMDc formulation: paper (default) or stable (one lag, '
                               'spectral radius <= 1; files named PREFIX_dmdc-stable_rR.npz, '
                               'flagged when their training error is worse than the paper '
                               "variant's)")


def _add_run_options(parser: argparse.ArgumentParser) -> None:
    """Streaming and Dask, the output directory and files, JSON and quiet."""
    parser.add_argument('--streaming', action='store_true',
                        help='stream the snapshots from disk with bounded memory (for training '
                             'sets larger than RAM; the exact Gram POD while it fits in 1 GiB, '
                             'else the randomized one)')
    parser.add_argument('--dask', type=_address, metavar='ADDRESS', default=None,
                        help='fit on a dask.distributed cluster (scheduler address, e.g. '
                             'tcp://host:8786); implies --streaming')
    parser.add_argument('--dask-timeout', type=float, default=30.0, metavar='S',
                        help='seconds to wait for the Dask scheduler (to connect, and after '
                             'losing it; default 30)')
    parser.add_argument('-o', '--output', type=a_path, required=True, metavar='OUTDIR',
                        help='directory for the model files (created if missing)')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace model files (and the --json file) soft_rom wrote before')
    parser.add_argument('--prefix', type=_prefix, default=None,
                        help='file-name prefix (default: the training set name, e.g. eel)')
    add_json(parser, help='also write the summary table as JSON')
    add_quiet(parser, old=True)


_MODEL_FILE = is_model_file
_FIT_JSON = is_summary_json(('method', 'r', 'path'))


def _basis_r(model: Any) -> int:
    """The ``r`` asked for: the basis size (a stable DMDc model has ``2r + m`` states)."""
    r = model.metadata.get('r') if model.method == 'dmdc' else None
    return int(r) if isinstance(r, int) and not isinstance(r, bool) else int(model.r)


def _stems(method: str, args: argparse.Namespace) -> list[str]:
    """The file-name stems a fit of ``method`` is expected to write (before fitting)."""
    name = method
    if method == 'lopinf' and args.forces == 'cubic':
        name = 'lopinf_cubic'
    if method == 'lopinf' and args.forces == 'auto':        # either, as the verdict keeps
        return [f'{n}_r{r}' for n in ('lopinf', 'lopinf_cubic') for r in args.r]
    if method == 'dmdc' and args.dmdc_variant not in (None, 'paper'):
        name = f'dmdc-{args.dmdc_variant}'
    return [f'{name}_r{r}' for r in args.r]


def _check_outputs_early(args: argparse.Namespace, outdir: Path, prefix: str) -> None:
    """Refuse before fitting what would be refused when writing (exists, not ours, ...)."""
    from soft_rom.outputs import check_output

    inside = enclosing_data(outdir)
    if inside is not None:
        raise ConfigError(f'-o {outdir} would put the model files inside the {inside[0]} '
                          f'{inside[1]}; choose another -o')
    check_writable_folder(outdir, 'model files')
    if args.r is not None:
        from soft_rom.models import MAX_STATES
        for method in args.method:
            states = 2 if method == 'lopinf' else 1
            too_big = [r for r in args.r if states * r > MAX_STATES]
            if too_big:
                raise ConfigError(f'--r {too_big[0]} is too large for {method}: model files hold '
                                  f'at most {MAX_STATES} states (r <= {MAX_STATES // states})')
    if args.json is not None:
        check_writable_folder(args.json.parent, '--json file')
        check_apart(args.json, '--json', [('training set', Path(args.training_set))])
        mine, models = args.json.resolve(), outdir.resolve()
        if mine == models or mine in models.parents:
            raise ConfigError(f'--json {args.json} would replace or hold the model folder '
                              f'{outdir}; choose another --json')
        if args.json.resolve().parent == outdir.resolve() and args.json.suffix == '.npz':
            raise ConfigError('--json must not be a .npz path among the model files')
        check_output(args.json, overwrite=args.overwrite, what='fit summary',
                     is_ours=_FIT_JSON)
    if args.r is not None:
        for method in args.method:
            for stem in _stems(method, args):
                check_output(outdir / f'{prefix}_{stem}.npz', overwrite=args.overwrite,
                             what='model file', is_ours=_MODEL_FILE)


def _settings(args: argparse.Namespace) -> FitSettings:
    """The fit's settings from the command line (``None``: the pipeline's defaults)."""
    era = {'episode': args.era_episode, 'decimation': args.decimation,
           'n_markov': args.n_markov, 'observer_order': args.observer_order,
           'hsv_tol': args.hsv_tol, 'output_rank': args.output_rank,
           'okid_rcond': args.okid_rcond, 'okid_ridge': args.okid_ridge}
    if args.era_preset:
        from soft_rom.study.presets import ERA_PRESETS
        era = {**ERA_PRESETS[args.era_preset], **{k: v for k, v in era.items() if v is not None}}
    lopinf: dict[str, Any] = {}
    if args.regularization is not None:
        reg = args.regularization
        if reg != 'auto':
            try:
                reg = float(reg)
                if not (math.isfinite(reg) and reg >= 0):
                    raise ValueError(reg)
            except ValueError:
                raise ConfigError(f"--regularization must be a number >= 0 or 'auto'; got "
                                  f'{args.regularization!r}') from None
        lopinf['regularization'] = reg
    if args.min_damping_ratio is not None:
        lopinf['min_damping_ratio'] = args.min_damping_ratio
    cubic = None
    if (args.cubic_reg is None) != (args.cubic_eps4 is None):
        raise ConfigError('--cubic-reg and --cubic-eps4 go together (fixed cubic settings); '
                          'give both, or neither to choose them on held-out data')
    if args.cubic_reg is not None:
        if args.forces != 'cubic':
            raise ConfigError('--cubic-reg and --cubic-eps4 need --forces cubic')
        cubic = {'reg': args.cubic_reg, 'eps4': args.cubic_eps4}
    return FitSettings(energy=args.energy, solver=args.solver, ddt=args.ddt,
                       ddt_order=args.ddt_order, coordinates=args.coordinates,
                       forces=args.forces, mass=args.mass, refine=args.refine,
                       cubic_options=cubic, lopinf=lopinf, dmdc_p=args.dmdc_p,
                       dmdc_variant=args.dmdc_variant or 'paper', era=era)


def _reducer(args: argparse.Namespace, clients: list[Any]) -> Any:
    """The streaming reducer (``--streaming``, ``--dask``: connected here), or ``None``."""
    if not (args.streaming or args.dask is not None):
        return None
    from soft_rom.reduce import StreamingReducer
    client = None
    if args.dask is not None:
        if not (math.isfinite(args.dask_timeout) and args.dask_timeout > 0):
            raise ConfigError(f'--dask-timeout must be a number of seconds > 0; got '
                              f'{args.dask_timeout!r}')
        from soft_rom.scale.dask_backend import connect
        client = connect(args.dask, args.dask_timeout)
        clients.append(client)
    return StreamingReducer(0.95 if args.energy is None else args.energy, client=client)


#: Options of one or two methods: ``dest -> (its flag, the methods it applies to, default)``.
_OF_METHODS: dict[str, tuple[str, tuple[str, ...], Any]] = {
    'solver': ('--solver', ('lopinf',), 'fast'),
    'forces': ('--forces', ('lopinf',), 'linear'),
    'mass': ('--mass', ('lopinf',), None),
    'refine': ('--refine', ('lopinf',), None),
    'ddt': ('--ddt', ('lopinf',), None),
    'ddt_order': ('--ddt-order', ('lopinf',), 8),
    'regularization': ('--regularization', ('lopinf',), None),
    'min_damping_ratio': ('--min-damping-ratio', ('lopinf',), None),
    'coordinates': ('--coordinates', ('lopinf', 'dmdc'), None),
    'dmdc_p': ('--p', ('dmdc',), None),
    'dmdc_variant': ('--dmdc-variant', ('dmdc',), None),
    **{dest: (f'--{dest.replace("_", "-")}', ('era',), None)
       for dest in ('era_episode', 'decimation', 'n_markov', 'observer_order', 'output_rank',
                    'okid_rcond', 'hsv_tol', 'era_preset', 'okid_ridge')},
}


def _check_applies(args: argparse.Namespace) -> None:
    """Refuse an option none of the methods asked for reads (it was silently ignored)."""
    for dest, (flag, methods, default) in _OF_METHODS.items():
        if getattr(args, dest, default) != default and not set(methods) & set(args.method):
            raise ConfigError(f'{flag} applies to {" and ".join(methods)}, not to --method '
                              f'{",".join(args.method)}')


def run(args: argparse.Namespace) -> int:
    """Execute ``soft-rom fit`` (a Dask client it connects is closed at the end)."""
    _check_applies(args)
    clients: list[Any] = []
    try:
        return _run(args, clients)
    finally:
        for client in clients:
            client.close()


def _run(args: argparse.Namespace, clients: list[Any]) -> int:
    from soft_rom.outputs import atomic_files

    outdir = Path(args.output)
    prefix = args.prefix or Path(str(args.training_set).rstrip('/')).stem or 'model'
    if '/' in prefix or prefix in ('.', '..'):
        raise ConfigError(f'--prefix must be a file-name prefix, not a path; got {prefix!r}')
    _check_outputs_early(args, outdir, prefix)
    ts = open_training_set(args.training_set)
    settings = _settings(args)
    provenance = {'training_set': str(Path(args.training_set).resolve()), 't_max': args.t_max,
                  'source': ts.provenance if hasattr(ts, 'provenance') else {}}
    try:
        json.dumps(provenance)
    except TypeError:
        provenance['source'] = str(provenance['source'])
    data = open_training_data(ts, episodes=args.episodes, t_max=args.t_max,
                              provenance=provenance)
    layout = ts.output_layout.to_dict() if getattr(ts, 'output_layout', None) else None
    reducer = _reducer(args, clients)
    fitted: list[FittedModel] = []
    for method in args.method:
        fitted += fit_method(data, method, args.r, settings, reducer, layout=layout,
                             progress=not args.quiet)
    rows, models = _rows(fitted, data, outdir, prefix)
    outputs: list[Path] = list(models)
    if args.json is not None:
        outputs.append(args.json)

    def ours(path: Path) -> bool:
        return _FIT_JSON(path) if args.json is not None and path == args.json else \
            _MODEL_FILE(path)

    with atomic_files(outputs, overwrite=args.overwrite, what='fit output',
                      is_ours=ours) as staged:
        for path, model in models.items():
            model.save(staged[path])
        if args.json is not None:
            staged[args.json].write_text(dumps_strict(rows, indent=2) + '\n',
                                         encoding='utf-8')
    print(format_table(rows))
    for row in rows:
        for note in row['notes']:
            print(f'  {Path(row["path"]).name}: {note}')
    return 0


def _rows(fitted: list[FittedModel], data: Any, outdir: Path, prefix: str
          ) -> tuple[list[dict[str, Any]], dict[Path, Any]]:
    """The fit table's rows (training errors, trust, notes) and the files to write."""
    from soft_rom.evaluation import evaluate
    from soft_rom.pipeline.review import review_rows
    rows: list[dict[str, Any]] = []
    models: dict[Path, Any] = {}
    for fit in fitted:
        model = fit.model
        path = outdir / f'{prefix}_{fit.stem}.npz'
        if path in models:
            raise ConfigError(f'two models would be written to {path.name}; fit one method '
                              'per call or give distinct --r values')
        models[path] = model
        train_eps = data.episodes
        if model.method == 'era':
            train_eps = [e for e in data.episodes
                         if e.name in model.metadata['training']['episodes']]
        ev = evaluate(model, train_eps).get()
        notes = list(fit.notes)
        refined = (model.metadata.get('diagnostics') or {}).get('refinement') or {}
        if refined.get('criterion') == 'output-error' and not refined.get('iterations'):
            # asked for and not kept: the table's figures are the equation-error fit's
            notes.append(f'--refine output-error was not applied ({refined.get("status")}): '
                         'this is the equation-error fit')
        rows.append({'model': fit.label, 'method': model.method, 'r': _basis_r(model),
                     'dt': model.dt, 'train_relative_error': ev['relative_error'],
                     'train_relative_deviation_error': ev['relative_deviation_error'],
                     'stability_margin': model.stability_margin(),
                     'trust': model.trust_issues(), 'seconds': fit.seconds,
                     'path': str(path), 'notes': notes,
                     **({'forces_selection': model.metadata['forces_selection']}
                        if 'forces_selection' in model.metadata else {})})
    review_rows(rows, fitted, data)
    return rows, models


def open_training_set(path: str | Path) -> Any:
    """The training set at ``path``; a bag is refused with the command that converts it."""
    from soft_rom.bags.reader import is_bag
    from soft_rom.dataset import TrainingSet
    p = Path(path)
    if p.exists() and is_bag(p):
        out = p.with_name((p.stem if p.is_file() else p.name) + '.zarr')
        raise ConfigError(f'{p} is a rosbag2 bag, not a training set: convert it first with '
                          f'`soft-rom convert {p} -o {out}`, then use {out}')
    return TrainingSet.open(p)


def format_table(rows: list[dict[str, Any]]) -> str:
    """Summary table of :func:`run`: the model named exactly (method, variant, forces, r)."""
    width = max([len('model')] + [len(r['model']) for r in rows])
    head = f'{"model":<{width}} {"dt [s]":>8} {"err":>10} {"dev err":>10} ' \
           f'{"margin":>10} {"time [s]":>9}  file'
    lines = [head, '-' * len(head)]
    for r in rows:
        flag = ' *' if r['notes'] else ''
        lines.append(f'{r["model"]:<{width}} {r["dt"]:>8.4g} '
                     f'{r["train_relative_error"]:>10.3e} '
                     f'{r["train_relative_deviation_error"]:>10.3e} '
                     f'{r["stability_margin"]:>10.3e} {r["seconds"]:>9.2f}  '
                     f'{Path(r["path"]).name}{flag}')
    if any(r['notes'] for r in rows):
        lines.append('* see the notes below')
    return '\n'.join(lines)
