"""``soft-rom info PATH``: describe a ROS 2 bag, a training set or a model file."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

from soft_rom.cli._common import a_path
from soft_rom.errors import ConfigError

__all__ = ['add_parser', 'describe', 'run']


def _json_target(text: str) -> str | Path:
    """``--json``'s value: ``-`` (standard output) or a path, not an empty string."""
    return '-' if text == '-' else a_path(text)


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``info``."""
    parser = subparsers.add_parser(
        'info', help='describe a bag, a training set or a model file',
        description='Describe a ROS 2 bag (topics, types, counts, rates, duration), a training '
                    'set (episodes, names, units, shapes) or a model file (method, r, dt, '
                    'names, units, stability margin, metadata).')
    parser.add_argument('paths', type=a_path, nargs='*', metavar='PATH')
    parser.add_argument('--json', type=_json_target, nargs='?', const='-', default=None,
                        metavar='FILE',
                        help='write JSON instead of text to FILE (default, or -: standard '
                             'output)')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace the --json FILE if soft-rom info wrote it')
    parser.add_argument('--strict', action='store_true',
                        help='exit 2 if a model file cannot be trusted')
    parser.set_defaults(func=run)
    return parser


def describe(path: str | Path) -> dict[str, Any]:
    """``{'kind': 'bag' | 'trainingset' | 'model', ...}`` for ``path``."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f'{p} does not exist.')
    if p.is_file() and p.suffix == '.npz':
        from soft_rom.models import load_model
        model = load_model(p)
        head = model.header()
        head.pop('format', None)
        return {'kind': 'model', 'path': str(p), **head, 'trust': model.trust_issues()}
    if p.is_dir() and ((p / '.zattrs').exists() or (p / 'zarr.json').exists()):
        from soft_rom.dataset import TrainingSet
        return {'kind': 'trainingset', **TrainingSet.open(p).describe()}
    from soft_rom.bags.reader import describe_bag, is_bag
    if is_bag(p):
        return {'kind': 'bag', **describe_bag(p)}
    raise ConfigError(f'{p} is neither a ROS 2 bag, a training set (.zarr) nor a model file '
                       '(.npz).')


def _fmt_names(names: list[str], units: list[str]) -> str:
    items = [f'{n} [{u}]' if u else n for n, u in zip(names, units)]
    if len(items) > 8:
        items = items[:4] + ['...'] + items[-2:]
    return ', '.join(items)


def _fmt_stamp(ns: int) -> str:
    """An integer stamp in ns, with its UTC date when it looks like epoch time."""
    import datetime

    ns = int(ns)
    if ns > 946_684_800 * 10 ** 9:                 # after 2000-01-01: an epoch stamp
        when = datetime.datetime.fromtimestamp(ns // 10 ** 9, tz=datetime.timezone.utc)
        return f"{ns} ns ({when.strftime('%Y-%m-%d %H:%M:%S')}.{ns % 10 ** 9:09d} UTC)"
    return f'{ns} ns'


def format_text(d: dict[str, Any]) -> str:
    """Human-readable form of :func:`describe`."""
    kind = d['kind']
    lines = []
    if kind == 'bag':
        lines.append(f"bag {d['path']} ({d['storage']}): {d['message_count']} messages, "
                     f"{d['duration_s']:.3f} s ({d['start_s']:.6f} .. {d['end_s']:.6f} s)")
        width = max([len(t) for t in d['topics']] + [5])
        for topic, info in d['topics'].items():
            rate = info['rate_hz']
            rate_s = f'{rate:9.2f} Hz' if math.isfinite(rate) else '        - Hz'
            lines.append(f"  {topic:{width}s}  {info['type']:36s} {info['count']:8d} msgs "
                         f'{rate_s}')
    elif kind == 'trainingset':
        sums = d.get('checksums')
        lines.append(f"training set {d['path']} (format {d['format_version']}, "
                     + (f'checksums: {sums}' if sums else 'no checksums') + '): '
                     f"{len(d['episodes'])} episode(s), n = {d['n_states']}; every chunk of "
                     'every array present' + (' and matching its checksum' if sums else ''))
        if not sums:
            lines.append('  (written before soft_rom stored checksums: a changed byte is not '
                         'detected; convert the bags again to add them)')
        lines.append(f"  inputs  (m = {len(d['input_names'])}): "
                     f"{_fmt_names(d['input_names'], d['input_units'])}")
        lines.append(f"  outputs (p = {len(d['output_names'])}): "
                     f"{_fmt_names(d['output_names'], d['output_units'])}")
        for name, ep in d['episodes'].items():
            q = 'no Q' if ep['Q'] is None else f"Q {ep['Q'][0]} x {ep['Q'][1]} " \
                f"(chunks {ep['Q_chunks'][0]} x {ep['Q_chunks'][1]})"
            lines.append(f"  {name}: {ep['n_samples']} samples, {ep['duration_s']:.6f} s from "
                         f"t0 = {_fmt_stamp(ep['t0_ns'])}, dt = {ep['dt_mean'] * 1e3:.6g} ms, "
                         f'{q}' + (f", from {ep['source']}" if ep.get('source') else ''))
    else:
        lines.append(f"model {d['path']}: {d['class']} (method {d['method']}), r = {d['r']}, "
                     f"state dimension {d['n_states']}, dt = {d['dt']:g} s")
        lines.append(f"  inputs  (m = {len(d['input_names'])}): "
                     f"{_fmt_names(d['input_names'], d['input_units'])}")
        lines.append(f"  outputs (p = {len(d['output_names'])}): "
                     f"{_fmt_names(d['output_names'], d['output_units'])}")
        margin = d['stability_margin']
        margin = float('nan') if margin is None else margin
        lines.append(f'  stability margin 1 - max|eig(A)| = {margin:.3e} '
                     f"({'stable' if margin > 0 else 'NOT asymptotically stable'})")
        pot = d.get('potential')
        if isinstance(pot, dict):          # cubic LOpInf: restoring force = grad of V(q)
            n = pot.get('independent_entries', {})
            lines.append(f"  forces: cubic, {pot.get('form')}; independent entries K "
                         f"{n.get('K')}, G {n.get('G')}, H {n.get('H')}; |K| = "
                         f"{pot.get('norm_K', 0):.3g}, |G| = {pot.get('norm_G', 0):.3g}, "
                         f"|H| = {pot.get('norm_H', 0):.3g} (margin: linearization at q = 0)")
        trust = d.get('trust') or []
        lines.append('  trust: ' + ('ok' if not trust else 'NOT TRUSTED: ' + '; '.join(trust)))
        meta = d.get('metadata') or {}
        diag = meta.get('diagnostics') if isinstance(meta, dict) else None
        mode = diag.get('least_damped_mode') if isinstance(diag, dict) else None
        if isinstance(mode, dict) and 'damping_ratio' in mode:
            lines.append(f"  least-damped mode: {mode.get('frequency_hz', float('nan')):.4g} Hz, "
                         f"damping ratio {mode['damping_ratio']:.4g}")
        ref = diag.get('refinement') if isinstance(diag, dict) else None
        if isinstance(ref, dict) and ref.get('criterion') == 'output-error':
            lines.append(f"  refined by output error: {ref.get('iterations')} iterations "
                         f"({ref.get('status')}), training simulation error "
                         f"-{100 * float(ref.get('improvement', 0.0)):.1f} %")
        held = meta.get('held_out') if isinstance(meta, dict) else None
        if isinstance(held, dict) and 'deviation_error' in held:
            # what the predictor's monitor thresholds come from (README, Monitoring)
            lines.append(f"  held-out deviation error {float(held['deviation_error']):.4g} "
                         f"({held.get('data', 'data it was not fitted on')})")
        if meta:
            text = json.dumps(meta, sort_keys=True, default=str)
            lines.append('  metadata: ' + (text if len(text) <= 400 else text[:400] + ' ...'))
    return '\n'.join(lines)


_INFO_JSON_KEYS = ('kind',)


def run(args: argparse.Namespace) -> int:
    """Run ``info``; returns the exit code."""
    from soft_rom.cli._common import check_apart, dumps_strict, is_summary_json, write_text_output

    paths = list(args.paths)
    if not paths and args.json not in (None, '-'):
        paths, args.json = [args.json], '-'   # ``info --json PATH`` (the old flag form)
    if not paths:
        raise ConfigError('give at least one PATH (bag, training set or model file)')
    out = [describe(p) for p in paths]
    if args.json is not None:
        text = dumps_strict(out if len(out) > 1 else out[0], indent=2, default=str)
        if args.json == '-':
            print(text)
        else:
            check_apart(Path(args.json), '--json', [('input', Path(p)) for p in paths])
            write_text_output(Path(args.json), text + '\n', overwrite=args.overwrite,
                              what='info JSON', is_ours=is_summary_json(_INFO_JSON_KEYS))
    else:
        print('\n'.join(format_text(d) for d in out))
    untrusted = [d['path'] for d in out if d.get('kind') == 'model' and d.get('trust')]
    if args.strict and untrusted:
        raise ConfigError(f'model file(s) cannot be trusted: {", ".join(untrusted)}')
    return 0
