"""What the studies run: :class:`StudyConfig`, and the BLAS threads they run with."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Any

from soft_rom.errors import ConfigError
from soft_rom.study.presets import ERA_EEL_OPTIONS

__all__ = ['blas_threads', 'StudyConfig']


@dataclass(frozen=True)
class StudyConfig:
    """What the studies run.

    Parameters
    ----------
    resolution : int
        Mesh resolution of the eel FOM (1 = the fast default).
    n_episodes : int
        Episodes simulated (the paper: 6).
    seed : int
        Seed of the random pressure sequences (episode ``i`` uses ``[seed, i]``).
    duration, dt : float
        Episode length and time step (s): 2 s at 1 ms in the paper.
    storage : str
        Bag storage, ``'mcap'`` or ``'sqlite3'``.
    record_state : bool
        Record the full FEM state in the bags (needed by LOpInf and DMDc).
    t_train : float
        End of training in study 1 (s).
    r_lopinf, r_dmdc, r_era : tuple of int
        Reduced dimensions swept.
    shape_times : tuple of float
        Times of the centerline-shape figure.
    jobs : int
        Processes used to simulate episodes.
    sim_options : dict
        Extra keywords of :func:`soft_rom.sim.record.record_episodes` (e.g. ``amplitude``).
    era_options : dict
        Hyperparameters of :class:`~soft_rom.learners.era.ERAOKID` (default
        :data:`soft_rom.study.presets.ERA_EEL_OPTIONS`).
    r_cubic : tuple of int
        Reduced dimensions of the cubic (quartic-potential) LOpInf; empty: not fitted. One
        small r by default: its conic fit grows like r⁴.
    cubic_options : dict, optional
        ``reg``, ``eps4`` of the cubic fit, fixed; ``None`` (default): chosen on held-out
        training data, as ``soft-rom fit --forces cubic`` does
        (:class:`~soft_rom.pipeline.cubic.HeldOutCubicSelection`).
    blas_threads : int or None
        BLAS threads of the whole run (threadpoolctl; ``None``: the library's default, one
        per core). Default 1: the SVDs and factorizations of the fits are medium-sized, and
        with one thread per core they run several times slower as soon as another process
        takes a core (the threads wait for each other); the simulation's worker processes
        take one each as well.
    streaming : bool
        Reduce by streaming the snapshots from disk with bounded memory
        (:class:`~soft_rom.reduce.StreamingReducer`) instead of loading them: the
        paper-scale run (:mod:`soft_rom.study.paper_scale`).
    """

    resolution: int = 1
    n_episodes: int = 6
    seed: int = 0
    duration: float = 2.0
    dt: float = 1e-3
    storage: str = 'mcap'
    record_state: bool = True
    t_train: float = 1.5
    r_lopinf: tuple[int, ...] = tuple(range(2, 23, 2))
    r_dmdc: tuple[int, ...] = tuple(range(2, 23, 2))
    r_era: tuple[int, ...] = tuple(range(20, 43, 2))
    shape_times: tuple[float, ...] = (0.5, 1.0, 2.0)
    jobs: int = 2
    sim_options: dict[str, Any] = field(default_factory=dict)
    era_options: dict[str, Any] = field(default_factory=lambda: dict(ERA_EEL_OPTIONS))
    r_cubic: tuple[int, ...] = (4,)
    cubic_options: dict[str, Any] | None = None
    blas_threads: int | None = 1
    streaming: bool = False

    def __post_init__(self) -> None:
        if self.n_episodes < 2:
            raise ConfigError('the studies need at least 2 episodes (6 for study 2).')
        if not 0 < self.t_train < self.duration:
            raise ConfigError(f't_train must lie in (0, {self.duration}); got {self.t_train}.')


def blas_threads(n: int | None) -> Any:
    """At most ``n`` BLAS threads in this process while the context lasts (threadpoolctl)."""
    if n is None:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:      # a ROS install without it: the library's default applies
        return contextlib.nullcontext()
    return threadpool_limits(limits=int(n), user_api='blas')
