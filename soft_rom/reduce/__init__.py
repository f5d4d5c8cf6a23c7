"""Reduce once, then learn: the reducers and the reduced data every learner fits on.

A reducer turns :class:`TrainingData` (episodes with full states, possibly lazy on disk) into
:class:`ReducedData` (each episode's coordinates in an orthonormal basis, with its inputs and
outputs), once; the learners (:mod:`soft_rom.learners`) then fit any number of models on it.

* :class:`InMemoryPOD` -- the snapshots in memory, a thin SVD
  (:mod:`soft_rom.reduce.memory`);
* :class:`StreamingReducer` -- the snapshots streamed from disk in blocks, locally or on a
  Dask cluster, with bounded memory (:mod:`soft_rom.reduce.streaming`, on the streaming POD of
  :mod:`soft_rom.scale`).

Both give the same reduced data to rounding when the streamed POD is exact (``'gram'``, or
every coordinate kept), so a model fitted on either is the same model.
"""

from __future__ import annotations

from soft_rom.reduce.data import BASES, ReducedData, TrainingData
from soft_rom.reduce.memory import InMemoryPOD, training_data
from soft_rom.reduce.streaming import ColumnWindow, episode_head, StreamingReducer

__all__ = ['BASES', 'ColumnWindow', 'episode_head', 'InMemoryPOD', 'ReducedData',
           'StreamingReducer', 'TrainingData', 'training_data']
