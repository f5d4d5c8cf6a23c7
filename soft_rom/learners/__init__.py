"""Learners: hyperparameters in ``__init__``, ``fit(data) -> self``, a frozen ``model_``.

- :class:`LOpInf` -- Lagrangian Operator Inference (second-order, SPD ``K`` and ``C``);
- :class:`DMDc` -- dynamic mode decomposition with control;
- :class:`ERAOKID` -- eigensystem realization with observer/Kalman filter identification.

LOpInf and DMDc fit on reduced data (:class:`~soft_rom.reduce.ReducedData`); ERA/OKID on the
inputs and outputs of one episode.
"""

from __future__ import annotations

from soft_rom.learners.dmdc import channel_scale, DMDc, dmdc_reduced_operators
from soft_rom.learners.era import decimate, era, ERAOKID, hankel_rank, okid_markov
from soft_rom.learners.lopinf import LOpInf
from soft_rom.learners.lopinf.solvers import (
    CvxpySolver,
    DEFAULT_EPS,
    FastSPDSolver,
    LOpInfSolution,
    OperatorSolver,
)

__all__ = ['CvxpySolver', 'DEFAULT_EPS', 'DMDc', 'ERAOKID', 'FastSPDSolver', 'LOpInf',
           'LOpInfSolution', 'OperatorSolver', 'channel_scale', 'decimate',
           'dmdc_reduced_operators', 'era', 'hankel_rank', 'okid_markov']
