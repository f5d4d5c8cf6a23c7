"""``soft-rom convert BAG... -o OUT.zarr``: ROS 2 bags to a chunked training set."""

from __future__ import annotations

import argparse
import sys

__all__ = ['add_parser', 'run']


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``convert``."""
    parser = subparsers.add_parser(
        'convert', help='convert ROS 2 bags to a training set (zarr)',
        description='Convert ROS 2 bags (sqlite3 or MCAP; one episode per bag) to a chunked '
                    'training set. Inputs are zero-order held onto the output/state stamps; a '
                    'report per topic says what was read, used, dropped (and why) and filled.')
    parser.add_argument('bags', nargs='+', metavar='BAG', help='bag directories (or files)')
    parser.add_argument('-o', '--output', required=True, metavar='OUT.zarr',
                        help='training set to write (atomically)')
    parser.add_argument('--mapping', metavar='YAML',
                        help='topic mapping (default: the bag contract; see '
                             'config/bag_mapping.yaml)')
    parser.add_argument('--storage', choices=('auto', 'mcap', 'sqlite3'), default='auto',
                        help='require a storage format (default: auto)')
    parser.add_argument('--split-gap', type=float, metavar='SECONDS',
                        help='split a bag into episodes where samples are further apart')
    parser.add_argument('--dt', type=float, help='resample to this uniform step (s)')
    parser.add_argument('--no-state', action='store_true', help='do not store full states Q')
    parser.add_argument('--overwrite', action='store_true', help='replace OUT if it exists')
    parser.add_argument('--quiet', action='store_true', help='no progress bar, no report')
    parser.set_defaults(func=run)
    return parser


def run(args: argparse.Namespace) -> int:
    """Run ``convert``; returns the exit code."""
    from soft_rom.convert import convert, load_mapping

    mapping = load_mapping(args.mapping)
    changes = {}
    if args.split_gap is not None:
        changes['split_gap'] = args.split_gap
    if args.dt is not None:
        changes['dt'] = args.dt
    if changes:
        mapping = mapping.replace(**changes)
    mapping = type(mapping).from_dict(_as_yaml_dict(mapping)) if changes else mapping
    echo = None if args.quiet else (lambda text: print(text, file=sys.stderr))
    ts, reports = convert(args.bags, args.output, mapping, storage=args.storage,
                          include_state=False if args.no_state else None,
                          overwrite=args.overwrite, progress=not args.quiet, echo=echo)
    n = sum(r.n_samples for r in reports)
    print(f'wrote {ts.path}: {len(ts)} episode(s), {n} samples, m = {len(ts.input_names)}, '
          f'p = {len(ts.output_names)}, n = {ts.n_states}')
    return 0


def _as_yaml_dict(mapping: object) -> dict:
    """Round trip through the YAML structure so option values are validated."""
    d = mapping.to_dict()  # type: ignore[attr-defined]
    inputs = {}
    if d['inputs'] is not None:
        inputs['sources'] = [{'topic': s['topic'], 'indices': s['indices']}
                             for s in d['inputs']]
    for key in ('input_names', 'input_units'):
        if d[key] is not None:
            inputs[key.split('_')[1]] = d[key]
    inputs['scale'] = d['scale']
    inputs['offset'] = d['offset']
    return {'inputs': inputs, 'output': d['output'], 'state': d['state'],
            'time': {k: d[k] for k in ('stamps', 'match_tolerance', 'dt', 'split_gap')}}
