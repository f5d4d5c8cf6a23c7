"""Run the streaming passes on a ``dask.distributed`` cluster.

The workers read the blocks themselves: each episode's snapshot array becomes a dask
array chunked as stored (a training set's :class:`~soft_rom.dataset.stored.StoredArray`
through its ``to_dask``, so that the workers' reads are checked and their errors named too;
a bare zarr array with :func:`dask.array.from_zarr`; the workers must see the same storage
path, e.g. a shared file system or an object store; each read task carries its own handle on
the array, so that a lost worker takes no key the reads depend on), cut into the *same* block
plan as the local executor. Each block is centred and multiplied on a worker by the same
kernel; the partial sums are added in plan order by a chain of tasks on the cluster, so
the result equals the local one (same kernels, same order of additions; what differs at
all is only BLAS-internal rounding, far below the 1e-10 agreement tested).

Large shared operands (the range basis ``Q_b``, ``q_ref``) are scattered to every worker
once per pass, under fresh keys (``hash=False``: content-hashed keys would be shared between
passes, and releasing one pass's copy could cancel the next pass's tasks).

Faults (:class:`~soft_rom.errors.ClusterError`, one line each): a scheduler that cannot be
reached within ``timeout`` seconds; a scheduler lost during a pass ("lost the connection to
the Dask scheduler at ADDR during the POD; nothing was written"); workers that kept dying
on a task. A worker that cannot read a chunk raises the training set's own error, which
names the worker (:mod:`soft_rom.dataset.stored`); a worker lost while others remain only
costs time: the scheduler computes its tasks again elsewhere, and the result is the same.
distributed's own log records go to the ``soft_rom.dask`` logger (shown with ``-v``), not
to stderr with their tracebacks.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
import logging
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import ClusterError, ConfigError, dask_worker, one_line, SoftRomError
from soft_rom.scale.blocks import Block, centre_block, Kernel, SnapshotSet

__all__ = ['DEFAULT_TIMEOUT', 'DaskExecutor', 'connect', 'route_logging']

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


#: Seconds to wait for a scheduler (connecting, and reconnecting after a loss).
DEFAULT_TIMEOUT = 30.0
#: Loggers of distributed and the libraries under it, routed by :func:`route_logging`.
_LOGGERS = ('distributed', 'tornado', 'asyncio', 'bokeh')
LOG = logging.getLogger('soft_rom.dask')


class _Forward(logging.Handler):
    """Re-emits a record on ``soft_rom.dask`` at DEBUG, as one line without its traceback."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = ' '.join(record.getMessage().split())
        except Exception:  # noqa: BLE001 - a record that cannot format itself
            text = str(record.msg)
        if record.exc_info and record.exc_info[1] is not None:
            text += f' ({type(record.exc_info[1]).__name__})'
        LOG.debug('%s %s: %s', record.levelname, record.name, text)


def route_logging() -> None:
    """Send distributed's log records to ``soft_rom.dask`` (DEBUG), not to stderr.

    distributed installs its own stderr handlers; a lost scheduler makes it log asyncio
    tracebacks there. Errors reach the user once, as a :class:`ClusterError`.
    """
    for name in _LOGGERS:
        logger = logging.getLogger(name)
        for handler in list(logger.handlers):
            if not isinstance(handler, _Forward):
                logger.removeHandler(handler)
        if not any(isinstance(h, _Forward) for h in logger.handlers):
            logger.addHandler(_Forward())
        logger.propagate = False


def connect(address: str, timeout: float = DEFAULT_TIMEOUT) -> Any:
    """A ``dask.distributed.Client`` for a scheduler ``address`` (``tcp://host:8786``).

    Raises
    ------
    ClusterError
        No scheduler answered within ``timeout`` seconds (also the time a lost scheduler
        is waited for before the pass fails).
    """
    try:
        from dask.distributed import Client
    except ImportError as err:  # pragma: no cover - dask is a dependency
        raise ConfigError('the Dask backend needs the dask[distributed] package: '
                          'pip install "dask[distributed]"') from err
    route_logging()
    try:
        return Client(address, timeout=timeout)
    except (OSError, TimeoutError, ValueError) as err:
        raise ClusterError(f'cannot connect to the Dask scheduler at {address} within '
                           f'{timeout:g} s ({one_line(err)}); start it (`dask scheduler`), '
                           'check --dask, or wait longer with --dask-timeout') from err


def _lost(err: BaseException) -> bool:
    """Whether ``err`` says the connection to the scheduler is gone (not a task's error)."""
    names = {c.__name__ for c in type(err).__mro__}
    return bool(names & {'CancelledError', 'FutureCancelledError', 'CommClosedError',
                         'StreamClosedError'})


def _worker_call(func: Any, *args: Any) -> Any:
    """Run ``func`` on a worker; an unexpected error names the worker."""
    try:
        return func(*args)
    except (SoftRomError, OSError, MemoryError):
        raise                                      # they name the worker themselves
    except Exception as err:  # noqa: BLE001 - anything else from a kernel
        raise ClusterError(f'{one_line(err)} on Dask worker {dask_worker()}') from err


class DaskExecutor:
    """Executor (see :class:`soft_rom.scale.blocks.Executor`) on a Dask cluster.

    Parameters
    ----------
    client : dask.distributed.Client or str
        A connected client, or a scheduler address to connect to.
    timeout : float
        Seconds to wait for the scheduler when connecting to an address.
    """

    def __init__(self, client: Any, timeout: float = DEFAULT_TIMEOUT) -> None:
        self.client = connect(client, timeout) if isinstance(client, str) else client

    @property
    def address(self) -> str:
        """The scheduler's address (for messages)."""
        try:
            return str(self.client.scheduler.address)
        except Exception:  # noqa: BLE001 - a client that lost its scheduler
            return 'its address'

    def _wait(self, get: Callable[[], Any], attempts: int = 5) -> Any:
        """``get()`` (a pass's result); its faults as one :class:`ClusterError`.

        A connection lost while the scheduler is still there was a worker's (older
        distributed lets that reach the client): the pass is submitted again, up to
        ``attempts`` times in all, after a growing pause (the scheduler must notice the
        dead worker first); the scheduler computes the lost parts elsewhere and the result
        is the same, bit for bit.
        """
        for attempt in range(1, attempts + 1):
            try:
                return get()
            except (SoftRomError, MemoryError):
                raise
            except Exception as err:  # noqa: BLE001 - distributed raises many kinds
                status = str(getattr(self.client, 'status', 'running'))
                if attempt < attempts and _lost(err) and status == 'running':
                    LOG.debug('pass interrupted (%s); submitted again', one_line(err))
                    time.sleep(0.5 * attempt)       # for the scheduler to drop the worker
                    continue
                self._fault(err, status)
        raise AssertionError('unreachable')        # pragma: no cover

    def _fault(self, err: Exception, status: str) -> None:
        """Raise ``err`` of a pass as a :class:`ClusterError` (or as it is)."""
        if _lost(err) or status not in ('running', 'newly-created'):
            raise ClusterError(f'lost the connection to the Dask scheduler at '
                               f'{self.address} during the POD; nothing was written') \
                from err
        if isinstance(err, TimeoutError):
            try:
                workers = len(self.client.scheduler_info().get('workers') or {})
            except Exception:  # noqa: BLE001 - no answer: say what happened
                workers = -1
            why = ('it has no workers: start some (`dask worker ADDRESS`)' if workers == 0
                   else f'{one_line(err)}')
            raise ClusterError(f'the Dask scheduler at {self.address} timed out during '
                               f'the POD ({why}); nothing was written') from err
        if type(err).__name__ == 'KilledWorker':
            raise ClusterError(f'Dask workers kept dying while running the POD '
                               f'({one_line(err)}); nothing was written') from err
        raise err

    def _arrays(self, snaps: SnapshotSet) -> list[Any]:
        import dask.array as da
        out = []
        for a in snaps.arrays:
            if hasattr(a, 'to_dask'):  # a training set's array, or a window (t_max) on one
                out.append(a.to_dask())
            elif type(a).__module__.startswith('zarr'):
                out.append(da.from_zarr(a, inline_array=True))
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
            tasks.append(delayed(_worker_call)(_centred_call, raw, ref, kernel, *args,
                                               *shared_f))
        return tasks, [ref_f, *shared_f]

    def sum(self, snaps: SnapshotSet, plan: Sequence[Block], kernel: Kernel,
            per_block: Sequence[tuple[Any, ...]] | None = None,
            shared: tuple[Any, ...] = ()) -> Any:
        """Sum of the kernel's results over the plan, added in plan order on the cluster."""
        from dask import delayed
        tasks, keep = self._wait(lambda: self._tasks(snaps, plan, kernel, per_block, shared))
        acc = tasks[0]
        for t in tasks[1:]:
            acc = delayed(_add)(acc, t)
        result = self._wait(lambda: self.client.compute(acc).result())
        del keep
        return result

    def collect(self, snaps: SnapshotSet, plan: Sequence[Block], kernel: Kernel,
                per_block: Sequence[tuple[Any, ...]] | None = None,
                shared: tuple[Any, ...] = ()) -> list[Any]:
        """The kernel's result for every block, in plan order, gathered to the client."""
        tasks, keep = self._wait(lambda: self._tasks(snaps, plan, kernel, per_block, shared))
        result = self._wait(lambda: self.client.gather(self.client.compute(tasks)))
        del keep
        return list(result)
