"""The bounded archive and JSON reader of model files: bounded cost, no code.

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
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Collection
import json
import math
import os
from pathlib import Path
import struct
from typing import Any
import zipfile

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import ConfigError, ModelFileError

__all__ = [
    'MAX_ARCHIVE_BYTES',
    'MAX_ENTRIES',
    'MAX_HEADER_BYTES',
    'MAX_JSON_BYTES',
    'MAX_JSON_DEPTH',
    'parse_json',
    'read_archive',
    'json_safe',
    'read_user_arrays',
    'valid_text',
]

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


def json_safe(value: Any) -> Any:
    """``value`` as plain JSON data (what a model file's metadata holds).

    Numpy scalars and arrays become Python numbers and lists, tuples lists, and NaN or
    infinite numbers ``None`` (JSON has none of them).
    """
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [json_safe(v) for v in (value.tolist() if isinstance(value, np.ndarray)
                                       else value)]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


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


def read_user_arrays(path: str | os.PathLike[str], what: str,
                     names: Collection[str]) -> dict[str, NDArray[Any]]:
    """The arrays ``names`` of a user's ``.npz`` (a reference, inputs): numbers, never code.

    Returns those of ``names`` it holds (other entries are not read). Each must be an array
    of real numbers (integers or floats); an object array (a pickle), strings, complex or
    boolean data, a file that is not a zip archive (a ``.npy``, a text file, a bag), a
    truncated or corrupt archive: one ``ConfigError`` line that starts with ``what`` and
    the path.
    """
    path = Path(path)
    head = f'{what} {path}'
    if path.is_dir():
        raise ConfigError(f'{head} is a folder; give the .npz file')
    if not zipfile.is_zipfile(path):
        raise ConfigError(f'{head}: not an .npz file (a zip archive of .npy arrays, as '
                          'numpy.savez writes)')
    out: dict[str, NDArray[Any]] = {}
    try:
        with np.load(path, allow_pickle=False) as z:
            for name in (n for n in z.files if n in names):
                a = z[name]
                if a.dtype.kind not in 'iuf':
                    raise ConfigError(f'{head}: array {name!r} holds {a.dtype} data; only real '
                                      'numbers are read')
                out[name] = a
    except ConfigError:
        raise
    except ValueError as err:
        if 'allow_pickle' in str(err):
            raise ConfigError(f'{head}: an array holds Python objects (a pickle), which '
                              'soft_rom never loads') from None
        raise ConfigError(f'{head}: not a readable .npz ({str(err)[:160]})') from None
    except Exception as err:  # BadZipFile, zlib.error, EOFError, OSError
        detail = str(err)[:160] or type(err).__name__
        raise ConfigError(f'{head}: corrupt or truncated .npz ({detail})') from None
    return out
