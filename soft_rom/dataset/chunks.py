"""The raw writer of ``Q``'s uncompressed zarr (format 2) chunk files.

:class:`ChunkFileWriter` is the one path by which state columns reach the disk; see its
docstring for the layout and why it writes the chunk files itself.
"""

from __future__ import annotations

from collections import deque
import os
from pathlib import Path
import queue
import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.dataset.checksum import crc32c
from soft_rom.errors import DatasetError

__all__ = ['ChunkFileWriter']

class ChunkFileWriter:
    """Writes the uncompressed zarr (format 2) chunk files of ``Q`` from a background thread.

    ``Q`` is stored in Fortran order: an uncompressed zarr v2 chunk is then the raw bytes of
    its columns one after the other (edge chunks padded with the fill value), in a file named
    ``'<i>.<j>'``; with ``checksum`` (the ``crc32c`` filter of format version 3) the file ends
    with the CRC-32C of those bytes, kept up to date as they are appended. The files of the
    chunk column being filled stay open and each snapshot is appended to them (its row block
    ``i`` to file ``i``) as it arrives, straight from the array it arrived in: no copy, and the
    message buffer is released a few snapshots later (holding whole chunk columns of message
    buffers made every new message land in fresh pages, whose page faults cost more than a
    copy). Writes are at most 1 MiB (larger ones were several times slower on Linux). A
    background thread overlaps the writes with reading the bag; at most ``queue_size``
    snapshots wait for it. With ``drop_cache`` the written files are evicted from the page
    cache ``drop_lag`` files behind the writer (``POSIX_FADV_DONTNEED``: the first call starts
    their write-back, a later one drops the clean pages), so that gigabytes of ``Q`` recycle
    the same pages instead of filling the page cache (measured 3-4x faster to write). The
    array's shape is updated through zarr when the episode is finished.
    """

    queue_size = 16
    drop_lag = 16       # chunk files (8 MiB each) left in the page cache behind the writer

    def __init__(self, directory: Path, n: int, chunks: tuple[int, int], separator: str,
                 drop_cache: bool = True, checksum: bool = True) -> None:
        self.directory = directory
        self.checksum = checksum
        self.n = n
        self.rows, self.cols = chunks
        self.separator = separator
        self.drop_cache = drop_cache and hasattr(os, 'posix_fadvise')
        self.n_blocks = -(-n // self.rows)
        self._zeros = np.zeros(self.rows, dtype=np.float64)
        self._queue: queue.Queue[Any] = queue.Queue(self.queue_size)
        self._count = 0                                  # snapshots queued
        self._fds: list[int] = []                        # files of the open chunk column
        self._paths: list[Path] = []
        self._crcs: list[int] = []                       # running CRC-32C of each open file
        self._open_j = -1
        self._filled = 0                                 # columns in the open chunk column
        self._written: deque[Path] = deque()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name='soft_rom-q-writer',
                                        daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    self._close_files(pad=False)
                    return
                if self._error is not None:
                    continue
                if item == 'flush':
                    self._close_files(pad=True)
                else:
                    self._write_column(*item)
            except BaseException as err:  # noqa: BLE001 - re-raised in the caller's thread
                self._error = err
                try:
                    self._close_files(pad=False)
                except OSError:
                    pass

    def _write_column(self, index: int, col: NDArray[np.float64]) -> None:
        j = index // self.cols
        if j != self._open_j:
            self._close_files(pad=True)
            for i in range(self.n_blocks):
                path = self.directory / f'{i}{self.separator}{j}'
                self._fds.append(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644))
                self._paths.append(path)
                self._crcs.append(0)
            self._open_j, self._filled = j, 0
        for i, fd in enumerate(self._fds):
            r0 = i * self.rows
            h = min(self.rows, self.n - r0)
            parts = [col[r0:r0 + h]] if h == self.rows else \
                [col[r0:r0 + h], self._zeros[:self.rows - h]]
            _write_all(fd, parts)
            if self.checksum:
                for part in parts:
                    self._crcs[i] = crc32c(part, self._crcs[i])
        self._filled += 1

    def _close_files(self, pad: bool) -> None:
        """Close the open chunk column (``pad``: fill its missing columns with zeros)."""
        fds, paths, self._fds, self._paths = self._fds, self._paths, [], []
        crcs, self._crcs = self._crcs, []
        self._open_j = -1
        try:
            if pad:
                pads = [self._zeros] * (self.cols - self._filled)
                for fd, crc in zip(fds, crcs):
                    _write_all(fd, pads)
                    if self.checksum:
                        for part in pads:
                            crc = crc32c(part, crc)
                        _write_all(fd, [np.array([crc], dtype='<u4')])
                    if self.drop_cache:      # starts writing it back now
                        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            for fd in fds:
                os.close(fd)
        if pad and self.drop_cache:
            # drop-behind: evict chunk files written a while ago, by now written back, so
            # that their pages are reused instead of the page cache growing by all of Q
            self._written.extend(paths)
            while len(self._written) > self.drop_lag:
                _drop_pages(self._written.popleft())

    def _check(self) -> None:
        if self._error is not None:
            raise DatasetError(f'writing Q chunks to {self.directory} failed: '
                               f'{self._error}') from self._error

    def append(self, column: NDArray[Any], copy: bool = True) -> None:
        """Queue one snapshot ``(n,)`` (any real dtype).

        Without ``copy`` a contiguous float64 ``column`` is written from as it is: the
        caller must not modify it afterwards.
        """
        self._check()
        if copy:
            col = np.array(column, dtype=np.float64)
        else:
            col = np.ascontiguousarray(column, dtype=np.float64)
        self._queue.put((self._count, col))
        self._count += 1

    def flush(self) -> None:
        """Complete the chunk column being filled (a partial one is padded with zeros)."""
        self._check()
        self._queue.put('flush')

    def close(self) -> None:
        """Wait for every queued snapshot; raise if one failed (an open column is dropped)."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        self._check()


def _drop_pages(path: Path) -> None:
    """Ask the kernel to evict the (written back) pages of ``path`` from the page cache."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


#: Largest single ``write``: measured on Linux/ext4, writing 8 MiB chunk files in one call
#: (or one ``writev``) was 4-10x slower (kernel time copying into fresh page-cache folios)
#: than writing them in 1 MiB pieces, which run at memory-copy speed.
_WRITE_PIECE = 1 << 20


def _write_all(fd: int, parts: list[Any]) -> None:
    """Write every buffer of ``parts`` to ``fd`` in pieces of ``_WRITE_PIECE`` bytes."""
    for part in parts:
        view = memoryview(part).cast('B')
        while view.nbytes:
            view = view[os.write(fd, view[:_WRITE_PIECE]):]


