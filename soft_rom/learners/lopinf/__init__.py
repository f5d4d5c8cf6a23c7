"""Lagrangian Operator Inference (paper section 2.2): a second-order ROM with SPD K and C.

* :mod:`~soft_rom.learners.lopinf.learner` -- :class:`LOpInf`, the learner;
* :mod:`~soft_rom.learners.lopinf.solvers` and :mod:`~soft_rom.learners.lopinf.ipm` -- the
  SPD-constrained operator fit (cvxpy reference, dedicated fast solver);
* :mod:`~soft_rom.learners.lopinf.margins` -- damping margin and Tikhonov selection;
* :mod:`~soft_rom.learners.lopinf.mass` -- a learned SPD mass matrix;
* :mod:`~soft_rom.learners.lopinf.refine` -- refinement by the simulation (output) error;
* :mod:`~soft_rom.learners.lopinf.cubic` -- restoring forces from a quartic potential.
"""

from __future__ import annotations

from soft_rom.learners.lopinf.learner import LOpInf

__all__ = ['LOpInf']
