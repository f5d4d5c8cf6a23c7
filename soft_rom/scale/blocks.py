"""Snapshot sources read in blocks, and the executors that run one pass over them.

Every streaming computation in :mod:`soft_rom.scale` is a sequence of *passes*. A pass
reads each stored block of the centred snapshot matrix

.. math:: X = [Q_1 - q_{ref} 1^T, \\dots, Q_E - q_{ref} 1^T] \\in \\mathbb{R}^{n \\times K}

once, applies a small *kernel* to it, and either sums the kernels' results (a fixed-order
sum, so that every executor gives the same bits) or returns them block by block.

Two executors run passes:

* :class:`LocalExecutor` -- this process; the next block is read in a background thread
  while the current one is being multiplied (reading and BLAS both release the GIL).
* :class:`soft_rom.scale.dask_backend.DaskExecutor` -- a ``dask.distributed`` cluster; the
  blocks are read *on the workers* from the training set's zarr arrays.

Both use the same block plan (:func:`column_plan`, :func:`row_plan`) and the same kernels
(module-level functions, so that they pickle), and sum partial results in plan order.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import all_finite
from soft_rom.errors import ConfigError, DimensionError

__all__ = [
    'DEFAULT_BLOCK_BYTES',
    'Block',
    'Executor',
    'LocalExecutor',
    'SnapshotSet',
    'column_plan',
    'row_plan',
]

Array = NDArray[np.float64]

#: Target size of one block read from disk (bytes). Two blocks are in memory at a time
#: (the one being multiplied and the one being read ahead).
DEFAULT_BLOCK_BYTES = 256 * 2 ** 20


@dataclass(frozen=True)
class Block:
    """One block of the snapshot matrix.

    Attributes
    ----------
    episode : int
        Index of the episode (source array) the block comes from (column blocks), or -1
        for a row block spanning every episode.
    rows : tuple of int
        ``(start, stop)`` row range.
    cols : tuple of int
        ``(start, stop)`` column range inside the episode (column blocks), or inside the
        concatenation of all episodes (row blocks).
    offset : int
        Column of the block's first snapshot in the concatenated matrix ``X`` (``K``
        columns in all).
    """

    episode: int
    rows: tuple[int, int]
    cols: tuple[int, int]
    offset: int

    @property
    def n_cols(self) -> int:
        """Number of columns in the block."""
        return self.cols[1] - self.cols[0]


class SnapshotSet:
    """Snapshot arrays of several episodes, possibly on disk, and the reference state.

    Parameters
    ----------
    arrays : sequence of array-like, each shape (n, k_i)
        Absolute snapshots (nodal positions), one array per episode: numpy arrays, numpy
        memmaps, zarr arrays -- anything with ``.shape`` and ``A[a:b, c:d]`` slicing.
    q_ref : array_like, shape (n,), optional
        Reference configuration subtracted from every snapshot (default zeros).
    names : sequence of str, optional
        Episode names (for messages and provenance).
    """

    def __init__(self, arrays: Sequence[Any], q_ref: ArrayLike | None = None,
                 names: Sequence[str] | None = None) -> None:
        arrays = list(arrays)
        if not arrays:
            raise DimensionError('no snapshot arrays given: need at least one episode with '
                                 'full states Q of shape (n, k).')
        shapes = []
        for i, a in enumerate(arrays):
            shape = getattr(a, 'shape', None)
            if shape is None or len(shape) != 2:
                raise DimensionError(
                    f'snapshot array {i} must be 2-D (n, k) with .shape; got {shape!r}.')
            shapes.append((int(shape[0]), int(shape[1])))
        n = shapes[0][0]
        if any(s[0] != n for s in shapes):
            raise DimensionError(f'all episodes must have the same number of states n; got '
                                 f'{[s[0] for s in shapes]}.')
        self.arrays = arrays
        self.n = n
        self.lengths = [s[1] for s in shapes]
        ref = np.zeros(n) if q_ref is None else np.asarray(q_ref, dtype=np.float64).reshape(-1)
        if ref.size != n:
            raise DimensionError(f'q_ref must have length n = {n}; got {ref.size}.')
        if not all_finite(ref):
            raise DimensionError('q_ref contains NaN or Inf.')
        self.q_ref = ref
        self.names = ([f'ep{i + 1}' for i in range(len(arrays))] if names is None
                      else [str(s) for s in names])
        if len(self.names) != len(arrays):
            raise DimensionError(f'{len(arrays)} arrays but {len(self.names)} names.')

    @property
    def n_total(self) -> int:
        """Total number of snapshots ``K`` over all episodes."""
        return int(sum(self.lengths))

    @property
    def offsets(self) -> list[int]:
        """Column of each episode's first snapshot in the concatenated matrix."""
        return [int(v) for v in np.concatenate([[0], np.cumsum(self.lengths)[:-1]])]

    def storage_chunks(self) -> tuple[int, int] | None:
        """The on-disk chunk shape ``(rows, cols)`` of the first array, if it has one."""
        chunks = getattr(self.arrays[0], 'chunks', None)
        if chunks is None or len(chunks) != 2:
            return None
        try:
            return int(chunks[0]), int(chunks[1])
        except (TypeError, ValueError):  # dask-style tuple of tuples
            return int(chunks[0][0]), int(chunks[1][0])

    def read_columns(self, block: Block) -> Array:
        """Read one column block and centre it: returns a fresh ``(n, c)`` array."""
        a = self.arrays[block.episode]
        return centre_block(a[:, block.cols[0]:block.cols[1]], self.q_ref,
                            fresh=not isinstance(a, np.ndarray))

    def read_rows(self, block: Block) -> Array:
        """Read rows ``block.rows`` of every episode, centred: returns ``(rows, K)``."""
        r0, r1 = block.rows
        out = np.empty((r1 - r0, self.n_total))
        for a, off, k in zip(self.arrays, self.offsets, self.lengths):
            out[:, off:off + k] = np.asarray(a[r0:r1, :], dtype=np.float64)
        out -= self.q_ref[r0:r1, None]
        return out


def centre_block(raw: Any, ref: Array, *, fresh: bool) -> Array:
    """Return the block ``raw - ref[:, None]`` as float64.

    ``fresh`` says that ``raw`` is memory nobody else holds (what a zarr read returns); it
    is then centred in place when it is a contiguous float64 array (zarr hands back
    Fortran-ordered blocks: copying them to C order cost more CPU than the kernels).
    Otherwise (numpy arrays, memmaps: the caller's data) a copy is centred.
    """
    if (fresh and isinstance(raw, np.ndarray) and raw.dtype == np.float64
            and raw.flags.writeable and (raw.flags.c_contiguous or raw.flags.f_contiguous)):
        x = raw
    else:
        x = np.array(raw, dtype=np.float64, order='K')
    x -= ref[:, None]
    return x


def _aligned(target: int, chunk: int | None, total: int) -> int:
    """``target`` rounded to a whole number of storage chunks (at least one), at most ``total``."""
    target = max(int(target), 1)
    if chunk and chunk < total:
        target = max(chunk, (target // chunk) * chunk)
    return min(target, total)


def column_plan(snaps: SnapshotSet, *, block_cols: int | None = None,
                block_bytes: int = DEFAULT_BLOCK_BYTES) -> list[Block]:
    """Split every episode into column blocks of full height.

    Parameters
    ----------
    snaps : SnapshotSet
    block_cols : int, optional
        Columns per block; default ``block_bytes / (8 n)`` rounded to whole storage chunks.
    block_bytes : int
        Target bytes per block when ``block_cols`` is not given.
    """
    chunks = snaps.storage_chunks()
    if block_cols is None:
        block_cols = _aligned(block_bytes // (8 * snaps.n), chunks[1] if chunks else None,
                              max(snaps.lengths))
    if block_cols < 1:
        raise ConfigError(f'block_cols must be positive; got {block_cols}.')
    plan = []
    for e, (k, off) in enumerate(zip(snaps.lengths, snaps.offsets)):
        for a in range(0, k, block_cols):
            b = min(a + block_cols, k)
            plan.append(Block(e, (0, snaps.n), (a, b), off + a))
    return plan


def row_plan(snaps: SnapshotSet, *, block_rows: int | None = None,
             block_bytes: int = DEFAULT_BLOCK_BYTES) -> list[Block]:
    """Split the concatenated snapshot matrix into row blocks spanning all ``K`` columns.

    Efficient only when the storage is chunked in rows as well (numpy memmaps, zarr chunks
    of fewer than ``n`` rows): each stored chunk is then read once per pass.
    """
    chunks = snaps.storage_chunks()
    K = snaps.n_total
    if block_rows is None:
        block_rows = _aligned(block_bytes // (8 * K), chunks[0] if chunks else None, snaps.n)
    if block_rows < 1:
        raise ConfigError(f'block_rows must be positive; got {block_rows}.')
    return [Block(-1, (a, min(a + block_rows, snaps.n)), (0, K), 0)
            for a in range(0, snaps.n, block_rows)]


Kernel = Callable[..., Any]


class Executor(Protocol):
    """Runs one pass of a kernel over the blocks of a :class:`SnapshotSet`.

    ``kernel(X, *per_block_args, *shared)`` receives the centred block ``X``. ``per_block``
    is a list with one tuple of (small) arguments per block; ``shared`` holds (possibly
    large) arrays sent once to every worker.
    """

    def sum(self, snaps: SnapshotSet, plan: Sequence[Block], kernel: Kernel,
            per_block: Sequence[tuple[Any, ...]] | None = None,
            shared: tuple[Any, ...] = ()) -> Any:
        """Sum of the kernel's results over the plan, added in plan order."""
        ...

    def collect(self, snaps: SnapshotSet, plan: Sequence[Block], kernel: Kernel,
                per_block: Sequence[tuple[Any, ...]] | None = None,
                shared: tuple[Any, ...] = ()) -> list[Any]:
        """The kernel's result for every block, in plan order."""
        ...


def add_results(acc: Any, part: Any) -> Any:
    """Add two kernel results (arrays, floats or tuples of them), in place where possible."""
    if acc is None:
        return part
    if isinstance(acc, tuple):
        return tuple(add_results(a, p) for a, p in zip(acc, part))
    if isinstance(acc, np.ndarray):
        acc += part
        return acc
    return acc + part


class LocalExecutor:
    """Run passes in this process, reading the next block while the current one computes.

    Parameters
    ----------
    progress : callable, optional
        Called with the number of columns (column blocks) or rows (row blocks) done after
        each block, e.g. ``tqdm.update``.
    prefetch : bool
        Read ahead in a background thread (default ``True``).
    """

    def __init__(self, progress: Callable[[int], Any] | None = None, *,
                 prefetch: bool = True) -> None:
        self.progress = progress
        self.prefetch = prefetch
        self.blocks_read = 0
        self.bytes_read = 0

    def _read(self, snaps: SnapshotSet, block: Block) -> Array:
        x = snaps.read_rows(block) if block.episode < 0 else snaps.read_columns(block)
        self.blocks_read += 1
        self.bytes_read += x.nbytes
        return x

    def _blocks(self, snaps: SnapshotSet, plan: Sequence[Block]) -> Iterator[Array]:
        if not self.prefetch or len(plan) < 2:
            for block in plan:
                yield self._read(snaps, block)
            return
        with ThreadPoolExecutor(max_workers=1) as pool:
            nxt = pool.submit(self._read, snaps, plan[0])
            for i in range(len(plan)):
                x = nxt.result()
                if i + 1 < len(plan):
                    nxt = pool.submit(self._read, snaps, plan[i + 1])
                yield x
                del x

    def _run(self, snaps: SnapshotSet, plan: Sequence[Block], kernel: Kernel,
             per_block: Sequence[tuple[Any, ...]] | None, shared: tuple[Any, ...],
             reduce: bool) -> Any:
        per_block = per_block if per_block is not None else [()] * len(plan)
        acc: Any = None
        out = []
        for block, args, x in zip(plan, per_block, self._blocks(snaps, plan)):
            res = kernel(x, *args, *shared)
            if reduce:
                acc = add_results(acc, res)
            else:
                out.append(res)
            if self.progress is not None:
                self.progress(block.n_cols if block.episode >= 0
                              else block.rows[1] - block.rows[0])
        return acc if reduce else out

    def sum(self, snaps: SnapshotSet, plan: Sequence[Block], kernel: Kernel,
            per_block: Sequence[tuple[Any, ...]] | None = None,
            shared: tuple[Any, ...] = ()) -> Any:
        """Sum of ``kernel(X_block, *per_block[i], *shared)`` over the plan, in order."""
        return self._run(snaps, plan, kernel, per_block, shared, True)

    def collect(self, snaps: SnapshotSet, plan: Sequence[Block], kernel: Kernel,
                per_block: Sequence[tuple[Any, ...]] | None = None,
                shared: tuple[Any, ...] = ()) -> list[Any]:
        """``kernel(X_block, *per_block[i], *shared)`` for every block, in plan order."""
        return self._run(snaps, plan, kernel, per_block, shared, False)
