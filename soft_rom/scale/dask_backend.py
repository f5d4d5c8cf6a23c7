"""Run the streaming passes on a ``dask.distributed`` cluster.

The workers read the blocks themselves: each episode's snapshot array becomes a dask
array chunked as stored (a training set's :class:`~soft_rom.dataset.stored.StoredArray`
through its ``to_dask``, so that the workers' reads are checked and their errors named too;
a bare zarr array with :func:`dask.array.from_zarr`; the workers must see the same storage
path, e.g. a shared file system or an object store), cut into the *same* block
plan as the local executor. Each block is centred and multiplied on a worker by the same
kernel; the partial sums are added in plan order by a chain of tasks on the cluster, so
the result equals the local one (same kernels, same order of additions; what differs at
all is only BLAS-internal rounding, far below the 1e-10 agreement tested).

Large shared operands (the range basis ``Q_b``, ``q_ref``) are scattered to every worker
once per pass, under fresh keys (``hash=False``: content-hashed keys would be shared between
passes, and releasing one pass's copy could cancel the next pass's tasks).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import ConfigError
from soft_rom.scale.blocks import Block, centre_block, Kernel, SnapshotSet

__all__ = ['DaskExecutor', 'connect']

Array = NDArray[np.float64]


def _centred_call(raw: Any, ref: Array, kernel: Kernel, *args: Any) -> Any:
    """Centre a raw block on the worker exactly as :meth:`SnapshotSet.read_columns` does."""
    return kernel(centre_block(np.asarray(raw), ref, fresh=False), *args)


def _add(a: Any, b: Any) -> Any:
    """Pure sum of two kernel results (arrays, floats or tuples of them)."""
    if isinstance(a, tuple):
        return tuple(_add(x, y) for x, y in zip(a, b))
    return a + b


def _ref_rows(ref: Array, r0: int, r1: int) -> Array:
    return np.ascontiguousarray(ref[r0:r1])


def connect(address: str) -> Any:
    """A ``dask.distributed.Client`` for a scheduler ``address`` (``tcp://host:8786``)."""
    try:
        from dask.distributed import Client
    except ImportError as err:  # pragma: no cover - dask is a dependency
        raise ConfigError('the Dask backend needs the dask[distributed] package: '
                          'pip install "dask[distributed]"') from err
    return Client(address)


class DaskExecutor:
    """Executor (see :class:`soft_rom.scale.blocks.Executor`) on a Dask cluster.

    Parameters
    ----------
    client : dask.distributed.Client or str
        A connected client, or a scheduler address to connect to.
    """

    def __init__(self, client: Any) -> None:
        self.client = connect(client) if isinstance(client, str) else client

    def _arrays(self, snaps: SnapshotSet) -> list[Any]:
        import dask.array as da
        out = []
        for a in snaps.arrays:
            if hasattr(a, 'to_dask'):  # a training set's array, or a window (t_max) on one
                out.append(a.to_dask())
            elif type(a).__module__.startswith('zarr'):
                out.append(da.from_zarr(a))
            elif isinstance(a, da.Array):
                out.append(a)
            else:  # in-memory data: shipped from the client (small data, tests)
                out.append(da.from_array(np.asarray(a), chunks=a.shape))
        return out

    def _block_delayed(self, arrays: list[Any], snaps: SnapshotSet, block: Block) -> Any:
        import dask.array as da
        if block.episode >= 0:
            x = arrays[block.episode][:, block.cols[0]:block.cols[1]]
        else:
            x = da.concatenate([a[block.rows[0]:block.rows[1], :] for a in arrays], axis=1)
        x = x.rechunk(x.shape)
        return x.to_delayed().ravel()[0]

    def _tasks(self, snaps: SnapshotSet, plan: Sequence[Block], kernel: Kernel,
               per_block: Sequence[tuple[Any, ...]] | None,
               shared: tuple[Any, ...]) -> tuple[list[Any], list[Any]]:
        from dask import delayed
        arrays = self._arrays(snaps)
        per_block = per_block if per_block is not None else [()] * len(plan)
        ref_f = self.client.scatter(snaps.q_ref, broadcast=True, hash=False)
        shared_f = [self.client.scatter(s, broadcast=True, hash=False)
                    if isinstance(s, np.ndarray)
                    else s for s in shared]
        tasks = []
        for block, args in zip(plan, per_block):
            raw = self._block_delayed(arrays, snaps, block)
            ref = ref_f if block.episode >= 0 else delayed(_ref_rows)(ref_f, *block.rows)
            tasks.append(delayed(_centred_call)(raw, ref, kernel, *args, *shared_f))
        return tasks, [ref_f, *shared_f]

    def sum(self, snaps: SnapshotSet, plan: Sequence[Block], kernel: Kernel,
            per_block: Sequence[tuple[Any, ...]] | None = None,
            shared: tuple[Any, ...] = ()) -> Any:
        """Sum of the kernel's results over the plan, added in plan order on the cluster."""
        from dask import delayed
        tasks, keep = self._tasks(snaps, plan, kernel, per_block, shared)
        acc = tasks[0]
        for t in tasks[1:]:
            acc = delayed(_add)(acc, t)
        result = self.client.compute(acc).result()
        del keep
        return result

    def collect(self, snaps: SnapshotSet, plan: Sequence[Block], kernel: Kernel,
                per_block: Sequence[tuple[Any, ...]] | None = None,
                shared: tuple[Any, ...] = ()) -> list[Any]:
        """The kernel's result for every block, in plan order, gathered to the client."""
        tasks, keep = self._tasks(snaps, plan, kernel, per_block, shared)
        futures = self.client.compute(tasks)
        result = self.client.gather(futures)
        del keep
        return list(result)
