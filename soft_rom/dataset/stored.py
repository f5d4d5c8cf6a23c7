"""One array of a training set as the reader hands it out: :class:`StoredArray`.

zarr reads a chunk that is not in the store as the array's fill value (zeros here), and it
lets codec and metadata errors through as they come (``RuntimeError`` from blosc,
``ValueError`` from a short uncompressed chunk, ``TypeError`` from a bad ``.zattrs``). A
training set whose copy was interrupted or whose files were damaged would then be read as
if it were intact, or fail with an error that names neither the set nor the array. Every
array :class:`~soft_rom.dataset.TrainingSet` reads is a :class:`StoredArray`, which

* before its first read checks once that every chunk of the array's grid is stored (one
  directory listing), that every uncompressed chunk (``Q``) is a whole chunk, and that every
  blosc-compressed chunk is as long as its header says (numcodecs' blosc trusts that
  header: a truncated chunk decodes to whatever memory follows it, without an error);
* turns every error of a read into a :class:`~soft_rom.errors.DatasetError` that names the
  training set, the episode and the array, and says what to do.

The format has no checksums: bytes overwritten in place by as many other bytes (in an
uncompressed ``Q`` chunk, or inside a compressed chunk where the codec does not notice) are
not detected.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
import contextlib
import itertools
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import DTypeLike, NDArray

from soft_rom.errors import DatasetError, SoftRomError

__all__ = ['BadMetadata', 'StoredArray', 'chunk_problem', 'one_line', 'translated']

#: Errors a read lets through unchanged: soft_rom's own, a caller's bad index, the
#: operating system's (permissions, I/O: the CLI reports those itself) and lack of memory.
PASS_THROUGH = (SoftRomError, IndexError, OSError, MemoryError)
#: Chunk names listed in a message at most.
SHOWN = 4
#: Length of a blosc header: version, versionlz, flags, typesize, nbytes, blocksize, cbytes.
BLOSC_HEADER = 16


def one_line(err: BaseException, limit: int = 300) -> str:
    """``'Type: message'`` of ``err`` on one line, at most ``limit`` characters."""
    text = ' '.join(str(err).split())
    if len(text) > limit:
        text = text[:limit - 3] + '...'
    return f'{type(err).__name__}: {text}' if text else type(err).__name__


@contextlib.contextmanager
def translated(prefix: str, advice: str, what: str = 'cannot be read') -> Iterator[None]:
    """Re-raise any error of the block (but :data:`PASS_THROUGH`) as a DatasetError.

    The message is ``'{prefix} {what} ({error}); {advice}'``.
    """
    try:
        yield
    except PASS_THROUGH:
        raise
    except Exception as err:  # noqa: BLE001 - zarr, numcodecs and json raise many kinds
        raise DatasetError(f'{prefix} {what} ({one_line(err)}); {advice}') from err


class BadMetadata(ValueError):
    """An array's ``.zarray`` is missing or does not describe the array zarr opened."""


def _zarray(directory: Path) -> dict[str, Any]:
    """The zarr format 2 metadata (``.zarray``) of the array in ``directory``."""
    path = directory / '.zarray'
    if not path.is_file():
        found = 'zarr format 3 metadata' if (directory / 'zarr.json').exists() else 'none'
        raise BadMetadata(f'its .zarray (the format is zarr format 2) is missing; found {found}')
    meta = json.loads(path.read_text(encoding='utf-8'))
    if not isinstance(meta, dict):
        raise BadMetadata(f'its .zarray holds a JSON {type(meta).__name__}, not an object')
    return meta


def _ints(value: Any, what: str) -> tuple[int, ...]:
    if not isinstance(value, list) or not all(
            isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in value):
        raise BadMetadata(f'its .zarray {what} is {value!r}, not a list of counts')
    return tuple(value)


def chunk_problem(directory: Path, shape: tuple[int, ...],
                  chunks: tuple[int, ...]) -> tuple[str, bool] | None:
    """What is wrong with the chunks of the zarr format 2 array in ``directory``, or ``None``.

    Lists the folder once and compares it with the chunk grid of ``shape`` / ``chunks``
    (which must agree with the folder's ``.zarray``): every chunk must be a file. The chunks
    of an uncompressed array must be whole chunks (one ``stat`` each; zarr format 2 stores
    edge chunks whole too), those of a blosc-compressed array as long as their header says
    and decode to a whole chunk (the first 16 bytes of each are read). Other codecs check
    their own data.

    Returns
    -------
    (str, bool) or None
        The problem in words (``'chunk 0.3 is missing'``) and whether chunks are missing.

    Raises
    ------
    BadMetadata
        The ``.zarray`` is missing or disagrees with ``shape`` / ``chunks``.
    ValueError, OSError
        The ``.zarray`` or the folder cannot be read.
    """
    meta = _zarray(directory)
    if _ints(meta.get('shape'), 'shape') != shape or _ints(meta.get('chunks'), 'chunks') \
            != chunks or len(chunks) != len(shape) or 0 in chunks:
        raise BadMetadata(f'its .zarray says shape {meta.get("shape")} and chunks '
                          f'{meta.get("chunks")}; zarr read {list(shape)} and {list(chunks)}')
    sep = meta.get('dimension_separator') or '.'
    if sep not in ('.', '/'):
        raise BadMetadata(f'its .zarray has dimension_separator {sep!r}')
    grid = [-(-s // c) for s, c in zip(shape, chunks)]
    keys = (sep.join(str(i) for i in idx) or '0' for idx in itertools.product(*map(range, grid)))
    stored = _chunk_files(directory, nested=sep == '/')
    missing = [k for k in keys if k not in stored]
    if missing:
        names = ', '.join(missing[:SHOWN]) + (', ...' if len(missing) > SHOWN else '')
        if len(missing) == 1:
            return f'chunk {names} is missing', True
        return f'{len(missing)} of its {int(np.prod(grid))} chunks are missing ({names})', True
    compressor = meta.get('compressor')
    whole = int(np.prod(chunks)) * np.dtype(meta.get('dtype')).itemsize
    if compressor is None and not meta.get('filters'):
        for key in sorted(stored):     # raw chunks (Q): every one is a whole chunk
            size = os.stat(directory / key).st_size
            if size != whole:
                return (f'chunk {key} is truncated or overwritten ({size} bytes; a chunk has '
                        f'{whole})', False)
    elif isinstance(compressor, Mapping) and compressor.get('id') == 'blosc':
        for key in sorted(stored):
            problem = _blosc_problem(directory / key, None if meta.get('filters') else whole)
            if problem is not None:
                return f'chunk {key} {problem}', False
    return None


def _chunk_files(directory: Path, nested: bool) -> set[str]:
    """Names (``'0.3'``, or ``'0/3'`` when ``nested``) of the chunk files in ``directory``."""
    if not nested:
        with os.scandir(directory) as it:
            return {e.name for e in it if not e.name.startswith('.') and e.is_file()}
    found: set[str] = set()
    for root, dirs, files in os.walk(directory):
        dirs[:] = [d for d in dirs if not d.startswith('.')]
        rel = Path(root).relative_to(directory)
        found.update((rel / f).as_posix() for f in files if not f.startswith('.'))
    return found


def _blosc_problem(path: Path, whole: int | None) -> str | None:
    """Why the blosc chunk ``path`` cannot hold ``whole`` bytes, or ``None`` if it can."""
    with open(path, 'rb') as f:
        head = f.read(BLOSC_HEADER)
        size = os.fstat(f.fileno()).st_size
    if len(head) < BLOSC_HEADER:
        return f'is truncated ({size} bytes, shorter than a blosc header)'
    nbytes = int.from_bytes(head[4:8], 'little')
    cbytes = int.from_bytes(head[12:16], 'little')
    if cbytes != size:
        return f'is truncated or overwritten (its header says {cbytes} bytes, it has {size})'
    if whole is not None and nbytes != whole:
        return f'is not a whole chunk (its header says {nbytes} bytes, a chunk has {whole})'
    return None


class StoredArray:
    """An array of a training set on disk, checked before its first read.

    ``A[key]`` reads like the zarr array it wraps (numpy-style slicing, e.g. the column
    block ``A[:, a:b]``; the result is a fresh numpy array); :meth:`to_dask` gives a dask
    array of the same chunks, whose reads (also on cluster workers) go through this object.
    Before the first read :meth:`check` verifies that every chunk is stored; any failure to
    read raises :class:`~soft_rom.errors.DatasetError` naming the set, episode and array.

    Parameters
    ----------
    array : zarr.Array
        The opened array (its metadata is read; no data).
    directory : Path
        The array's folder in the store.
    label : str
        Beginning of every message, e.g. ``"training set ts.zarr is corrupt or incomplete:
        episode 'ep3', array Y"``.
    advice : str
        End of every message: what to do.
    missing_hint : str
        Said after a missing chunk (a likely cause).

    Attributes
    ----------
    shape, chunks : tuple of int
    dtype : numpy.dtype
    array : zarr.Array
        The raw array (reads of it are neither checked nor translated).
    """

    def __init__(self, array: Any, directory: Path, label: str, advice: str,
                 missing_hint: str = 'was the copy interrupted?') -> None:
        self.array = array
        self.directory = Path(directory)
        self.label = label
        self.advice = advice
        self.missing_hint = missing_hint
        self.shape: tuple[int, ...] = tuple(int(s) for s in array.shape)
        self.chunks: tuple[int, ...] = tuple(int(c) for c in array.chunks)
        self.dtype = np.dtype(array.dtype)
        self._checked = False

    @property
    def ndim(self) -> int:
        """Number of dimensions."""
        return len(self.shape)

    @property
    def size(self) -> int:
        """Number of elements."""
        return int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0] if self.shape else 0

    def __repr__(self) -> str:
        return f'<StoredArray {self.directory} shape={self.shape} chunks={self.chunks}>'

    def check(self) -> None:
        """Verify once that every chunk is stored and whole; DatasetError if not."""
        if self._checked:
            return
        try:
            found = chunk_problem(self.directory, self.shape, self.chunks)
        except BadMetadata as err:
            found = (str(err), False)
        except PASS_THROUGH:
            raise
        except Exception as err:  # noqa: BLE001 - json and numpy raise many kinds
            found = (f'its metadata cannot be read ({one_line(err)})', False)
        if found is not None:
            problem, missing = found
            hint = f' ({self.missing_hint})' if missing else ''
            raise DatasetError(f'{self.label}: {problem}{hint}; {self.advice}')
        self._checked = True

    def __getitem__(self, key: Any) -> Any:
        self.check()
        with translated(self.label, self.advice):
            return self.array[key]

    def __array__(self, dtype: DTypeLike | None = None,
                  copy: bool | None = None) -> NDArray[Any]:
        return np.asarray(self[...], dtype=dtype)

    def to_dask(self) -> Any:
        """A dask array over this one, chunked as stored (what ``da.from_zarr`` would give)."""
        import dask.array as da
        from dask.base import tokenize
        self.check()
        name = 'soft_rom-stored-' + tokenize(str(self.directory), self.array, self.chunks)
        return da.from_array(self, chunks=self.chunks, name=name)
