"""Learners: hyperparameters in ``__init__``, ``fit(...) -> self``, a frozen ``model_``.

- :class:`LOpInf` -- Lagrangian Operator Inference (second-order, SPD ``K`` and ``C``);
- :class:`DMDc` -- dynamic mode decomposition with control;
- :class:`ERAOKID` -- eigensystem realization with observer/Kalman filter identification.
"""

from __future__ import annotations

from soft_rom.learners.dmdc import DMDc
from soft_rom.learners.era import ERAOKID
from soft_rom.learners.lopinf import LOpInf
from soft_rom.learners.lopinf_solvers import (
    CvxpySolver,
    DEFAULT_EPS,
    FastSPDSolver,
    LOpInfSolution,
    OperatorSolver,
)

__all__ = ['CvxpySolver', 'DEFAULT_EPS', 'DMDc', 'ERAOKID', 'FastSPDSolver', 'LOpInf',
           'LOpInfSolution', 'OperatorSolver']
