"""Closed-loop control on the ROMs: MPC, offset-free estimation, the FOM as the plant.

ROS-free. :class:`MPC` (linear, condensed, warm-started QP from a solver made for MPC) on
any linear ROM; :class:`OffsetFreeEstimator` (the ROM state plus an output disturbance,
estimated by a steady-state Kalman filter); :class:`Controller` (both, with the safety rules
the node follows); :func:`run_closed_loop` (the embedded FOM as the plant, seen through a
noisy motion-capture-like sensor); references (:func:`parse_reference`).
"""

from soft_rom.control.controller import Command, Controller
from soft_rom.control.estimator import EstimatorConfig, OffsetFreeEstimator
from soft_rom.control.loop import (
    ClosedLoopResult,
    FOMPlant,
    open_loop_plan,
    ROMPlant,
    run_closed_loop,
    Sensor,
    simulate_inputs,
)
from soft_rom.control.mpc import input_bounds, MPC, MPCConfig, MPCStep
from soft_rom.control.reference import (
    check_moves,
    load_reference,
    parse_reference,
    Reference,
)

__all__ = [
    'ClosedLoopResult',
    'Command',
    'Controller',
    'EstimatorConfig',
    'FOMPlant',
    'MPC',
    'MPCConfig',
    'MPCStep',
    'OffsetFreeEstimator',
    'ROMPlant',
    'Reference',
    'Sensor',
    'check_moves',
    'input_bounds',
    'load_reference',
    'open_loop_plan',
    'parse_reference',
    'run_closed_loop',
    'simulate_inputs',
]
