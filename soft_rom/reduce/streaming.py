"""The streaming reducer: snapshots larger than memory, streamed from disk (or on Dask).

The data flow one way:

1. :func:`soft_rom.pipeline.open_training_data` -- episodes with ``U``, ``Y``, ``t`` in
   memory and ``Q`` left lazy on disk (:class:`ColumnWindow` keeps a ``--t-max`` cut lazy),
   and the references ``q_ref``, ``y_ref``;
2. :meth:`StreamingReducer.reduce` -- the *only* read of the snapshots: the streaming POD
   (:class:`~soft_rom.scale.pod.StreamingPOD`, 1--3 passes over the data, locally or on a
   Dask cluster) leaves a :class:`~soft_rom.reduce.data.ReducedData` (POD coordinates of
   every episode, inputs, outputs) in memory;
3. any learner fits on it (:mod:`soft_rom.learners`), as many times as wanted.

The POD method: ``'gram'`` (method of snapshots) is exact to rounding and yields every
coordinate (``K x K`` numbers for ``K`` snapshots), so that the models are those of the
in-memory fit; ``'randomized'`` reads the data a few times with memory ``O(n l)`` whatever
``K`` and is accurate to the decay of the singular values beyond ``l``. ``'auto'`` (default)
takes ``'gram'`` while its memory stays under :data:`GRAM_MEMORY` and the storage is split in
rows, else ``'randomized'``.

DMDc on streamed coordinates: with :math:`X \\approx W Z` (``W`` the ``l`` leading POD
modes, orthonormal), :math:`\\Omega = [X; U] = \\mathrm{diag}(W, I) [Z; U]`, so the SVDs of
``Ω`` and of ``Q'`` are those of the small ``[Z; U]`` and ``Z'`` with left factors multiplied
by ``W``; every DMDc operator is unchanged by that orthonormal factor (exact when the
snapshots lie in the span of the ``l`` modes, as with ``'gram'``). The unit-invariant
scaling needs the *full* state RMS, measured in the stream
(:attr:`~soft_rom.reduce.data.ReducedData.pairs_sq_norm`).
"""

from __future__ import annotations

from collections.abc import Callable
import time
from typing import Any

import numpy as np

from soft_rom.data import Episode
from soft_rom.errors import DimensionError
from soft_rom.reduce.data import ReducedData, TrainingData
from soft_rom.scale.blocks import (
    DEFAULT_BLOCK_BYTES,
    Executor,
    LocalExecutor,
    row_plan,
    SnapshotSet,
)
from soft_rom.scale.pod import StreamingPOD

__all__ = ['GRAM_MEMORY', 'ColumnWindow', 'StreamingReducer', 'episode_head', 'make_executor']

#: Largest memory (bytes) the ``'auto'`` POD method lets the exact ``'gram'`` method hold
#: (the Gram matrix and two row blocks); beyond, ``'randomized'``.
GRAM_MEMORY = 1 << 30


class ColumnWindow:
    """Lazy view of columns ``[0, stop)`` of an on-disk ``(n, k)`` array (no data read).

    ``Episode.slice`` would read a zarr array eagerly; this keeps training-time limits
    (``t_max``) lazy for the streaming passes and for Dask.
    """

    def __init__(self, array: Any, stop: int) -> None:
        self.array = array
        self.stop = int(stop)
        self.shape = (int(array.shape[0]), self.stop)
        self.chunks = getattr(array, 'chunks', None)
        self.dtype = getattr(array, 'dtype', np.dtype(np.float64))

    def __getitem__(self, key: Any) -> Any:
        rows, cols = key
        a, b, step = cols.indices(self.stop)
        if step != 1:
            raise DimensionError('ColumnWindow supports contiguous column slices only.')
        return self.array[rows, a:b]

    def to_dask(self) -> Any:
        """The window as a dask array (the stored array's own, else ``from_zarr``)."""
        import dask.array as da
        if hasattr(self.array, 'to_dask'):      # a training set's checked StoredArray
            base = self.array.to_dask()
        elif type(self.array).__module__.startswith('zarr'):
            base = da.from_zarr(self.array, inline_array=True)
        else:
            base = da.from_array(self.array, inline_array=True)
        return base[:, :self.stop]


def make_executor(client: Any = None,
                  progress: Callable[[int], Any] | None = None) -> Executor:
    """Local executor, or a Dask one for a ``Client`` or a scheduler address string."""
    if client is None:
        return LocalExecutor(progress)
    from soft_rom.scale.dask_backend import DaskExecutor
    return DaskExecutor(client)


def episode_head(ep: Episode, k: int) -> Episode:
    """The first ``k`` samples of ``ep``; a stored (lazy) ``Q`` stays on disk (ColumnWindow).

    ``Episode.slice`` reads a stored ``Q`` into memory: at paper scale gigabytes that a
    streaming fit never reads.
    """
    if ep.Q is None or isinstance(ep.Q, np.ndarray):
        return ep.slice(0, k)
    return Episode(t=ep.t[:k], U=ep.U[:, :k], Y=ep.Y[:, :k], Q=ColumnWindow(ep.Q, k),
                   name=ep.name, metadata=dict(ep.metadata))


class StreamingReducer:
    """Reduce training data by streaming the snapshots through a POD (locally or on Dask).

    Parameters
    ----------
    energy : float
        POD energy fraction when ``r`` is not given (paper: 0.95).
    method : {'auto', 'gram', 'randomized'}
        POD method (module docstring).
    n_coords : int, optional
        Coordinates kept per snapshot with ``'randomized'`` (default: what the learner needs
        plus 10). ``'gram'`` keeps them all.
    power_iters, oversample, block_bytes, seed
        Options of :class:`~soft_rom.scale.pod.StreamingPOD`.
    client : dask.distributed.Client or str, optional
        Run the passes on this Dask cluster (workers read the zarr chunks).
    progress : callable, optional
        ``progress(n_columns_done)`` (local executor).
    """

    name = 'streaming'

    def __init__(self, energy: float = 0.95, *, method: str = 'auto',
                 n_coords: int | None = None, power_iters: int = 1, oversample: int = 10,
                 block_bytes: int = DEFAULT_BLOCK_BYTES, seed: int = 0, client: Any = None,
                 progress: Callable[[int], Any] | None = None) -> None:
        self.energy = energy
        self.method = method
        self.n_coords = n_coords
        self.power_iters = power_iters
        self.oversample = oversample
        self.block_bytes = block_bytes
        self.seed = seed
        self.client = client
        self.progress = progress

    def __repr__(self) -> str:
        return f'StreamingReducer(method={self.method!r}, n_coords={self.n_coords!r})'

    def pod_method(self, snaps: SnapshotSet) -> str:
        """``'gram'`` or ``'randomized'``: the method that :attr:`method` means for ``snaps``."""
        if self.method != 'auto':
            return str(self.method)
        K = snaps.n_total
        chunks = snaps.storage_chunks()
        if chunks is not None and chunks[0] >= snaps.n and snaps.n * K * 8 > 4 * self.block_bytes:
            return 'randomized'             # stored in full-height chunks: no row blocks
        rows = max(b.rows[1] - b.rows[0] for b in row_plan(snaps, block_bytes=self.block_bytes))
        return 'gram' if 8 * (2 * rows * K + 2 * K * K) <= GRAM_MEMORY else 'randomized'

    def reduce(self, data: TrainingData, *, basis: str = 'pod', r: int | None = None,
               n_coordinates: int | None = None, what: str = 'the POD') -> ReducedData:
        """Stream the snapshots once through the POD; keep coordinates, inputs and outputs.

        Parameters
        ----------
        data : TrainingData
            Episodes with full states ``Q`` (lazy zarr arrays for large sets).
        basis : {'pod', 'identity', 'none'}
            What the learner needs; ``'identity'`` is served by POD coordinates (DMDc works
            in any orthonormal basis), ``'none'`` reads no snapshot.
        r : int, optional
            POD dimension; default by :attr:`energy`.
        n_coordinates : int, optional
            Coordinates the learner needs (``'randomized'`` keeps 10 more).
        what : str
            The learner, for messages.
        """
        eps = data.episodes
        common: dict[str, Any] = dict(U=tuple(ep.U for ep in eps), Y=tuple(ep.Y for ep in eps),
                      t=tuple(ep.t for ep in eps), y_ref=data.y_ref,
                      names=tuple(ep.name for ep in eps), channels=dict(data.names),
                      metadata={'training': dict(data.provenance)} if data.provenance else {})
        if basis == 'none':
            return ReducedData(coordinates=None, basis='none', **common)
        missing = [ep.name for ep in eps if ep.Q is None]
        if missing:
            raise DimensionError(f'episodes {missing} have no full states Q: {what} needs '
                                 'them (ERA/OKID does not; on measured outputs fit with '
                                 '--coordinates outputs).')
        if data.q_ref is None:
            raise DimensionError('q_ref is missing: the streaming POD centres the snapshots '
                                 'on it.')
        own = isinstance(self.client, str)
        client = self.client
        if own:
            from soft_rom.scale.dask_backend import connect
            client = connect(self.client)
        try:
            return self._reduce(data, common, r, n_coordinates, client)
        finally:
            if own:
                client.close()

    def _reduce(self, data: TrainingData, common: dict[str, Any], r: int | None,
                n_coordinates: int | None, client: Any) -> ReducedData:
        eps = data.episodes
        t0 = time.perf_counter()
        snaps = SnapshotSet([ep.Q for ep in eps], data.q_ref, [ep.name for ep in eps])
        method = self.pod_method(snaps)
        n_coords = self.n_coords
        if method == 'gram':
            n_coords = snaps.n_total            # every coordinate: exact
        elif n_coords is None and n_coordinates is not None:
            n_coords = int(n_coordinates) + 10
        pod = StreamingPOD(r=r, energy=self.energy, method=method, n_coords=n_coords,
                           power_iters=self.power_iters, oversample=self.oversample,
                           block_bytes=self.block_bytes, seed=self.seed,
                           compute_basis=method != 'gram',
                           executor=make_executor(client, self.progress),
                           progress=self.progress)
        pod.fit(snaps)
        # Squared norm of the centred snapshots that start a pair: total minus the last
        # column of each episode (E single columns, read directly).
        last = 0.0
        for ep in eps:
            k = ep.Q.shape[1]
            x = np.asarray(ep.Q[:, k - 1:k], dtype=np.float64)[:, 0] - pod.q_ref_
            last += float(x @ x)
        seconds = time.perf_counter() - t0
        meta = dict(common.pop('metadata'))
        meta['scale'] = _summary(pod, seconds)
        return ReducedData(coordinates=tuple(pod.coords_), basis='pod', energy=pod.energy_,
                           singular_values=pod.singular_values_, n_states=int(snaps.n),
                           pairs_sq_norm=pod.total_energy_ - last, q_ref=pod.q_ref_,
                           modes=getattr(pod, 'modes_', None), metadata=meta, **common)


def _summary(pod: StreamingPOD, seconds: float) -> dict[str, Any]:
    """JSON-ready provenance of the streaming POD (stored in model metadata)."""
    return {
        'pod_method': pod.method, 'n_coords': int(pod.singular_values_.size),
        'passes': int(pod.n_passes_), 'power_iters': int(pod.power_iters),
        'oversample': int(pod.oversample), 'seed': int(pod.seed),
        'backend': type(pod.executor).__name__ if pod.executor is not None
        else 'LocalExecutor',
        'n_states': int(pod.q_ref_.size), 'n_snapshots': int(sum(z.shape[1] for z in pod.coords_)),
        'singular_values': pod.singular_values_[:200].tolist(),
        'energy_captured_l': float(pod.energy_[-1]), 'seconds': float(seconds),
    }
