"""``soft-rom convert BAG... -o OUT.zarr``: ROS 2 bags to a chunked training set."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from soft_rom.cli._common import add_quiet

__all__ = ['add_parser', 'run']


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``convert``."""
    parser = subparsers.add_parser(
        'convert', help='convert ROS 2 bags to a training set (zarr)',
        description='Convert ROS 2 bags (sqlite3 or MCAP; one episode per bag, split at long '
                    'gaps) to a chunked training set on a uniform time grid: outputs and '
                    'states interpolated across short gaps, inputs zero-order held. A report '
                    'per topic says what was read, used, dropped (and why), interpolated, '
                    'held and split.')
    parser.add_argument('bags', nargs='+', metavar='BAG', help='bag directories (or files)')
    parser.add_argument('-o', '--output', required=True, metavar='OUT.zarr',
                        help='training set to write (atomically)')
    parser.add_argument('--mapping', metavar='YAML',
                        help='topic mapping (default: the bag contract; see '
                             'config/bag_mapping.yaml)')
    parser.add_argument('--storage', choices=('auto', 'mcap', 'sqlite3'), default='auto',
                        help='require a storage format (default: auto)')
    parser.add_argument('--dt', type=float, metavar='SECONDS',
                        help="grid step (default: the output's median period)")
    parser.add_argument('--max-gap', type=float, metavar='PERIODS',
                        help='longest stretch without output samples that is interpolated, in '
                             'output periods (default 1.5); longer gaps split the episode')
    parser.add_argument('--split-gap', type=float, metavar='SECONDS',
                        help='split where samples are further apart (overrides --max-gap)')
    parser.add_argument('--no-state', action='store_true', help='do not store full states Q')
    parser.add_argument('--overwrite', action='store_true',
                        help='replace OUT if it is a training set soft_rom wrote')
    add_quiet(parser, help='no progress bar, no line per bag (with -v, the report still)')
    parser.set_defaults(func=run)
    return parser


def run(args: argparse.Namespace) -> int:
    """Run ``convert``; returns the exit code."""
    from soft_rom.convert import convert, load_mapping
    from soft_rom.convert.report import ConversionReport

    mapping = load_mapping(args.mapping)
    changes: dict[str, Any] = {}
    for key in ('dt', 'max_gap', 'split_gap'):
        if getattr(args, key) is not None:
            changes[key] = getattr(args, key)
    if changes:
        mapping = mapping.replace(**changes)      # validated like the mapping file
    verbose = getattr(args, 'verbose', 0) > 0
    echo = None
    if verbose or not args.quiet:               # -v: the report, --quiet or not
        def echo(report: ConversionReport) -> None:
            print(report.format() if verbose else report.summary_line(), file=sys.stderr)
    ts, reports = convert(args.bags, args.output, mapping, storage=args.storage,
                          include_state=False if args.no_state else None,
                          overwrite=args.overwrite, progress=not args.quiet, echo=echo)
    n = sum(r.n_samples for r in reports)
    dt = reports[0].dt if reports else float('nan')
    states = 'no states' if ts.n_states is None else f'n = {ts.n_states} states'
    print(f'wrote {ts.path}: {len(ts)} episode(s), {n} samples at dt = {dt * 1e3:.6g} ms, '
          f'm = {len(ts.input_names)} inputs, p = {len(ts.output_names)} outputs, {states}'
          + ('' if verbose or args.quiet else
             ' (per-topic details: soft-rom convert ... --verbose)'))
    return 0
