"""The embedded full-order model (FOM): a corotational-FEM eel soft robot.

``EelModel`` builds the mesh and operators and integrates episodes
(:meth:`EelModel.simulate`); :func:`random_pressures` draws the seeded pressure sequences of
episodes Ep 1-Ep 6; :meth:`EelModel.linearization` exports ``(M, C, K, B, E)`` at rest.
numpy and scipy; the ``fast`` extra (numba for the element loop, CHOLMOD from scikit-sparse
for the linear solve) makes a step about 3x cheaper on the paper-size mesh. No ROS.

Modules: :mod:`~soft_rom.sim.eel` (the model and its time stepping), with
:mod:`~soft_rom.sim.eel_types` (configuration, linearization, results),
:mod:`~soft_rom.sim.eel_geometry` (chambers, walls, pressure loads, centerline map) and
:mod:`~soft_rom.sim.linsolve` (the rest-system factor, PCG, memory estimate);
:mod:`~soft_rom.sim.mesh`, :mod:`~soft_rom.sim.fem`, :mod:`~soft_rom.sim.inputs`,
:mod:`~soft_rom.sim.record` (episodes to bags).
"""

from __future__ import annotations

from soft_rom.sim.eel import (
                              EelConfig,
                              EelModel,
                              Linearization,
                              simulate_episode,
                              SimulationResult,
                              StepCallback,
)
from soft_rom.sim.fem import CorotationalFEM, lame, polar_rotation
from soft_rom.sim.inputs import random_pressures
from soft_rom.sim.mesh import box_grid, TetMesh, tetrahedralize

__all__ = [
    'CorotationalFEM',
    'EelConfig',
    'EelModel',
    'Linearization',
    'SimulationResult',
    'StepCallback',
    'TetMesh',
    'box_grid',
    'lame',
    'polar_rotation',
    'random_pressures',
    'simulate_episode',
    'tetrahedralize',
]

