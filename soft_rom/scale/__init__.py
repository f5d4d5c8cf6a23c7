"""Fitting at scale: POD, projection and fits streamed from disk, locally or on Dask.

Training sets larger than memory (the paper's 231,336-DOF FOM: 6 x 2,000 snapshots, 22 GB)
are read in column blocks by a streaming POD (:class:`StreamingPOD`, a few passes, bounded
memory) whose last pass also yields the reduced coordinates; LOpInf, DMDc and the output
fits then run in memory on reduced data, and ERA/OKID needs inputs and outputs only.

>>> from soft_rom.scale import fit_streaming                       # doctest: +SKIP
>>> model = fit_streaming('train.zarr', 'lopinf', r=16)               # doctest: +SKIP
>>> model = fit_streaming('train.zarr', 'dmdc', r=16,
...                       client='tcp://scheduler:8786')              # doctest: +SKIP

Several models from one pass over the data::

    red = reduce_streaming('train.zarr', n_coords=60)
    models = [fit_reduced_model(red, 'lopinf', r) for r in (4, 8, 16)]

Modules: :mod:`~soft_rom.scale.blocks` (snapshot sources, block plans, the local executor),
:mod:`~soft_rom.scale.kernels` (what a pass computes on one block),
:mod:`~soft_rom.scale.dask_backend` (the Dask executor), :mod:`~soft_rom.scale.pod` (the
streaming POD) and :mod:`~soft_rom.scale.streaming` (reduce once, then fit).
"""

from soft_rom.scale.blocks import LocalExecutor, SnapshotSet
from soft_rom.scale.pod import StreamingPOD
from soft_rom.scale.streaming import (
    fit_reduced_model,
    fit_streaming,
    open_training_data,
    reduce_streaming,
    ReducedData,
    TrainingData,
)

__all__ = [
    'LocalExecutor',
    'ReducedData',
    'SnapshotSet',
    'StreamingPOD',
    'TrainingData',
    'fit_reduced_model',
    'fit_streaming',
    'open_training_data',
    'reduce_streaming',
]
