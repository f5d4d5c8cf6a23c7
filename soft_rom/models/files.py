"""Model files: format constants, physical checks, the class registry and :func:`load_model`.

The reader knows no model class: each class registers itself (:func:`register_model_class`)
with the arrays it needs and a constructor hook, and :func:`read_model` builds the class a
file names (:func:`soft_rom.models.load_model` is it, typed). The bounded reading of the
archive and of the JSON document is :mod:`soft_rom.models.archive`.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import DimensionError, ModelFileError
from soft_rom.models.archive import _fail, parse_json, read_archive

__all__ = [
    'FORMAT_NAME',
    'FORMAT_VERSION',
    'MAX_STATES',
    'check_arrays',
    'check_header',
    'file_sha256',
    'read_model',
    'register_model_class',
]

FORMAT_NAME = 'soft_rom.model'
FORMAT_VERSION = 1
#: Versions the loader reads: 1 (linear models), 2 (adds the cubic LOpInf model's tensors);
#: a class declares the newest version its files may have (``_format_version``, default 1).
READ_VERSIONS = (1, 2)
_META_KEY = '__metadata__'
#: Largest state dimension of a model file: r <= 256 for DMDc/ERA, r <= 128 for LOpInf
#: (loading, discretizing and the trust checks then stay well under a second).
MAX_STATES = 256

#: Sample times a model file may declare, seconds.
DT_RANGE = (1e-9, 1e4)
#: Largest magnitude of a matrix entry in a model file.
MAX_ABS_ENTRY = 1e150
#: Largest magnitude of an output offset ``y_ref`` a model file may hold.
MAX_ABS_OFFSET = 1e12
_MAX_NAME = 256


def _text_ok(value: str) -> bool:
    return len(value) <= _MAX_NAME and not any(ord(c) < 32 or ord(c) == 127 for c in value)


def check_header(path: str | os.PathLike[str], header: Any) -> dict[str, Any]:
    """Check the physical fields of a model file's metadata; returns the constructor kwargs.

    Returns ``{'dt', 'input_names', 'output_names', 'input_units', 'output_units',
    'metadata', 'method'}``; raises :class:`~soft_rom.errors.ModelFileError` naming the
    first field that is wrong.
    """
    path = Path(path)
    if not isinstance(header, dict):
        raise _fail(path, 'metadata is not a JSON object.')
    dt = header.get('dt')
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not math.isfinite(dt):
        raise _fail(path, f'metadata dt must be a finite number of seconds; got '
                          f'{str(dt)[:40]}.')
    if not DT_RANGE[0] <= dt <= DT_RANGE[1]:
        raise _fail(path, f'metadata dt = {dt:g} s is outside the plausible range '
                          f'[{DT_RANGE[0]:g}, {DT_RANGE[1]:g}] s.')
    kwargs: dict[str, Any] = {'dt': float(dt)}
    for key in ('input_names', 'output_names', 'input_units', 'output_units'):
        value = header.get(key)
        if value is not None and (not isinstance(value, list) or not all(
                isinstance(v, str) and _text_ok(v) for v in value)):
            raise _fail(path, f'metadata {key!r} must be a list of strings of at most '
                              f'{_MAX_NAME} printable characters.')
        kwargs[key] = value
    method = header.get('method', 'discrete')
    if not isinstance(method, str) or not method or not _text_ok(method) or len(method) > 32:
        raise _fail(path, 'metadata method must be a short name.')
    kwargs['method'] = method
    meta = header.get('metadata') or {}
    if not isinstance(meta, dict):
        raise _fail(path, 'metadata "metadata" must be a JSON object.')
    kwargs['metadata'] = meta
    for key in ('r', 'n_states'):
        value = header.get(key)
        if value is not None and (type(value) is not int or value < 1):
            raise _fail(path, f'metadata {key} must be a positive integer; got '
                              f'{str(value)[:40]}.')
    return kwargs


def check_arrays(path: str | os.PathLike[str], arrays: dict[str, NDArray[Any]]) -> None:
    """Refuse NaN, Inf and implausible magnitudes in the arrays of a model file."""
    path = Path(path)
    for name, arr in arrays.items():
        if arr.size == 0:
            continue
        with np.errstate(invalid='ignore'):
            peak = float(np.max(np.abs(arr)))
        if not math.isfinite(peak):
            raise _fail(path, f'array {name!r} contains NaN or Inf.')
        limit = MAX_ABS_OFFSET if name == 'y_ref' else MAX_ABS_ENTRY
        if peak > limit:
            raise _fail(path, f'array {name!r} holds a value of magnitude {peak:.3g}, beyond '
                              f'the plausible {limit:g}.')


_CLASSES: dict[str, Any] = {}

_M = TypeVar('_M', bound=type)


def register_model_class(cls: _M) -> _M:
    """Let :func:`load_model` read files of ``cls`` (usable as a class decorator).

    The file's ``class`` field is ``cls.__name__``; the loader accepts exactly the arrays
    ``cls._matrix_names`` (plus any of ``cls._optional_matrices``) and ``y_ref``, and builds
    the model with ``cls._from_file(arrays, **common)``. The reader imports no model class:
    ``cls`` is checked for those hooks only.
    """
    hooks = ('_matrix_names', '_optional_matrices', '_file_methods', '_from_file', 'save')
    if not (isinstance(cls, type) and all(hasattr(cls, h) for h in hooks)):
        raise TypeError('register_model_class needs a LinearROM subclass')
    _CLASSES[cls.__name__] = cls
    return cls


def file_sha256(path: str | os.PathLike[str]) -> str:
    """Hex SHA-256 of a file (reported by the predictor node as the model's identity)."""
    h = hashlib.sha256()
    with open(path, 'rb') as fh:
        for block in iter(lambda: fh.read(1 << 20), b''):
            h.update(block)
    return h.hexdigest()


def _header_of(path: Path, meta_arr: NDArray[Any]) -> dict[str, Any]:
    """The metadata document of a model file, which must declare the model format."""
    if meta_arr.dtype != np.uint8 or meta_arr.ndim != 1:
        raise ModelFileError(f'{path}: metadata entry must be a 1-D uint8 array.')
    header = parse_json(path, meta_arr.tobytes())
    if not isinstance(header, dict) or header.get('format') != FORMAT_NAME:
        raise ModelFileError(f'{path}: metadata does not declare format {FORMAT_NAME!r}.')
    return header


def _check_version(path: Path, header: dict[str, Any]) -> int:
    version = header.get('format_version')
    if not isinstance(version, int) or isinstance(version, bool):
        raise ModelFileError(f'{path}: model file format version must be an integer; got '
                             f'{json.dumps(version)[:30]}.')
    if version not in READ_VERSIONS:
        raise ModelFileError(
            f'{path}: model file format version {str(version)[:20]} is not supported by this '
            f'soft_rom (it reads versions {", ".join(map(str, READ_VERSIONS))}); upgrade '
            'soft_rom or re-export the model.')
    return version


def read_model(path: str | os.PathLike[str], *, strict: bool = False) -> Any:
    """The model a file holds, of the registered class it names (see ``load_model``).

    :func:`soft_rom.models.load_model` is this, typed; the reader knows the classes only
    through the registry.
    """
    path = Path(path)
    if not os.path.lexists(path):
        raise FileNotFoundError(f'model file not found: {path}')
    if not path.is_file():
        raise ModelFileError(f'{path}: not a regular file.')
    allowed = {_META_KEY, 'y_ref'}
    for known in _CLASSES.values():
        allowed.update(known._matrix_names, known._optional_matrices)

    def newer(meta: NDArray[Any]) -> None:
        """Arrays this version does not know: say so if the metadata is of a newer one."""
        try:
            header = _header_of(path, meta)
        except ModelFileError:
            return
        version = _check_version(path, header)
        cls = _CLASSES.get(str(header.get('class'))[:100])
        if cls is None:
            raise ModelFileError(f'{path}: unknown model class '
                                 f'{str(header.get("class"))[:60]!r} (a newer soft_rom may '
                                 'read it).')
        _check_class_version(path, cls, version)

    raw = read_archive(path, allowed, first=_META_KEY, explain=newer)
    header = _header_of(path, raw.pop(_META_KEY))
    cls, common = _class_and_fields(path, header, raw)
    model = _build(path, cls, raw, header, common)
    if strict and not model.trusted:
        raise ModelFileError(f'{path}: the model cannot be trusted: '
                             f'{"; ".join(model.trust_issues())} (strict mode refuses it).')
    return model


def _check_class_version(path: Path, cls: Any, version: int) -> None:
    cls_version = int(getattr(cls, '_format_version', FORMAT_VERSION))
    if version > cls_version:
        raise ModelFileError(f'{path}: a {cls.__name__} file of format version {version} is '
                             f'newer than this soft_rom reads (at most {cls_version}); upgrade '
                             'soft_rom or re-export the model.')


def _class_and_fields(path: Path, header: dict[str, Any], raw: dict[str, NDArray[Any]]
                      ) -> tuple[Any, dict[str, Any]]:
    """The registered class a file names and its checked constructor fields."""
    version = _check_version(path, header)
    cls = _CLASSES.get(str(header.get('class'))[:100])
    if cls is None:
        raise ModelFileError(f'{path}: unknown model class {str(header.get("class"))[:60]!r}.')
    _check_class_version(path, cls, version)
    needed = set(cls._matrix_names) | {'y_ref'}
    if not needed <= set(raw) <= needed | set(cls._optional_matrices):
        raise ModelFileError(
            f'{path}: {cls.__name__} needs arrays {sorted(needed)}; found {sorted(raw)}.')
    common = check_header(path, header)
    if cls._file_methods and 'method' not in header:      # none declared: the class's own
        common['method'] = cls._file_methods[0]
    if cls._file_methods and common['method'] not in cls._file_methods:
        raise ModelFileError(f'{path}: a {cls.__name__} cannot have method '
                             f'{common["method"]!r} (its method is '
                             f'{" or ".join(map(repr, cls._file_methods))}): the file\'s '
                             'class and method disagree.')
    for name, arr in raw.items():
        if arr.ndim > (1 if name == 'y_ref' else 3):
            raise ModelFileError(f'{path}: array {name!r} has {arr.ndim} dimensions.')
    check_arrays(path, raw)
    return cls, common


def _build(path: Path, cls: Any, raw: dict[str, NDArray[Any]],
           header: dict[str, Any], common: dict[str, Any]) -> Any:
    """The model of ``cls`` from checked arrays; its sizes and native system checked too."""
    y_ref = raw.pop('y_ref')
    try:
        model = cls._from_file(raw, y_ref=y_ref, **common)
        n, m, p = model.n_states, model.n_inputs, model.n_outputs
        if not 1 <= n <= MAX_STATES:
            raise DimensionError(f'{n} states; a model file holds 1 to {MAX_STATES}')
        if m < 1 or p < 1:
            raise DimensionError(f'{m} inputs and {p} outputs; needs at least one of each')
        for key, value in (('r', model.r), ('n_states', n)):
            if header.get(key) is not None and header[key] != value:
                raise DimensionError(f'metadata says {key}={header[key]}, arrays give {value}')
        model.system  # noqa: B018  (discretize now: an unusable model is refused here)
    except (DimensionError, ValueError, TypeError, KeyError) as err:
        raise ModelFileError(f'{path}: inconsistent model file: {err}') from None
    return model
