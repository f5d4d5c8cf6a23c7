"""Streaming POD of snapshot sets larger than memory, locally or on a Dask cluster.

Training sets larger than memory (the paper's 231,336-DOF FOM: 6 x 2,000 snapshots, 22 GB)
are read in blocks by a streaming POD (:class:`StreamingPOD`, a few passes, bounded memory)
whose last pass also yields the reduced coordinates. The reducer built on it is
:class:`soft_rom.reduce.StreamingReducer`; the learners then fit on the reduced data.

Modules: :mod:`~soft_rom.scale.blocks` (snapshot sources, block plans, the local executor),
:mod:`~soft_rom.scale.kernels` (what a pass computes on one block),
:mod:`~soft_rom.scale.dask_backend` (the Dask executor) and :mod:`~soft_rom.scale.pod` (the
streaming POD).
"""

from soft_rom.scale.blocks import LocalExecutor, SnapshotSet
from soft_rom.scale.pod import StreamingPOD

__all__ = ['LocalExecutor', 'SnapshotSet', 'StreamingPOD']
