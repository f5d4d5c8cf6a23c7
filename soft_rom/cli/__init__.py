"""``soft-rom <verb>``: the command-line interface.

Each verb lives in its own module ``soft_rom.cli.<verb>`` exposing ``add_parser(subparsers)``
(which registers the sub-command and its ``--help``) and ``run(args) -> int``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import importlib
import logging
import sys

from soft_rom import __version__
from soft_rom.errors import SoftRomError

__all__ = ['main', 'VERBS']

VERBS = ('simulate', 'convert', 'fit', 'evaluate', 'replay', 'study', 'demo', 'info')


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every verb registered."""
    parser = argparse.ArgumentParser(
        prog='soft-rom',
        description='Reduced-order models of soft robots from ROS 2 bags '
                    '(LOpInf, DMDc, ERA/OKID).')
    parser.add_argument('--version', action='version', version=f'soft_rom {__version__}')
    parser.add_argument('-v', '--verbose', action='count', default=0,
                        help='more log output (-vv for debug)')
    sub = parser.add_subparsers(dest='verb', metavar='VERB')
    sub.required = True
    for verb in VERBS:
        name = f'soft_rom.cli.{verb}'
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as err:
            if err.name != name:
                raise
            continue
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``soft-rom``; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose + 1, 2),
        format='%(levelname)s %(name)s: %(message)s')
    try:
        return int(args.func(args) or 0)
    except (SoftRomError, FileNotFoundError, FileExistsError) as err:
        print(f'soft-rom {args.verb}: error: {err}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f'soft-rom {args.verb}: interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':  # pragma: no cover
    sys.exit(main())
