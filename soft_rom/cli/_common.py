"""Helpers shared by the CLI verbs: one grammar for options, validated numbers, resources.

Every verb spells the same thing the same way:

* ``-o/--output PATH`` for what it writes (``--out`` is kept as a hidden alias for one
  release where it existed: ``simulate``, ``study``, ``demo``), ``--overwrite`` to replace
  an output soft_rom wrote before;
* ``--quiet`` to hide progress bars (``--no-progress`` is a hidden alias on every verb
  that has ``--quiet``);
* ``--json FILE`` to also write a machine-readable summary (``--summary-json`` is a
  hidden alias on every verb that has it: ``fit``, ``evaluate``, ``replay``);
* ``-v/--verbose`` for more detail, ``--debug`` to show the traceback of an error (or
  ``SOFT_ROM_DEBUG=1``), before or after the verb.

Numbers are checked by the ``type=`` of their option (:func:`finite_float`,
:func:`int_range`), so that a bad value is a usage error before any work starts.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
import errno
import json
import math
import os
from pathlib import Path
from typing import Any

from soft_rom.resources import available_memory

__all__ = [
    'a_path',
    'add_json',
    'add_output',
    'add_quiet',
    'available_memory',
    'check_apart',
    'check_model_matches_data',
    'check_writable_folder',
    'dumps_strict',
    'enclosing_data',
    'finite_float',
    'int_range',
    'is_model_file',
    'is_summary_json',
    'is_training_set',
    'list_items',
    'parse_r_list',
    'write_text_output',
]


def list_items(text: str, what: str) -> list[str]:
    """The comma-separated items of ``text``, stripped; an empty one (``'1,,2'``) is refused.

    A typo that drops a value must not pass for a shorter list.
    """
    items = [v.strip() for v in text.split(',')]
    if len(items) > 1 and not all(items):
        raise argparse.ArgumentTypeError(f'{what} {text!r} has an empty item; separate the '
                                         'values with single commas')
    return [v for v in items if v]


def parse_r_list(text: str, what: str = 'r') -> tuple[int, ...]:
    """Parse ``'16'``, ``'4,8,16'`` or ``'2:22:2'`` (inclusive stop) into a tuple of ints."""
    usage = 'give --r as N, N,M,... or START:STOP[:STEP] (stop included), e.g. --r 4:12:4'
    if ':' not in text:
        list_items(text, f'the {what} values')
    try:
        if ':' in text:
            parts = [int(p) for p in text.split(':')]
            if len(parts) not in (2, 3):
                raise ValueError
            start, stop = parts[0], parts[1]
            step = parts[2] if len(parts) == 3 else 1
        else:
            values = tuple(int(p) for p in text.split(',') if p.strip())
    except ValueError as err:
        raise argparse.ArgumentTypeError(f'{text!r} is not a list of r values: {usage}') from err
    if ':' in text:
        if step < 1:
            raise argparse.ArgumentTypeError(f'range {text}: the step must be at least 1')
        if stop < start:
            raise argparse.ArgumentTypeError(f'range {text} is empty: start must be below '
                                             f'stop (e.g. --r {stop}:{start}:{step})')
        if stop - start > 100_000:
            raise argparse.ArgumentTypeError(f'range {text} is too long: r is at most 10000')
        values = tuple(range(start, stop + 1, step))
    if not values:
        raise argparse.ArgumentTypeError(f'no r value in {text!r}: {usage}')
    if min(values) < 1:
        raise argparse.ArgumentTypeError(f'{what} values must be positive integers; got '
                                         f'{text!r}')
    if max(values) > 10_000:
        raise argparse.ArgumentTypeError(f'{what} values must be at most 10000; got {text!r}')
    if len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f'r values repeat in {text!r}: give each once')
    return values


def _range_text(lo: float | None, hi: float | None, lo_open: bool, hi_open: bool) -> str:
    if lo is not None and hi is not None:
        return f'in {"(" if lo_open else "["}{lo:g}, {hi:g}{")" if hi_open else "]"}'
    if lo is not None:
        return f'{">" if lo_open else ">="} {lo:g}'
    if hi is not None:
        return f'{"<" if hi_open else "<="} {hi:g}'
    return 'finite'


def finite_float(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False,
                 hi_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type`` accepting finite floats in a range (bounds inclusive by default)."""
    want = _range_text(lo, hi, lo_open, hi_open)

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'expected a number; got {text!r}') from None
        ok = math.isfinite(value)
        if ok and lo is not None:
            ok = value > lo if lo_open else value >= lo
        if ok and hi is not None:
            ok = value < hi if hi_open else value <= hi
        if not ok:
            raise argparse.ArgumentTypeError(f'must be a finite number {want}; got {text!r}')
        return value

    parse.__name__ = 'number'
    return parse


def int_range(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """An argparse ``type`` accepting integers in ``[lo, hi]``."""
    want = _range_text(lo, hi, False, False).replace('finite', 'an integer')

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'expected an integer; got {text!r}') from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f'must be an integer {want}; got {text!r}')
        return value

    parse.__name__ = 'integer'
    return parse


def a_path(text: str) -> Path:
    """An argparse ``type``: a path, not an empty string (``-o ""`` meant the working folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError('an empty path; give a file or folder name')
    return Path(text)


def add_output(parser: argparse.ArgumentParser, *, help: str, default: Path | None = None,
               required: bool = False, metavar: str = 'PATH', old: bool = False) -> None:
    """``-o/--output`` (and, with ``old``, the hidden alias ``--out``)."""
    if default is not None:
        help = f'{help} (default: {default})'
    parser.add_argument('-o', '--output', type=a_path, default=default, required=required,
                        metavar=metavar, help=help)
    if old:
        parser.add_argument('--out', type=a_path, dest='output', help=argparse.SUPPRESS)


def add_quiet(parser: argparse.ArgumentParser, *, help: str = 'no progress bars',
              old: bool = True) -> None:
    """``--quiet`` and its hidden alias ``--no-progress`` (kept for one release)."""
    parser.add_argument('--quiet', action='store_true', help=help)
    if old:
        parser.add_argument('--no-progress', action='store_true', dest='quiet',
                            help=argparse.SUPPRESS)


def add_json(parser: argparse.ArgumentParser, *, help: str,
             old: str | None = '--summary-json') -> None:
    """``--json FILE`` and its hidden alias ``--summary-json`` (kept for one release)."""
    parser.add_argument('--json', type=a_path, default=None, metavar='FILE', help=help)
    if old:
        parser.add_argument(old, type=Path, dest='json', help=argparse.SUPPRESS)


def is_summary_json(keys: Sequence[str]) -> Callable[[Path], bool]:
    """A check that a file is a ``--json`` summary soft_rom wrote.

    The file holds rows (or one object) with all of ``keys``; for
    :func:`soft_rom.outputs.check_output`.
    """

    def check(path: Path) -> bool:
        try:
            if path.stat().st_size > 64 * 2**20:
                return False
            data = json.loads(path.read_text(encoding='utf-8'))
        except (OSError, ValueError, RecursionError):
            return False
        items = data if isinstance(data, list) else [data]
        return bool(items) and all(isinstance(d, dict) and all(k in d for k in keys)
                                   for d in items)
    return check


def is_model_file(path: Path) -> bool:
    """Whether ``path`` is a model file soft_rom wrote (it loads)."""
    from soft_rom.errors import ModelFileError
    from soft_rom.models import load_model
    try:
        load_model(path)
    except (ModelFileError, OSError):
        return False
    return True


def check_writable_folder(folder: Path, what: str) -> None:
    """Refuse early (before any work) an output folder that is a file or cannot be written."""
    from soft_rom.errors import ConfigError

    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        raise ConfigError(f'{probe} is not a folder; cannot write the {what} there')
    if not os.access(probe, os.W_OK | os.X_OK):
        raise PermissionError(errno.EACCES, f'cannot write the {what} here (permission denied)',
                              str(probe))


def check_apart(path: Path, option: str, others: Sequence[tuple[str, Path]]) -> None:
    """Refuse early an output ``path`` that is, holds or sits inside another path of the run.

    ``others``: ``(what, path)`` pairs (the inputs and the other outputs), e.g.
    ``[('output bag', out), ('input bag', bag)]``.
    """
    from soft_rom.errors import ConfigError

    mine = path.resolve()
    for what, other in others:
        theirs = Path(other).resolve()
        if mine == theirs or theirs in mine.parents or mine in theirs.parents:
            raise ConfigError(f'{option} {path} would replace or sit inside the {what} '
                              f'{other}; choose another {option}')


def write_text_output(path: Path, text: str, *, overwrite: bool, what: str,
                      is_ours: Callable[[Path], bool]) -> None:
    """Write one text output atomically, replacing only a file soft_rom wrote."""
    from soft_rom.outputs import atomic_files

    with atomic_files([path], overwrite=overwrite, what=what, is_ours=is_ours) as staged:
        staged[path].write_text(text, encoding='utf-8')


def enclosing_data(path: Path) -> tuple[str, Path] | None:
    """The bag or training set that ``path`` is or sits inside (``('bag', p)``), if any."""
    from soft_rom.bags.reader import is_bag

    for p in (path.resolve(), *path.resolve().parents):
        if p.is_dir() and is_bag(p):
            return 'bag', p
        if is_training_set(p):
            return 'training set', p
    return None


def is_training_set(path: Path) -> bool:
    """Whether ``path`` is a training set soft_rom wrote (marker, or its zarr attributes)."""
    from soft_rom.dataset.writer import KIND
    from soft_rom.outputs import is_marked

    if not path.is_dir() or path.is_symlink():
        return False
    if is_marked(path, (KIND,)):                 # 'trainingset' (the zarr attributes below)
        return True
    for name, key in (('.zattrs', None), ('zarr.json', 'attributes')):
        attrs_file = path / name
        try:
            if not attrs_file.is_file() or attrs_file.stat().st_size > 64 * 2**20:
                continue
            attrs = json.loads(attrs_file.read_text(encoding='utf-8'))
        except (OSError, ValueError, RecursionError):
            continue
        if key is not None and isinstance(attrs, dict):
            attrs = attrs.get(key)
        if isinstance(attrs, dict) and attrs.get('format') == 'soft_rom.trainingset':
            return True
    return False


def _units_text(units: Sequence[str]) -> str:
    """``'Pa'`` when every channel has that unit, else the list."""
    return units[0] if len(set(units)) == 1 else str(list(units))


def check_model_matches_data(model: Any, label: str, data: str, *, counts: tuple[int, int],
                             input_units: Sequence[str] | None,
                             output_units: Sequence[str] | None,
                             layout: Any | None) -> None:
    """Refuse data whose input/output counts, units or output layout differ from the model's.

    ``counts``: the data's numbers of inputs and outputs (0 outputs: none recorded, accepted).

    The counts may agree while the numbers mean something else (kPa fed to a model fitted
    in Pa, a point-major or ``xy`` centerline to a component-major ``xz`` model): the
    errors would be computed, and wrong. Units unknown on either side (empty) are not
    compared; the layout only when both are known.

    Parameters
    ----------
    model : LinearROM
        The loaded model (``input_units``, ``output_units``, ``output_names``, metadata).
    label : str
        How the model is named in the message (its path).
    data : str
        What the data are (``'the training set x.zarr'``, ``'the bag run3'``).
    input_units, output_units : sequence of str, optional
        The data's units, one per channel.
    layout : OutputLayout, optional
        The data's output layout.
    """
    from soft_rom.errors import ConfigError, DimensionError
    from soft_rom.layout import layout_of

    m, p = counts
    if model.n_inputs != m or p not in (0, model.n_outputs):
        raise DimensionError(
            f'{label}: the model has {model.n_inputs} inputs and {model.n_outputs} outputs but '
            f'{data} has {m} inputs and {p} outputs; use data of the same layout.')
    for kind, mine, theirs in (('inputs', list(model.input_units), input_units),
                               ('outputs', list(model.output_units), output_units)):
        if theirs is None or len(theirs) != len(mine):
            continue
        if any(a and b and a != b for a, b in zip(mine, theirs)):
            raise ConfigError(
                f"{label}: the model's {kind} are in {_units_text(mine)} but those of {data} "
                f'are in {_units_text(list(theirs))}; convert the data with the units (and '
                'scale) the model was fitted with.')
    ours = layout_of(model.metadata, model.output_names)
    if ours is not None and layout is not None and ours != layout:
        raise ConfigError(
            f'{label}: the model outputs {ours.describe()} but {data} has '
            f'{layout.describe()}; convert the data with the output mapping the model was '
            'fitted with.')


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def dumps_strict(obj: Any, **kwargs: Any) -> str:
    """``json.dumps`` that writes strict JSON: NaN and infinities become ``null``.

    Python's ``json`` writes them as ``NaN`` / ``Infinity``, which strict parsers (jq,
    JavaScript, most languages' JSON libraries) refuse; an error that cannot be computed
    (a segment with no samples, a model that blew up) is then ``null``.
    """
    return json.dumps(_finite(obj), allow_nan=False, **kwargs)
