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
* before every read checks that the chunks it touches are stored (one ``stat`` each), in
  the process that reads: a chunk deleted after the first check, or a Dask worker that
  does not see the files (a mount missing on its host), is refused there, not read as zeros;
* turns every error of a read into a :class:`~soft_rom.errors.DatasetError` that names the
  training set, the episode, the array and, where it can tell, the chunk, and says what to
  do; on a Dask worker every message (and an operating-system error such as a permission
  denied) also names the worker.

Sets of format version 3 end every chunk with its CRC-32C (:mod:`soft_rom.dataset.checksum`),
verified at every read, so bytes changed on disk are refused (the chunk named): the raw
chunks of ``Q`` by :func:`~soft_rom.dataset.direct.read_region` (one read per chunk file,
no extra copy), the compressed arrays by zarr.
Older sets have no checksums: bytes overwritten in place by as many other bytes are not
detected there.
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

from soft_rom.dataset.checksum import chunk_crc_problem, CODEC_ID, CRC_BYTES, register
from soft_rom.dataset.direct import basic_bounds, ChunkUnreadable, read_region
from soft_rom.errors import dask_worker, DatasetError, one_line, SoftRomError

__all__ = ['BadMetadata', 'StoredArray', 'chunk_problem', 'dask_worker', 'one_line',
           'translated']

#: Errors a read lets through unchanged: soft_rom's own, a caller's bad index, the
#: operating system's (permissions, I/O: the CLI reports those itself) and lack of memory.
PASS_THROUGH = (SoftRomError, IndexError, OSError, MemoryError)
#: Chunk names listed in a message at most.
SHOWN = 4
#: Length of a blosc header: version, versionlz, flags, typesize, nbytes, blocksize, cbytes.
BLOSC_HEADER = 16


def _on_worker() -> str:
    worker = dask_worker()
    return f' on Dask worker {worker}' if worker else ''


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
    filters = meta.get('filters') or []
    if compressor is None and filters in ([], [{'id': CODEC_ID}]):
        whole += CRC_BYTES if filters else 0
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


def _listing(directory: Path) -> list[Path]:
    """The entries of ``directory`` (none if it is missing or unreadable)."""
    try:
        return list(directory.iterdir())
    except OSError:
        return []


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
    """An array of a training set on disk, checked before its first read and at every read.

    ``A[key]`` reads like the zarr array it wraps (numpy-style slicing, e.g. the column
    block ``A[:, a:b]``; the result is a fresh numpy array); :meth:`to_dask` gives a dask
    array of the same chunks, whose reads (also on cluster workers) go through this object.
    Before the first read :meth:`check` verifies that every chunk is stored; every read
    first checks that the chunks it touches are stored, and any failure to read (a chunk
    whose checksum fails, a damaged file) raises :class:`~soft_rom.errors.DatasetError`
    naming the set, episode, array and chunk. Pickled (to a Dask worker) it carries its
    folder, not the zarr array: the worker opens the array itself and checks it again, so
    that what the worker cannot see or read is said there, with the worker's address.

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
    checksummed : bool
        Whether its chunks carry a CRC-32C (format version 3).
    """

    def __init__(self, array: Any, directory: Path, label: str, advice: str,
                 missing_hint: str = 'was the copy interrupted?') -> None:
        self._array = array
        self.directory = Path(directory)
        self.label = label
        self.advice = advice
        self.missing_hint = missing_hint
        self.shape: tuple[int, ...] = tuple(int(s) for s in array.shape)
        self.chunks: tuple[int, ...] = tuple(int(c) for c in array.chunks)
        self.dtype = np.dtype(array.dtype)
        self._checked = False
        self._layout: tuple[str, bool, int | None] | None = None
        self._stored: tuple[np.dtype, str] | None = None  # raw checksummed: read_region

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state['_array'] = None           # reopened where it is read
        state['_checked'] = False        # and checked there again
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)

    @property
    def array(self) -> Any:
        """The zarr array (opened from :attr:`directory` in a process that got a pickle)."""
        if self._array is None:
            from soft_rom.dataset._format import _zarr
            register()
            zarr = _zarr()
            with translated(f'{self.label}:', f'{self.advice}',
                            what=f'its metadata (.zarray) cannot be read{_on_worker()}'):
                if not (self.directory / '.zarray').is_file():
                    raise FileNotFoundError(f'{self.directory / ".zarray"} does not exist')
                kw = {'zarr_format': 2} if int(str(zarr.__version__).split('.')[0]) >= 3 \
                    else {}
                self._array = zarr.open_array(str(self.directory), mode='r', **kw)
        return self._array

    @property
    def ndim(self) -> int:
        """Number of dimensions."""
        return len(self.shape)

    @property
    def size(self) -> int:
        """Number of elements."""
        return int(np.prod(self.shape))

    @property
    def checksummed(self) -> bool:
        """Whether the chunks end with a CRC-32C (the ``crc32c`` filter)."""
        return self._chunk_layout()[1]

    def __len__(self) -> int:
        return self.shape[0] if self.shape else 0

    def __repr__(self) -> str:
        return f'<StoredArray {self.directory} shape={self.shape} chunks={self.chunks}>'

    def _chunk_layout(self) -> tuple[str, bool, int | None]:
        """``(separator, checksummed, raw chunk bytes or None if compressed)``."""
        if self._layout is None:
            try:
                meta = _zarray(self.directory)
            except (BadMetadata, OSError, ValueError):
                meta = {}
            filters = meta.get('filters') or []
            raw = None
            if meta.get('compressor') is None:
                raw = int(np.prod(self.chunks)) * self.dtype.itemsize
            self._layout = (meta.get('dimension_separator') or '.',
                            {'id': CODEC_ID} in filters, raw)
            if raw is not None and self._layout[1] and meta.get('order') in ('C', 'F'):
                self._stored = (np.dtype(meta.get('dtype')), meta['order'])
        return self._layout

    def check(self) -> None:
        """Verify once that every chunk is stored and whole; DatasetError if not."""
        if self._checked:
            return
        try:
            found = chunk_problem(self.directory, self.shape, self.chunks)
        except BadMetadata as err:
            found = (str(err), False)
            worker = dask_worker()
            if worker and not any(p.name != '.zarray' for p in _listing(self.directory)):
                first = self._name((0,) * self.ndim)
                raise DatasetError(
                    f'{self.label}: its folder {self.directory} is missing or empty on Dask '
                    f'worker {worker}: no .zarray, and chunk {first} and every other chunk '
                    'are missing (does this worker see the same storage as the client? a '
                    f'mount missing on its host?); {self.advice}') from err
        except PASS_THROUGH as err:
            raise self._located(err) from err
        except Exception as err:  # noqa: BLE001 - json and numpy raise many kinds
            found = (f'its metadata cannot be read ({one_line(err)})', False)
        if found is not None:
            problem, missing = found
            raise DatasetError(f'{self.label}: {problem}{_on_worker()}'
                               f'{self._hint() if missing else ""}; {self.advice}')
        self._checked = True

    def _hint(self) -> str:
        if dask_worker():
            return (f' (does this worker see the same storage as the client? '
                    f'{self.missing_hint})')
        return f' ({self.missing_hint})'

    def _located(self, err: BaseException) -> BaseException:
        """``err`` (an operating-system error) naming the Dask worker, when on one."""
        where = _on_worker()
        if not where or not isinstance(err, OSError) or err.errno is None:
            return err
        try:
            return type(err)(err.errno, f'{err.strerror}{where}', err.filename)
        except Exception:  # noqa: BLE001 - an OSError subclass with another signature
            return err

    def _touched(self, found: Any) -> list[tuple[int, ...]] | None:
        """Chunk indices a key reads, from its :func:`basic_bounds` (``None``: another kind)."""
        if found is None:
            return None
        if any(b <= a for a, b in found[0]):
            return []
        return list(itertools.product(*(range(a // c, (b - 1) // c + 1)
                                        for (a, b), c in zip(found[0], self.chunks))))

    def _name(self, idx: tuple[int, ...]) -> str:
        return self._chunk_layout()[0].join(str(i) for i in idx) or '0'

    def _require(self, touched: list[tuple[int, ...]] | None) -> None:
        """Every chunk of ``touched`` (``None``: all) is stored; DatasetError if not."""
        if touched is None:
            grid = [range(-(-s // c)) for s, c in zip(self.shape, self.chunks)]
            touched = list(itertools.product(*grid))
        missing = []
        for idx in touched:
            name = self._name(idx)
            try:
                os.stat(self.directory / name)
            except FileNotFoundError:
                missing.append(name)
            except OSError as err:
                raise self._located(err) from err
        if missing:
            names = ', '.join(missing[:SHOWN]) + (', ...' if len(missing) > SHOWN else '')
            what = f'chunk {names} is missing' if len(missing) == 1 else \
                f'chunks {names} are missing'
            raise DatasetError(f'{self.label}: {what}{_on_worker()}{self._hint()}; '
                               f'{self.advice}')

    def _bad_chunk(self, touched: list[tuple[int, ...]] | None) -> str | None:
        """Which chunk of ``touched`` cannot be read and why (after a failed read)."""
        if touched is None:
            grid = [range(-(-s // c)) for s, c in zip(self.shape, self.chunks)]
            touched = list(itertools.product(*grid))
        _sep, checksummed, raw = self._chunk_layout()
        for idx in touched:
            name = self._name(idx)
            try:
                if checksummed and raw is not None:
                    problem = chunk_crc_problem(self.directory / name, raw)
                else:
                    region = tuple(slice(i * c, min((i + 1) * c, s))
                                   for i, c, s in zip(idx, self.chunks, self.shape))
                    try:
                        self.array[region]
                        problem = None
                    except PASS_THROUGH:
                        raise
                    except Exception as err:  # noqa: BLE001 - the codecs raise many kinds
                        problem = f'cannot be decoded ({one_line(err)})'
                        if 'checksum' in str(err):
                            problem = ('fails its CRC-32C checksum (its bytes changed on '
                                       'disk)')
            except OSError:
                continue
            if problem is not None:
                return f'chunk {name} {problem}'
        return None

    def verify(self) -> None:
        """Check every chunk against its checksum (reads the whole array); DatasetError if not.

        Uncompressed chunks are read file by file (no array is built); compressed ones are
        decoded by zarr, which verifies them. Without checksums only :meth:`check` runs.
        """
        self.check()
        _sep, checksummed, raw = self._chunk_layout()
        if not checksummed:
            return
        if raw is None:
            self[...]
            return
        grid = [range(-(-s // c)) for s, c in zip(self.shape, self.chunks)]
        for idx in itertools.product(*grid):
            name = self._name(idx)
            try:
                problem = chunk_crc_problem(self.directory / name, raw)
            except FileNotFoundError:
                problem = 'is missing'
            except OSError as err:
                raise self._located(err) from err
            if problem is not None:
                raise DatasetError(f'{self.label}: chunk {name} {problem}{_on_worker()}; '
                                   f'{self.advice}')

    def __getitem__(self, key: Any) -> Any:
        self.check()
        found = basic_bounds(key, self.shape)
        touched = self._touched(found)
        self._require(touched)
        try:
            self._chunk_layout()
            if self._stored is not None and touched and found and not all(found[1]):
                out = read_region(self.directory, self.chunks, *self._stored, self.dtype,
                                  found[0], self._name)
                return out.reshape([n for n, i in zip(out.shape, found[1]) if not i])
            return self.array[key]
        except ChunkUnreadable as err:
            raise DatasetError(f'{self.label}: {err}{_on_worker()}; {self.advice}') from err
        except FileNotFoundError as err:     # removed since the check above
            self._require(touched)
            raise self._located(err) from err
        except PASS_THROUGH as err:
            located = self._located(err)
            if located is err:
                raise
            raise located from err
        except Exception as err:  # noqa: BLE001 - zarr, numcodecs raise many kinds
            bad = self._bad_chunk(touched)
            what = bad if bad is not None else f'cannot be read ({one_line(err)})'
            raise DatasetError(f'{self.label}: {what}{_on_worker()}; {self.advice}') from err

    def __array__(self, dtype: DTypeLike | None = None,
                  copy: bool | None = None) -> NDArray[Any]:
        return np.asarray(self[...], dtype=dtype)

    def to_dask(self) -> Any:
        """A dask array over this one, chunked as stored (what ``da.from_zarr`` would give).

        Every chunk's read task carries its own copy of this array (``inline_array``), so
        that no task holds the array for the reads to depend on: a worker lost while holding
        such a key leaves reads waiting on it, and distributed 2024.1's scheduler then fails
        on them and drops every worker (a fit waited for ever). A copy reopens and checks
        the array where it is read (a directory listing and a ``stat`` per chunk).
        """
        import dask.array as da
        from dask.base import tokenize
        self.check()
        name = 'soft_rom-stored-' + tokenize(str(self.directory), self.array, self.chunks)
        return da.from_array(self, chunks=self.chunks, name=name, inline_array=True)
