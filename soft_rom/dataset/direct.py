"""Direct reads of uncompressed, checksummed chunks (the ``Q`` arrays of format version 3).

zarr decodes a chunk with a filter through the filter: the file is read, the ``crc32c``
codec checks it and copies the payload into a new buffer, and the requested region is then
copied into the result. An unfiltered raw chunk skips that middle copy. On the snapshot
matrices, which are read whole several times per fit, the extra copy cost more than the
checksum itself (the POD on the medium preset took 1.13 x as long with checksums as
without, while the CRC-32C alone runs at about 18 GB/s here).

:func:`read_region` reads such an array itself, without zarr: each chunk file is read
once, its long runs (the columns of an F-ordered chunk, the rows of a C-ordered one) straight
into the result with one ``preadv`` and the rest into scratch, and the CRC-32C is computed on
the bytes as read. Chunks with short runs go through one buffer per thread and a copy.
Up to :data:`CONCURRENCY` chunk files are read at once. The bytes, the checksum and the
layout are zarr format 2's, so the result equals zarr's read bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
import itertools
import os
from pathlib import Path
import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.dataset.checksum import crc32c, CRC_BYTES, read_checked

__all__ = ['CONCURRENCY', 'ChunkUnreadable', 'basic_bounds', 'read_region']

#: Chunk files read at once, each in its own thread (file reads, the CRC and the copy
#: release the GIL). On a cold page cache the disk serves several reads at once faster than
#: one after another: zarr 3 reads up to 10 chunks concurrently for the same reason.
CONCURRENCY = 8
#: A chunk's runs (rows in C order, columns in F order) at least this long, in bytes, are
#: read straight into the result (``os.preadv``), without a copy.
SCATTER_MIN = 64 * 1024
#: Buffers one ``preadv`` fills at most.
IOV_MAX = 1024


class ChunkUnreadable(Exception):
    """A chunk that fails its checksum or is not a whole chunk: ``name`` and ``problem``."""

    def __init__(self, name: str, problem: str) -> None:
        super().__init__(f'chunk {name} {problem}')
        self.name = name
        self.problem = problem


def basic_bounds(key: Any, shape: tuple[int, ...]
                 ) -> tuple[list[tuple[int, int]], list[bool]] | None:
    """``(start, stop)`` per dimension of a basic-slicing ``key``, and which are integers.

    ``None`` for another kind of key (a step other than 1, a list, a mask, several
    ellipses, an index out of range); ``stop == start`` for an empty slice.
    """
    ndim = len(shape)
    key = key if isinstance(key, tuple) else (key,)
    ell = [i for i, k in enumerate(key) if k is Ellipsis]
    if len(ell) > 1:
        return None
    if ell:
        i = ell[0]
        key = key[:i] + (slice(None),) * (ndim - len(key) + 1) + key[i + 1:]
    if len(key) > ndim:
        return None
    key = key + (slice(None),) * (ndim - len(key))
    bounds, ints = [], []
    for k, size in zip(key, shape):
        if isinstance(k, slice):
            start, stop, step = k.indices(size)
            if step != 1:
                return None
            bounds.append((start, max(start, stop)))
        elif isinstance(k, (int, np.integer)) and not isinstance(k, bool):
            v = int(k) + (size if k < 0 else 0)
            if not 0 <= v < size:
                return None
            bounds.append((v, v + 1))
        else:
            return None
        ints.append(not isinstance(k, slice))
    return bounds, ints


def _scatter(out: NDArray[Any], idx: tuple[int, ...], chunks: Sequence[int],
             bounds: Sequence[tuple[int, int]], order: Any, stored: np.dtype
             ) -> list[NDArray[np.uint8]] | None:
    """Byte buffers that the chunk file ``idx`` fills in order, the result's among them.

    For a 2-D chunk whose rows (C order) or columns (F order) in the region are long runs
    of the result: each run read straight into the result, the bytes outside the region
    (and the CRC) into scratch. ``None`` where that does not apply.
    """
    if out.ndim != 2 or out.dtype != stored or not hasattr(os, 'preadv') or \
            not (out.flags.f_contiguous if order == 'F' else out.flags.c_contiguous):
        return None
    a, b = (0, 1) if order == 'F' else (1, 0)          # runs along axis a
    lo = [max(lo, i * c) - i * c for i, c, (lo, _hi) in zip(idx, chunks, bounds)]
    hi = [min(hi, (i + 1) * c) - i * c for i, c, (_lo, hi) in zip(idx, chunks, bounds)]
    at = [i * c + l - lo_ for i, c, l, (lo_, _hi) in zip(idx, chunks, lo, bounds)]
    if (hi[a] - lo[a]) * stored.itemsize < SCATTER_MIN or 2 * chunks[b] + 2 > IOV_MAX:
        return None
    plan: list[Any] = []                                # runs of the result, scratch lengths
    skip = 0
    for j in range(chunks[b]):
        if not lo[b] <= j < hi[b]:
            skip += chunks[a]
            continue
        skip += lo[a]
        if skip:
            plan.append(skip)
        k = at[b] + j - lo[b]
        run = out[at[a]:at[a] + hi[a] - lo[a], k] if a == 0 else \
            out[k, at[a]:at[a] + hi[a] - lo[a]]
        plan.append(run.view(np.uint8))
        skip = chunks[a] - hi[a]
    total = sum(p for p in plan if isinstance(p, int)) * stored.itemsize
    scratch = np.empty((skip * stored.itemsize + total + CRC_BYTES), dtype=np.uint8)
    pieces, used = [], 0
    for p in plan + [skip]:
        if isinstance(p, int):
            if p:
                pieces.append(scratch[used:used + p * stored.itemsize])
                used += p * stored.itemsize
        else:
            pieces.append(p)
    pieces.append(scratch[used:used + CRC_BYTES])
    return pieces


def _read_into(path: Path, pieces: list[NDArray[np.uint8]], nbytes: int, name: str) -> bool:
    """Read the chunk file into ``pieces`` and check its CRC-32C (False: a short read)."""
    with open(path, 'rb', buffering=0) as f:
        size = os.fstat(f.fileno()).st_size
        if size != nbytes:
            raise ChunkUnreadable(name, f'is truncated or overwritten ({size} bytes; a chunk '
                                  f'has {nbytes})')
        if os.preadv(f.fileno(), [p.data for p in pieces], 0) != size:
            return False                                # read again, the plain way
    value = 0
    for p in pieces[:-1]:
        value = crc32c(p, value)
    if value != int(pieces[-1].view('<u4')[0]):
        raise ChunkUnreadable(name, 'fails its CRC-32C checksum (its bytes changed on disk)')
    return True


def read_region(directory: Path, chunks: Sequence[int], stored: np.dtype, order: Any,
                dtype: np.dtype, bounds: Sequence[tuple[int, int]],
                name: Callable[[tuple[int, ...]], str]) -> NDArray[np.generic]:
    """The region ``bounds`` (``(start, stop)`` per dimension) of a raw, checksummed array.

    Parameters
    ----------
    directory : Path
        The array's folder (zarr format 2, no compressor, the ``crc32c`` filter).
    chunks : sequence of int
        Its chunk shape; every chunk file holds a whole chunk (edge chunks too) and its
        CRC-32C.
    stored : numpy.dtype
        The dtype of the stored bytes (the ``.zarray``'s).
    order : {'C', 'F'}
        The order of the values in a chunk (the ``.zarray``'s).
    dtype : numpy.dtype
        The dtype of the result.
    bounds : sequence of (int, int)
        The region, non-empty in every dimension and inside the array.
    name : callable
        The file name of a chunk index (``'3.0'``, or ``'3/0'`` with the ``/`` separator).

    Returns
    -------
    numpy.ndarray
        A new array of the region's shape, in the chunks' order (as zarr gives it).

    Raises
    ------
    ChunkUnreadable
        A chunk is not a whole chunk, or fails its checksum.
    OSError
        A chunk file cannot be read (``FileNotFoundError`` if it is missing).
    """
    out = np.empty(tuple(b - a for a, b in bounds), dtype=dtype, order=order)
    nbytes = int(np.prod(chunks)) * stored.itemsize + CRC_BYTES
    local = threading.local()

    def read(idx: tuple[int, ...]) -> None:
        pieces = _scatter(out, idx, chunks, bounds, order, stored)
        if pieces is not None and _read_into(directory / name(idx), pieces, nbytes, name(idx)):
            return
        buf = getattr(local, 'buf', None)
        if buf is None:
            buf = local.buf = np.empty(nbytes, dtype=np.uint8)
        problem = read_checked(directory / name(idx), buf)
        if problem is not None:
            raise ChunkUnreadable(name(idx), problem)
        src, dst = [], []
        for i, c, (a, b) in zip(idx, chunks, bounds):
            lo, hi = max(a, i * c), min(b, (i + 1) * c)
            src.append(slice(lo - i * c, hi - i * c))
            dst.append(slice(lo - a, hi - a))
        chunk = buf[:-CRC_BYTES].view(stored).reshape(tuple(chunks), order=order)
        out[tuple(dst)] = chunk[tuple(src)]

    todo = list(itertools.product(*(range(a // c, (b - 1) // c + 1)
                                    for (a, b), c in zip(bounds, chunks))))
    if len(todo) == 1 or CONCURRENCY == 1:
        for idx in todo:
            read(idx)
        return out
    with ThreadPoolExecutor(min(CONCURRENCY, len(todo))) as pool:
        for done in [pool.submit(read, idx) for idx in todo]:
            done.result()                   # the first failing chunk, in grid order
    return out
