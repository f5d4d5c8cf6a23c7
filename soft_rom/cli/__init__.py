"""``soft-rom <verb>``: the command-line interface.

Each verb lives in its own module ``soft_rom.cli.<verb>`` exposing ``add_parser(subparsers)``
(which registers the sub-command and its ``--help``) and ``run(args) -> int``.

One error path serves every verb (:func:`main`): an error prints one line,
``soft-rom VERB: error: WHAT WAS WRONG``, and exits with

* **2** -- usage: what was asked is wrong -- a bad or out-of-range value, an input path
  that does not exist or is of the wrong kind, an input file that is corrupt or does not
  fit the others (model file, bag, training set, mapping), an output that exists without
  ``--overwrite`` or that soft_rom did not write;
* **1** -- run time: what was asked is right but could not be done -- no permission, no
  space on the disk, not enough memory (estimated before the work starts), a solver that
  failed, an unexpected error (a bug: ``--debug`` shows where).

``--debug`` (before or after the verb) or ``SOFT_ROM_DEBUG=1`` also prints the traceback.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import errno
import importlib
import logging
import math
import os
import re
import sys
import traceback
from typing import Any, NoReturn
import warnings

from soft_rom import __version__
from soft_rom.errors import (
    ClusterError,
    ConfigError,
    ResourceError,
    SoftRomError,
    SolverError,
)

__all__ = ['main', 'VERBS', 'build_parser']

VERBS = ('simulate', 'convert', 'fit', 'evaluate', 'replay', 'control', 'study', 'demo', 'info')

USAGE, RUNTIME = 2, 1


#: What argparse takes for a negative number rather than an option: with an exponent and
#: comma lists too (``--bias -1e4``, ``--u-min -2e4,-2e4``; argparse's own takes ``-5``, ``-.5``).
_NEGATIVE = re.compile(r'^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?'
                       r'(,[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)*$')


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (usage is in ``--help``)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE

    def error(self, message: str) -> NoReturn:
        self.exit(USAGE, f'{self.prog}: error: {message} (see {self.prog} --help)\n')


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every verb registered."""
    parser = _Parser(
        prog='soft-rom',
        description='Reduced-order models of soft robots from ROS 2 bags '
                    '(LOpInf, DMDc, ERA/OKID).')
    parser.add_argument('--version', action='version', version=f'soft_rom {__version__}')
    parser.add_argument('-v', '--verbose', action='count', default=0,
                        help='more log output (-vv for debug)')
    parser.add_argument('--debug', action='store_true',
                        help='show the traceback of an error (or set SOFT_ROM_DEBUG=1)')
    sub = parser.add_subparsers(dest='verb', metavar='VERB', parser_class=_Parser)
    sub.required = True
    for verb in VERBS:
        importlib.import_module(f'soft_rom.cli.{verb}').add_parser(sub)
    for verb_parser in sub.choices.values():
        verb_parser.add_argument('-v', '--verbose', action='count', default=argparse.SUPPRESS,
                                 help='more detail (-vv for debug logging)')
        verb_parser.add_argument('--debug', action='store_true', default=argparse.SUPPRESS,
                                 help='show the traceback of an error')
    return parser


def _check_numbers(args: argparse.Namespace) -> None:
    """No option of any verb may be NaN or infinite (ranges are checked by each option)."""
    for key, value in vars(args).items():
        values = value if isinstance(value, (list, tuple)) else [value]
        for v in values:
            if isinstance(v, float) and not math.isfinite(v):
                raise _UsageError(f'argument --{key.replace("_", "-")}: must be a finite '
                                  f'number; got {v!r}')


class _UsageError(ConfigError):
    pass


def _guard_outputs(args: argparse.Namespace) -> None:
    """``--overwrite`` of verbs whose writers replace without asking: only soft_rom's outputs.

    ``convert -o OUT --overwrite`` may replace a training set, never a bag or a folder of
    someone else's.
    """
    from pathlib import Path

    from soft_rom.cli._common import is_training_set
    from soft_rom.errors import OutputExistsError

    if args.verb != 'convert' or not getattr(args, 'overwrite', False):
        return
    out = Path(args.output)
    if (out.exists() or out.is_symlink()) and not is_training_set(out):
        raise OutputExistsError(f'{out} was not written by soft_rom as a training set; refusing '
                                'to replace it (--overwrite only replaces soft_rom outputs)')


def _describe(err: BaseException) -> tuple[int, str]:
    """Exit code and one-line message for an exception raised by a verb."""
    if isinstance(err, (ResourceError, SolverError, ClusterError)):
        code, text = RUNTIME, str(err)
    elif isinstance(err, (SoftRomError, argparse.ArgumentTypeError)):
        code, text = USAGE, str(err)
    elif isinstance(err, (FileNotFoundError, FileExistsError, IsADirectoryError,
                          NotADirectoryError)):
        code = USAGE
        what = {FileNotFoundError: 'no such file or directory',
                FileExistsError: 'exists already', IsADirectoryError: 'is a directory',
                NotADirectoryError: 'is not a directory'}[type(err)] \
            if type(err) in (FileNotFoundError, FileExistsError, IsADirectoryError,
                             NotADirectoryError) else err.strerror
        text = f'{err.filename}: {what}' if err.filename else str(err)
    elif isinstance(err, OSError):
        code = RUNTIME
        what = err.strerror or str(err) or type(err).__name__
        if err.errno == errno.ENOSPC:
            what = 'no space left on the device'
        where = ': '.join(str(f) for f in (err.filename, err.filename2) if f is not None)
        text = f'{where}: {what}' if where else what
    elif isinstance(err, MemoryError):
        code, text = RUNTIME, f'out of memory ({err or "allocation failed"})'
    else:
        code = RUNTIME
        text = (f'unexpected {type(err).__name__}: {err} (a bug; run with --debug for the '
                'traceback and report it)')
    return code, ' '.join(text.split()) or type(err).__name__


def _robust_streams() -> None:
    """Never fail to print a message because of its characters (lone surrogates, ...)."""
    for stream in (sys.stdout, sys.stderr):
        reconfigure: Any = getattr(stream, 'reconfigure', None)
        if reconfigure is not None:
            try:
                reconfigure(errors='backslashreplace')
            except (ValueError, OSError):
                pass


def _logging(verbose: int) -> None:
    """soft_rom's own messages from INFO; other libraries' only from WARNING (``-vv``: all)."""
    logging.basicConfig(level=logging.DEBUG if verbose >= 2 else logging.WARNING,
                        format='%(levelname)s %(name)s: %(message)s')
    logging.getLogger('soft_rom').setLevel(logging.DEBUG if verbose >= 2 else logging.INFO)


def _show(held: list[warnings.WarningMessage]) -> None:
    for w in held:
        warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``soft-rom``; returns the process exit code."""
    _robust_streams()
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, usage errors (already printed)
        return int(exc.code or 0) if not isinstance(exc.code, str) else USAGE
    debug = bool(getattr(args, 'debug', False)) or \
        os.environ.get('SOFT_ROM_DEBUG', '').strip() not in ('', '0')
    _logging(int(getattr(args, 'verbose', 0) or 0))
    try:
        _check_numbers(args)
        _guard_outputs(args)
        from tqdm.contrib.logging import logging_redirect_tqdm
        # numpy's warnings on the way to an error (an overflow before 'diverged') would bury
        # its one line: they are held, and shown after a run that succeeds (or with --debug)
        held: list[warnings.WarningMessage] = []
        try:
            with warnings.catch_warnings(record=True) as held, logging_redirect_tqdm():
                warnings.simplefilter('default')
                code = int(args.func(args) or 0)
        except BaseException:
            if debug:
                _show(held)
            raise
        _show(held)
        return code
    except KeyboardInterrupt:
        print(f'soft-rom {args.verb}: interrupted', file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into `head` and the like
        try:
            sys.stdout = open(os.devnull, 'w')  # noqa: SIM115 -- stop further write errors
        except OSError:
            pass
        return RUNTIME
    except Exception as err:  # noqa: BLE001 -- the one error path of every verb
        code, text = _describe(err)
        if debug:
            traceback.print_exc()
        print(f'soft-rom {args.verb}: error: {text}', file=sys.stderr)
        return code


if __name__ == '__main__':  # pragma: no cover
    sys.exit(main())
