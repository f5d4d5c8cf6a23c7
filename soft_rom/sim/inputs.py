"""Random chamber-pressure sequences for simulation episodes (seeded, reproducible).

A sequence is a train of random steps (hold times drawn uniformly in ``hold`` seconds,
levels uniform in the amplitude range) passed through a first-order low-pass filter of time
constant ``smoothing`` -- smooth random steps, as pneumatic valves deliver. With
``antagonistic=True`` the two chambers of a segment get ``bias + a`` and ``bias - a``
(the paper's antagonistic fluid elastomer actuators); otherwise each chamber draws its own
level in ``[0, amplitude]``.

Episode ``i`` with seed ``s`` draws from ``numpy.random.default_rng([s, i])``: episodes are
independent of each other and of how many are generated.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import ConfigError

__all__ = ['DEFAULT_AMPLITUDE', 'random_pressures']

#: Default pressure amplitude (Pa): tail deflections of tens of mm on the default eel.
DEFAULT_AMPLITUDE = 50e3


def random_pressures(n_steps: int, dt: float, *, seed: int = 0, episode: int = 1,
                     amplitude: float = DEFAULT_AMPLITUDE, antagonistic: bool = True,
                     bias: float = 0.0, hold: tuple[float, float] = (0.1, 0.4),
                     smoothing: float = 0.02,
                     n_chambers: int = 6) -> NDArray[np.float64]:
    """Random smooth step pressures for one episode.

    Parameters
    ----------
    n_steps : int
        Number of samples ``k``.
    dt : float
        Sample period (s).
    seed, episode : int
        Reproducibility: the generator is ``default_rng([seed, episode])``.
    amplitude : float
        Pa. Antagonistic: ``a`` uniform in ``[-amplitude, amplitude]``; otherwise each
        chamber's level is uniform in ``[0, amplitude]``.
    antagonistic : bool
        Chambers ``2i`` and ``2i+1`` (0-based) of segment ``i`` get ``bias + a`` and ``bias - a``.
    bias : float
        Pa, common offset of antagonistic pairs.
    hold : (float, float)
        Range of hold times of each level (s).
    smoothing : float
        Time constant (s) of the first-order filter (0 for raw steps).
    n_chambers : int
        Number of chambers ``m`` (even when antagonistic).

    Returns
    -------
    ndarray, shape (n_chambers, n_steps)
        Gauge pressures in Pa; sample ``j`` is held over ``[j dt, (j + 1) dt)``.
    """
    if n_steps < 1 or dt <= 0:
        raise ConfigError(f'need n_steps >= 1 and dt > 0; got {n_steps}, {dt}.')
    if not 0 < hold[0] <= hold[1]:
        raise ConfigError(f'hold must be (min, max) seconds with 0 < min <= max; got {hold}.')
    if antagonistic and n_chambers % 2:
        raise ConfigError(f'antagonistic pairs need an even number of chambers; got {n_chambers}.')
    rng = np.random.default_rng([int(seed), int(episode)])
    n_drive = n_chambers // 2 if antagonistic else n_chambers
    levels = np.empty((n_drive, n_steps))
    for c in range(n_drive):
        j = 0
        while j < n_steps:
            length = max(1, int(round(rng.uniform(*hold) / dt)))
            if antagonistic:
                levels[c, j:j + length] = rng.uniform(-amplitude, amplitude)
            else:
                levels[c, j:j + length] = rng.uniform(0.0, amplitude)
            j += length
    if smoothing > 0:
        a = float(np.exp(-dt / smoothing))
        out = np.empty_like(levels)
        state = np.zeros(n_drive)               # the episode starts from zero pressure
        for j in range(n_steps):
            state = a * state + (1 - a) * levels[:, j]
            out[:, j] = state
        levels = out
    if not antagonistic:
        return levels
    U = np.empty((n_chambers, n_steps))
    U[0::2] = bias + levels
    U[1::2] = bias - levels
    return U
