"""Pieces of the closed-loop study that need no FOM: the weight choice and the reach floor."""

from __future__ import annotations

from _eel_rom import modal_rom
import numpy as np

from soft_rom.control import MPCConfig, parse_reference, Reference
from soft_rom.control.study import _reach_floor
from soft_rom.sim import random_pressures


def test_reach_floor_is_zero_for_what_the_model_produces_and_not_for_the_wave() -> None:
    model = modal_rom(4)
    k = 900
    U = random_pressures(k, 1e-3, seed=4, episode=1, amplitude=20e3)
    U = np.repeat(U[:, ::10], 10, axis=1)[:, :k]          # 10 ms holds: the MPC's own grid
    feasible = Reference(t=np.arange(k) * 1e-3, Y=model.simulate(U))
    cfg = MPCConfig(rate_weight=1e-9)
    assert _reach_floor(model, feasible, cfg, 0.6) < 1e-3
    # a 2 Hz travelling wave along 20 points is not a shape 3 bending pairs make
    wave = parse_reference('wave:f=2,wavelength=0.8,amplitude=0.005', model, duration=0.9)
    assert _reach_floor(model, wave, cfg, 0.6) > 0.2
