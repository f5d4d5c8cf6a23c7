"""Model files: the safe archive reader and :func:`load_model`; bounded cost, no code.

A model file is a zip archive (``.npz``) of ``.npy`` members. :func:`read_archive` reads
one without :func:`numpy.load`, so that every size is checked before anything is read:

1. the file size, then the zip central directory: the number of entries, their names
   (only the names the caller allows, no duplicates), the compression method (stored or
   deflate), the encryption flag and the declared uncompressed sizes (their total at most
   :data:`MAX_ARCHIVE_BYTES`);
2. each member's ``.npy`` header (magic, version, at most :data:`MAX_HEADER_BYTES`,
   parsed as a literal, not evaluated): the dtype must be a plain float (or ``uint8`` for
   the metadata entry), at most 3 dimensions, and the shape must account for exactly the
   member's declared size -- a header cannot declare more data than the archive holds;
3. only then the data, exactly that many bytes (the zip CRC is checked on the way).

:func:`parse_json` reads the metadata document with a size limit, a nesting depth limit,
bounded integers, no NaN/Infinity and no strings that cannot be encoded as UTF-8.

Anything else -- a truncated or corrupt archive, an unknown compression method, a corrupt
deflate stream, an unreadable file -- raises :class:`~soft_rom.errors.ModelFileError`.

:func:`load_model` reads a model file with these, checks its physical fields and builds the
model of the class the file names (:func:`register_model_class`).
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Collection
import hashlib
import json
import math
import os
from pathlib import Path
import struct
from typing import Any, TYPE_CHECKING, TypeVar
import zipfile

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import DimensionError, ModelFileError

if TYPE_CHECKING:
    from soft_rom.models import LinearROM

__all__ = [
    'FORMAT_NAME',
    'FORMAT_VERSION',
    'MAX_ARCHIVE_BYTES',
    'MAX_ENTRIES',
    'MAX_HEADER_BYTES',
    'MAX_JSON_BYTES',
    'MAX_JSON_DEPTH',
    'MAX_STATES',
    'file_sha256',
    'load_model',
    'parse_json',
    'read_archive',
    'register_model_class',
    'valid_text',
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

#: Total declared uncompressed size of all members of a model file (32 MiB).
MAX_ARCHIVE_BYTES = 32 * 1024 * 1024
#: Most members a model file may have.
MAX_ENTRIES = 16
#: Longest ``.npy`` header accepted (numpy writes about 120 bytes).
MAX_HEADER_BYTES = 4096
#: Largest metadata document (1 MiB).
MAX_JSON_BYTES = 1024 * 1024
#: Deepest nesting of lists/objects in the metadata document.
MAX_JSON_DEPTH = 32
#: Longest integer literal (digits) in the metadata document.
MAX_INT_DIGITS = 30

_MAGIC = b'\x93NUMPY'
_FLOAT_DESCR = {'<f8', '>f8', '<f4', '>f4'}
_BYTE_DESCR = {'|u1', '<u1', '>u1'}
_ZIP_METHODS = {zipfile.ZIP_STORED: 'stored', zipfile.ZIP_DEFLATED: 'deflate'}


def _fail(path: Path, what: str) -> ModelFileError:
    return ModelFileError(f'{path}: {what}')


def _check_directory(path: Path, infos: list[zipfile.ZipInfo],
                     allowed: Collection[str]) -> dict[str, zipfile.ZipInfo]:
    if len(infos) > MAX_ENTRIES:
        raise _fail(path, f'{len(infos)} archive entries; a model file has at most '
                          f'{MAX_ENTRIES}.')
    entries: dict[str, zipfile.ZipInfo] = {}
    total = 0
    for info in infos:
        name = info.filename
        key = name[:-4] if name.endswith('.npy') else name
        if key not in allowed or not name.endswith('.npy'):
            raise _fail(path, f'unexpected archive entry {name[:80]!r}; not a soft_rom model '
                              f'file (allowed: {", ".join(sorted(allowed))}).')
        if key in entries:
            raise _fail(path, f'archive entry {name!r} appears twice.')
        if info.flag_bits & 0x1:
            raise _fail(path, f'archive entry {name!r} is encrypted.')
        if info.compress_type not in _ZIP_METHODS:
            raise _fail(path, f'archive entry {name!r} uses compression method '
                              f'{info.compress_type}; only stored and deflate are read.')
        total += int(info.file_size)
        if total > MAX_ARCHIVE_BYTES:
            raise _fail(path, f'archive declares more than {MAX_ARCHIVE_BYTES // 2**20} MiB '
                              'of data; larger than any model file this soft_rom reads.')
        entries[key] = info
    return entries


def _parse_npy_header(path: Path, name: str, fh: Any) -> tuple[np.dtype[Any], bool,
                                                                tuple[int, ...], int]:
    """``(dtype, fortran_order, shape, header_bytes)`` of the member open in ``fh``."""
    pre = fh.read(8)
    if len(pre) != 8 or pre[:6] != _MAGIC:
        raise _fail(path, f'archive entry {name!r} is not a .npy array (no NUMPY magic).')
    major = pre[6]
    if major == 1:
        raw = fh.read(2)
        if len(raw) != 2:
            raise _fail(path, f'archive entry {name!r}: truncated .npy header.')
        (hlen,), used = struct.unpack('<H', raw), 10
    elif major in (2, 3):
        raw = fh.read(4)
        if len(raw) != 4:
            raise _fail(path, f'archive entry {name!r}: truncated .npy header.')
        (hlen,), used = struct.unpack('<I', raw), 12
    else:
        raise _fail(path, f'archive entry {name!r}: unknown .npy version {major}.')
    if hlen > MAX_HEADER_BYTES:
        raise _fail(path, f'archive entry {name!r}: .npy header of {hlen} bytes (at most '
                          f'{MAX_HEADER_BYTES}).')
    text_raw = fh.read(hlen)
    if len(text_raw) != hlen:
        raise _fail(path, f'archive entry {name!r}: truncated .npy header.')
    try:
        text = text_raw.decode('utf-8' if major == 3 else 'latin1')
        header = ast.literal_eval(text)
    except Exception as err:  # SyntaxError, ValueError, MemoryError, RecursionError, ...
        raise _fail(path, f'archive entry {name!r}: unreadable .npy header '
                          f'({type(err).__name__}).') from None
    if not isinstance(header, dict) or set(header) != {'descr', 'fortran_order', 'shape'}:
        raise _fail(path, f'archive entry {name!r}: .npy header is not '
                          "{'descr', 'fortran_order', 'shape'}.")
    descr, fortran, shape = header['descr'], header['fortran_order'], header['shape']
    if not isinstance(descr, str) or descr not in _FLOAT_DESCR | _BYTE_DESCR:
        raise _fail(path, f'archive entry {name!r} has dtype {str(descr)[:40]!r}; model '
                          'files hold float arrays only (no objects, no pickle).')
    if not isinstance(fortran, bool):
        raise _fail(path, f'archive entry {name!r}: fortran_order must be True or False.')
    if (not isinstance(shape, tuple) or len(shape) > 3
            or not all(type(d) is int and 0 <= d < 2**40 for d in shape)):
        raise _fail(path, f'archive entry {name!r}: shape {str(shape)[:60]} is not a tuple of '
                          'at most 3 non-negative sizes.')
    return np.dtype(descr), fortran, shape, used + hlen


def _read_member(path: Path, zf: zipfile.ZipFile, info: zipfile.ZipInfo,
                 key: str) -> NDArray[Any]:
    name = info.filename
    with zf.open(info) as fh:
        dtype, fortran, shape, head = _parse_npy_header(path, name, fh)
        nbytes = math.prod(shape) * dtype.itemsize
        if head + nbytes != info.file_size:
            raise _fail(path, f'archive entry {name!r}: its header declares shape {shape} '
                              f'({nbytes} bytes) but the entry holds '
                              f'{max(info.file_size - head, 0)} bytes.')
        data = fh.read(nbytes)
        if len(data) != nbytes or fh.read(1):
            raise _fail(path, f'archive entry {name!r} is truncated.')
    flat = np.frombuffer(data, dtype=dtype)
    arr = flat.reshape(shape, order='F' if fortran else 'C')
    if dtype.kind == 'f':
        return np.asarray(arr, dtype=np.float64)
    if key != '__metadata__':
        raise _fail(path, f'archive entry {name!r} has dtype {dtype}; expected float.')
    return arr


def _explain_refusal(path: Path, zf: zipfile.ZipFile, first: str,
                     explain: Callable[[NDArray[Any]], None]) -> None:
    """Hand the entry ``first`` (the metadata) to ``explain`` if it reads as a small array."""
    try:
        info = zf.getinfo(f'{first}.npy')
    except KeyError:
        return
    if (info.file_size > MAX_JSON_BYTES + MAX_HEADER_BYTES + 16 or info.flag_bits & 0x1
            or info.compress_type not in _ZIP_METHODS):
        return
    try:
        arr = _read_member(path, zf, info, first)
    except Exception:  # noqa: BLE001  (unreadable: the refusal as it was stands)
        return
    explain(arr)


def read_archive(path: str | os.PathLike[str], allowed: Collection[str],
                 first: str | None = None,
                 explain: Callable[[NDArray[Any]], None] | None = None
                 ) -> dict[str, NDArray[Any]]:
    """Read the arrays of a model archive, checking every size before reading.

    Parameters
    ----------
    path : path
        The ``.npz`` file.
    allowed : collection of str
        Entry names (without ``.npy``) that may appear; any other refuses the file.
    first : str, optional
        Name of an entry that must be present.
    explain : callable, optional
        When the archive holds an entry not in ``allowed`` (a file of a newer format with
        arrays this version does not know), called with the entry ``first`` (if it is
        there and small) before the refusal; it may raise a clearer ``ModelFileError``.

    Returns
    -------
    dict of str to ndarray
        Float entries as float64; the metadata entry as ``uint8``.

    Raises
    ------
    ModelFileError
        Whatever is wrong with the bytes (and if the file cannot be read).
    """
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as err:
        raise _fail(path, f'cannot read ({err.strerror or err}).') from None
    if size > MAX_ARCHIVE_BYTES + 2**20:
        raise _fail(path, f'{size / 2**20:.1f} MiB; larger than any model file this soft_rom '
                          f'reads ({MAX_ARCHIVE_BYTES // 2**20} MiB of arrays).')
    try:
        with zipfile.ZipFile(path) as zf:
            try:
                entries = _check_directory(path, zf.infolist(), allowed)
            except ModelFileError:
                if explain is not None and first is not None:
                    _explain_refusal(path, zf, first, explain)
                raise
            if first is not None and first not in entries:
                raise _fail(path, f'not a soft_rom model file (no {first} entry); write '
                                  'models with LinearROM.save().')
            return {key: _read_member(path, zf, info, key) for key, info in entries.items()}
    except ModelFileError:
        raise
    except OSError as err:
        if err.errno is None:
            raise _fail(path, f'corrupt or not an .npz archive ({str(err)[:160]}).') from None
        raise _fail(path, f'cannot read ({err.strerror or err}).') from None
    except Exception as err:  # BadZipFile, zlib.error, NotImplementedError, ...
        detail = str(err)[:160] or type(err).__name__
        raise _fail(path, f'corrupt or not an .npz archive ({detail}).') from None


def valid_text(value: Any) -> Any:
    """``value`` (a JSON document) with every string made valid UTF-8, for writing a file.

    Paths of a file system that is not UTF-8 reach Python as strings with lone surrogates
    (``os.fsdecode``), which the loader refuses (:func:`parse_json`); the writer keeps such
    bytes visible instead (byte 0xff of a folder name is stored as the text ``\\xff``).
    """
    if isinstance(value, str):
        try:
            value.encode('utf-8')
            return value
        except UnicodeEncodeError:
            try:
                raw = value.encode('utf-8', 'surrogateescape')
            except UnicodeEncodeError:
                return value.encode('utf-8', 'backslashreplace').decode('utf-8')
            return raw.decode('utf-8', 'backslashreplace')
    if isinstance(value, dict):
        return {valid_text(k): valid_text(v) for k, v in value.items()}
    if isinstance(value, list):
        return [valid_text(v) for v in value]
    return value


def _check_value(value: Any) -> None:
    stack: list[tuple[Any, int]] = [(value, 0)]
    while stack:
        item, level = stack.pop()
        if level > MAX_JSON_DEPTH:
            raise ValueError(f'nested deeper than {MAX_JSON_DEPTH} levels')
        if isinstance(item, str):
            item.encode('utf-8')  # lone surrogates raise UnicodeEncodeError
        elif isinstance(item, dict):
            for k, v in item.items():
                k.encode('utf-8')
                stack.append((v, level + 1))
        elif isinstance(item, list):
            stack.extend((v, level + 1) for v in item)


def _parse_int(text: str) -> int:
    if len(text.lstrip('-')) > MAX_INT_DIGITS:
        raise ValueError(f'integer of {len(text)} digits')
    return int(text)


def _parse_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f'number {text[:30]} out of range')
    return value


def _parse_constant(text: str) -> float:
    raise ValueError(f'{text} is not allowed')


def parse_json(path: str | os.PathLike[str], data: bytes) -> Any:
    """Parse the metadata document of a model file with size and depth limits.

    Raises
    ------
    ModelFileError
        Too large, too deep, not UTF-8 JSON, integers longer than 30 digits, NaN or
        Infinity, strings with lone surrogates.
    """
    path = Path(path)
    if len(data) > MAX_JSON_BYTES:
        raise _fail(path, f'metadata of {len(data)} bytes (at most {MAX_JSON_BYTES}).')
    try:
        text = data.decode('utf-8')
        value = json.loads(text, parse_int=_parse_int, parse_float=_parse_float,
                           parse_constant=_parse_constant)
        _check_value(value)
    except RecursionError:
        raise _fail(path, f'metadata nested deeper than {MAX_JSON_DEPTH} levels.') from None
    except Exception as err:  # UnicodeError, JSONDecodeError, ValueError
        raise _fail(path, f'metadata is not valid UTF-8 JSON within limits '
                          f'({str(err)[:120]}).') from None
    return value


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


_CLASSES: dict[str, type[LinearROM]] = {}

_M = TypeVar('_M', bound='type[LinearROM]')


def register_model_class(cls: _M) -> _M:
    """Let :func:`load_model` read files of ``cls`` (usable as a class decorator).

    The file's ``class`` field is ``cls.__name__``; the loader accepts exactly the arrays
    ``cls._matrix_names`` (plus any of ``cls._optional_matrices``) and ``y_ref``, and builds
    the model with ``cls._from_file(arrays, **common)``.
    """
    from soft_rom.models import LinearROM

    if not (isinstance(cls, type) and issubclass(cls, LinearROM)):
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


def load_model(path: str | os.PathLike[str], *, strict: bool = False) -> LinearROM:
    """Load a model file written by :meth:`LinearROM.save`, without executing any code.

    Every size is checked from the zip directory and the ``.npy`` headers before anything
    is read (:func:`soft_rom.model_io.read_archive`: only the entries a model class needs,
    at most 32 MiB of arrays, float dtypes only, never pickle), the metadata JSON is parsed
    with size and depth limits, and every physical field is checked: ``dt`` finite in
    [1e-9, 1e4] s, ``1 <= n_states <=`` :data:`MAX_STATES` (r <= 256 for DMDc/ERA,
    r <= 128 for LOpInf), ``m, p >= 1``, shapes consistent with r, m and p, entries finite
    with magnitude at most 1e150, offsets ``|y_ref| <= 1e12``, and the discrete system at
    the native ``dt`` finite.

    Parameters
    ----------
    path : path
        The ``.npz`` model file.
    strict : bool
        Also refuse a model that loads but cannot be trusted
        (:meth:`LinearROM.trust_issues`).

    Raises
    ------
    FileNotFoundError
        No such file.
    ModelFileError
        Anything else wrong with the file, whatever its bytes (a ``ValueError``).
    """
    import soft_rom.models  # noqa: F401  (registers the built-in model classes)
    import soft_rom.models_cubic  # noqa: F401  (registers CubicSecondOrderModel)

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
        _check_version(path, header)
        if str(header.get('class'))[:100] not in _CLASSES:
            raise ModelFileError(f'{path}: unknown model class '
                                 f'{str(header.get("class"))[:60]!r} (a newer soft_rom may '
                                 'read it).')

    raw = read_archive(path, allowed, first=_META_KEY, explain=newer)
    header = _header_of(path, raw.pop(_META_KEY))
    version = _check_version(path, header)
    cls = _CLASSES.get(str(header.get('class'))[:100])
    if cls is None:
        raise ModelFileError(f'{path}: unknown model class {str(header.get("class"))[:60]!r}.')
    cls_version = int(getattr(cls, '_format_version', FORMAT_VERSION))
    if version > cls_version:
        raise ModelFileError(f'{path}: a {cls.__name__} file has format version at most '
                             f'{cls_version}, not {version}.')
    needed = set(cls._matrix_names) | {'y_ref'}
    if not needed <= set(raw) <= needed | set(cls._optional_matrices):
        raise ModelFileError(
            f'{path}: {cls.__name__} needs arrays {sorted(needed)}; found {sorted(raw)}.')
    common = check_header(path, header)
    if cls._file_methods and common['method'] not in cls._file_methods:
        raise ModelFileError(f'{path}: a {cls.__name__} cannot have method '
                             f'{common["method"]!r}.')
    for name, arr in raw.items():
        if arr.ndim > (1 if name == 'y_ref' else 3):
            raise ModelFileError(f'{path}: array {name!r} has {arr.ndim} dimensions.')
    check_arrays(path, raw)
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
    if strict and not model.trusted:
        raise ModelFileError(f'{path}: the model cannot be trusted: '
                             f'{"; ".join(model.trust_issues())} (strict mode refuses it).')
    return model
