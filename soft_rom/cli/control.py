"""``soft-rom control MODEL --reference REF -o OUT``: MPC on a ROM, the embedded FOM as the plant.

The controller (:class:`soft_rom.control.Controller`: offset-free estimator + MPC) sees only
the FOM's centerline through a motion-capture-like sensor (``--sensor-rate``,
``--sensor-noise``); the loop runs in one process (:func:`soft_rom.control.run_closed_loop`).
``OUT`` gets ``closed_loop.npz`` (``t``, ``U`` applied, ``Y`` noise-free, ``Y_meas``,
``Y_ref``, solve and step times), ``summary.json`` and ``closed_loop.png``; it is built in
a staging folder and appears whole. ``soft-rom simulate --inputs OUT/closed_loop.npz``
re-runs the plant on the applied pressures.
"""

from __future__ import annotations

import argparse
from pathlib import Path
import sys
from typing import Any
import warnings

from soft_rom.cli._common import (
    a_path,
    add_quiet,
    check_writable_folder,
    dumps_strict,
    finite_float,
    int_range,
)
from soft_rom.errors import ConfigError, SoftRomWarning

__all__ = ['add_parser', 'run']


def _floats(text: str) -> tuple[float, ...]:
    import math
    try:
        values = tuple(float(v) for v in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected numbers separated by commas; got {text!r}'
                                         ) from None
    if not values or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f'expected finite numbers; got {text!r}')
    return values


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``control`` and its options."""
    parser = subparsers.add_parser(
        'control', help='MPC on a ROM with the embedded FOM as the plant (closed loop)',
        description='Close the loop in one process: an offset-free MPC on the model tracks a '
                    'reference centerline; the embedded eel FOM is the plant and the '
                    'controller sees only its measured centerline. Writes OUT/closed_loop.npz, '
                    'OUT/summary.json and OUT/closed_loop.png.')
    parser.add_argument('model', type=Path, help='linear model file (.npz: LOpInf, DMDc, ERA)')
    parser.add_argument('--reference', required=True, metavar='REF',
                        help='reference: an .npz with t (k,) s and Y (p, k) absolute outputs, '
                             'or wave:f=2,wavelength=0.8,amplitude=auto (travelling wave), '
                             'step:u=P1/P2/P3/P4/P5/P6[,at=0.1] (static bend of the FOM), '
                             'episode:BAG (a recorded episode)')
    parser.add_argument('-o', '--output', type=a_path, required=True, metavar='OUT',
                        help='output folder')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace an OUT that soft-rom control wrote before')
    parser.add_argument('--duration', type=finite_float(0.0, 3600.0, lo_open=True),
                        default=None, help='seconds to run (default: the reference length; 2 s '
                                           'for wave and step)')
    parser.add_argument('--step', type=finite_float(0.0, 10.0, lo_open=True), default=0.01,
                        help='control step in s, a multiple of the model dt (default 0.01)')
    parser.add_argument('--horizon', type=finite_float(0.0, 100.0, lo_open=True), default=0.2,
                        help='prediction horizon in s (default 0.2)')
    parser.add_argument('--rate-weight', type=finite_float(0.0, 1e12), default=1e-4,
                        help='weight of input increments against the output error (default '
                             '1e-4, the library default)')
    parser.add_argument('--u-min', type=_floats, default=None, metavar='P[,P...]',
                        help='lower pressure bound(s), Pa (default: the training range)')
    parser.add_argument('--u-max', type=_floats, default=None, metavar='P[,P...]',
                        help='upper pressure bound(s), Pa (default: the training range)')
    parser.add_argument('--rate-max', type=finite_float(0.0, 1e15, lo_open=True), default=None,
                        help='largest pressure change, Pa/s (default: the range in 50 ms)')
    parser.add_argument('--solver', choices=('daqp', 'osqp'), default='daqp',
                        help='QP solver (default daqp)')
    parser.add_argument('--terminal', choices=('none', 'riccati'), default='none',
                        help='terminal cost: none (default) or riccati (the infinite-horizon '
                             'cost-to-go of the ROM, docs/control.md)')
    parser.add_argument('--sensor-rate', type=finite_float(0.0, 1e5, lo_open=True),
                        default=120.0, help='measured centerline rate, Hz (default 120)')
    parser.add_argument('--sensor-noise', type=finite_float(0.0, 1.0), default=5e-4,
                        help='measurement noise (std, m; default 0.0005)')
    parser.add_argument('--seed', type=int_range(0, 2**63 - 1), default=0,
                        help='seed of the sensor noise')
    parser.add_argument('--resolution', type=int, choices=range(1, 5), default=1,
                        metavar='{1..4}', help='FOM mesh resolution (default 1)')
    add_quiet(parser)
    parser.set_defaults(func=run)
    study = subparsers.add_parser(
        'control-study', help='the closed-loop study (MPC on several ROMs, the FOM as plant)',
        description="The follow-up paper's experiments 1 and 2 on the embedded eel: MPC on each "
                    'model (same horizon, bounds, weight chosen once on a training reference) '
                    "tracks feasible references (the FOM's responses to held-out random "
                    'pressures) and the travelling wave; plus the offset-free check. Writes '
                    'OUT/report.md, summary.json and figures.')
    study.add_argument('models', type=Path, nargs='+',
                       help="linear model files of the eel (e.g. the study's models/*.npz)")
    study.add_argument('-o', '--output', type=a_path, required=True, metavar='OUT',
                       help='output folder')
    study.add_argument('--overwrite', action='store_true',
                       help='replace an OUT that soft-rom control-study wrote before')
    study.add_argument('--duration', type=finite_float(0.0, 60.0, lo_open=True), default=2.0,
                       help='seconds per closed loop (default 2)')
    study.add_argument('--references', type=int_range(1, 20), default=4,
                       metavar='{1..20}', help='feasible references (default 4)')
    study.add_argument('--seed', type=int_range(0, 2**63 - 1), default=100,
                       help="seed of the references' random pressures (default 100; not a "
                            'training seed)')
    study.add_argument('--wave', default='wave:f=2,wavelength=0.8,reach=0.1',
                       help='the travelling wave (default %(default)s)')
    study.add_argument('--jobs', type=int_range(1, 64), default=1, metavar='N',
                       help='closed loops run at once (default 1)')
    add_quiet(study)
    study.set_defaults(func=run_study)
    return parser


def run_study(args: argparse.Namespace) -> int:
    """``soft-rom control-study``; returns the exit code."""
    from soft_rom.control.study import ControlStudyConfig, load_models, run_control_study
    from soft_rom.outputs import atomic_dir, check_output

    out = Path(args.output)
    check_output(out, overwrite=args.overwrite, what='closed-loop study',
                 kinds=('control-study',))
    models = load_models(args.models)
    from soft_rom.models import load_model
    for label, path in models.items():
        if getattr(load_model(path), 'is_nonlinear', False):
            raise ConfigError(f'{label}: a cubic LOpInf model is nonlinear; the MPC is linear.')
    if not args.wave.startswith('wave:'):
        raise ConfigError(f'--wave must be a wave:... reference; got {args.wave!r}')
    cfg = ControlStudyConfig(duration=args.duration, n_references=args.references,
                             seed=args.seed, wave=args.wave)
    log = (lambda text: None) if args.quiet else (lambda text: print(text, flush=True))
    with atomic_dir(out, overwrite=args.overwrite, kind='control-study',
                    what='closed-loop study') as stage:
        run_control_study(stage, models, cfg, jobs=args.jobs, log=log)
    print(f'wrote {out}/report.md, summary.json and figures')
    return 0


def run(args: argparse.Namespace) -> int:
    """Run the closed loop and write OUT; returns the exit code."""
    from soft_rom.control import (
        check_moves,
        ClosedLoopResult,
        EstimatorConfig,
        FOMPlant,
        input_bounds,
        MPCConfig,
        parse_reference,
        run_closed_loop,
        Sensor,
    )
    from soft_rom.control.figures import closed_loop_figure
    from soft_rom.control.loop import check_plant_units
    from soft_rom.models import load_model
    from soft_rom.outputs import atomic_dir, check_output
    from soft_rom.sim import EelModel

    out = Path(args.output)
    check_writable_folder(out.parent if str(out.parent) else Path('.'), 'output folder')
    check_output(out, overwrite=args.overwrite, what='closed-loop run', kinds=('control',))
    model = load_model(args.model)
    if getattr(model, 'is_nonlinear', False) or getattr(model, 'is_linear', True) is False:
        raise ConfigError(f'{args.model}: a cubic LOpInf model is nonlinear; the MPC is linear. '
                          'Fit a linear one (soft-rom fit --forces linear).')
    check_plant_units(model)                         # before the FOM's set-up (seconds)
    input_bounds(model, args.u_min, args.u_max)
    mpc = MPCConfig(step=args.step, horizon=args.horizon, rate_weight=args.rate_weight,
                    u_min=args.u_min, u_max=args.u_max, rate_max=args.rate_max,
                    solver=args.solver, terminal=args.terminal)
    sensor = Sensor(rate=args.sensor_rate, noise=args.sensor_noise, seed=args.seed)
    eel = EelModel(resolution=args.resolution)
    ref = parse_reference(args.reference, model, duration=args.duration, plant=eel)
    check_moves(ref, model, args.duration)
    said = _check_with_controller(model, mpc, ref)
    plant = FOMPlant(model, eel)
    bar: Any = None
    if not args.quiet:
        from tqdm import tqdm
        bar = tqdm(total=100, desc='closed loop', leave=False,
                   bar_format='{desc}: {percentage:3.0f}%|{bar}| [{elapsed}<{remaining}]')

    def progress(frac: float) -> None:
        if bar is not None:
            bar.n = int(100 * frac)
            bar.refresh()

    est = EstimatorConfig(measurement_noise=max(args.sensor_noise, 1e-5),
                          sensor_rate=args.sensor_rate)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter('ignore', SoftRomWarning)     # said before the run
            res: ClosedLoopResult = run_closed_loop(model, ref, plant=plant, mpc=mpc,
                                                    estimator=est, sensor=sensor,
                                                    duration=args.duration, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    summary = res.summary()
    summary.update({'model': str(args.model), 'reference_spec': args.reference,
                    'model_trust': model.trust_issues(), 'warnings': said,
                    'fom_resolution': args.resolution,
                    'u_min': res.u_min.tolist(), 'u_max': res.u_max.tolist()})
    with atomic_dir(out, overwrite=args.overwrite, kind='control',
                    what='closed-loop run') as stage:
        res.save(stage / 'closed_loop.npz')
        (stage / 'summary.json').write_text(dumps_strict(summary, indent=2) + '\n',
                                            encoding='utf-8')
        closed_loop_figure(stage / 'closed_loop.png', res, list(model.output_names),
                           title=f'{model.method} r={model.r}: {ref.label}')
    _print_summary(model, plant, ref, res, summary)
    print(f'  wrote {out}/closed_loop.npz, summary.json, closed_loop.png')
    if not summary['status_counts'].get('ok'):      # the plant ran on held commands only
        print(f'soft-rom control: error: no control step succeeded '
              f'({", ".join(f"{k} {v}" for k, v in summary["status_counts"].items())}); the '
              f'record of the run is in {out}', file=sys.stderr)
        return 1
    return 0


def _check_with_controller(model: Any, mpc: Any, ref: Any) -> list[str]:
    """The controller's verdict on ``ref`` before the run (a refusal is an error).

    Its warnings (an untrusted model, a target out of reach) are printed now, one line each,
    and returned.
    """
    from soft_rom.control import Controller
    with warnings.catch_warnings(record=True) as held:
        warnings.simplefilter('always', SoftRomWarning)
        refused = Controller(model, mpc).check_reference(ref)
    if refused:
        raise ConfigError(refused)
    said = []
    for w in held:
        if issubclass(w.category, SoftRomWarning):
            said.append(str(w.message))
            print(f'soft-rom control: warning: {w.message}', file=sys.stderr, flush=True)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return said


def _print_summary(model: Any, plant: Any, ref: Any, res: Any, summary: dict[str, Any]
                   ) -> None:
    """The run in a few lines: what ran, the tracking error, the solves, the bounds."""
    solve = summary['solve']
    counts = ', '.join(f'{k} {v}' for k, v in summary['status_counts'].items())
    print(f'{model.method} r={model.r} MPC on the eel FOM ({plant.eel.n_dof:,} DOF), '
          f'{res.t[-1] + res.info["plant_step_s"]:.2f} s, reference: {ref.label}')
    err, after = (summary[k] for k in ('tracking_deviation_error',
                                       'tracking_deviation_error_after_1s'))
    print('  tracking deviation error ' + ('undefined' if err is None else f'{err:.4f}')
          + (f' (after 1 s: {after:.4f})' if after is not None else ''))
    if solve['p50_ms'] is not None:
        period_ms = 1e3 * res.info['control_step_s']
        print(f'  QP ({res.info["qp_solver"]}) solve p50 {solve["p50_ms"]:.3f} ms, p99 '
              f'{solve["p99_ms"]:.3f} ms, max {solve["max_ms"]:.3f} ms; control step p99 '
              f'{summary["control_step"]["p99_ms"]:.3f} ms wall, '
              f'{summary["control_step_cpu"]["p99_ms"]:.3f} ms CPU, of a {period_ms:g} ms '
              'period')
    saturated = 100 * summary['saturated_fraction']
    print(f'  control steps: {counts}; inputs at a bound {saturated:.1f} % of the time')
