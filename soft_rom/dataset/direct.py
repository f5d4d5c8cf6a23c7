"""Direct reads of uncompressed, checksummed chunks (the ``Q`` arrays of format version 3).

zarr decodes a chunk with a filter through the filter: the file is read, the ``crc32c``
codec checks it and copies the payload into a new buffer, and the requested region is then
copied into the result. An unfiltered raw chunk skips that middle copy. On the snapshot
matrices, which are read whole several times per fit, the extra copy cost more than the
checksum itself (the POD on the medium preset took 1.13 x as long with checksums as
without, while the CRC-32C alone runs at about 18 GB/s here).

:func:`read_region` reads such an array itself: each chunk file once into one reused buffer,
the CRC-32C on that buffer, then the region straight into the result. The bytes, the
checksum and the layout are zarr format 2's, so the result equals zarr's read bit for bit.
Up to :data:`CONCURRENCY` chunk files are read at once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
import itertools
from pathlib import Path
import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.dataset.checksum import CRC_BYTES, read_checked

__all__ = ['CONCURRENCY', 'ChunkUnreadable', 'basic_bounds', 'read_region']

#: Chunk files read at once, each in its own thread (file reads, the CRC and the copy
#: release the GIL). On a cold page cache the disk serves several reads at once faster than
#: one after another: zarr 3 reads up to 10 chunks concurrently for the same reason.
CONCURRENCY = 8


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
