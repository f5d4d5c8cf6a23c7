"""The eel FOM's configuration and what it produces (:mod:`soft_rom.sim.eel`).

:class:`EelConfig` (geometry, material, discretization), :class:`Linearization` (the FOM
linearized at rest) and :class:`SimulationResult` (an integrated episode), plus the
:data:`StepCallback` signature that streams samples out of a simulation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
import scipy.sparse as sp

from soft_rom.data import Episode
from soft_rom.errors import ConfigError

__all__ = ['EelConfig', 'Linearization', 'SimulationResult', 'StepCallback']

Array = NDArray[np.float64]

#: ``callback(j, t, u, centerline, positions)`` called for every recorded sample; ``positions``
#: (n_nodes, 3) is a view of the solver's buffer, valid only during the call.
StepCallback = Callable[[int, float, Array, Array, Array], None]


@dataclass(frozen=True)
class EelConfig:
    """Geometry, material and discretization of the eel FOM (SI units).

    Parameters
    ----------
    resolution : int
        Mesh refinement factor: the grid has ``(48 r, 4 r, 6 r)`` cells along ``(x, y, z)``.
        ``r = 1`` (default, 5,145 DOF) keeps the demo quick; ``r = 2``: 33,237 DOF;
        ``r = 3``: 103,305; ``r = 4``: 234,357 DOF, the paper's size (231,336).
    length, width, height : float
        Body box (m): ``x`` in ``[0, length]``, ``y`` and ``z`` centred on 0.
    segments : tuple of (float, float)
        ``x``-ranges of the three actuated body segments; between them are couplers.
    couplers : tuple of (float, float)
        ``x``-ranges of the stiffer couplers.
    chamber_margin : float
        Solid length (m) at each end of a segment, closing its chambers.
    chamber_y : float
        Half-width (m) of a chamber in ``y``.
    chamber_z : (float, float)
        ``|z|`` range (m) of a chamber (top chamber ``z > 0``, bottom ``z < 0``).
    fiber_reinforced : bool
        Chambers are fiber-reinforced (default): hoop fibers carry the pressure on the
        lateral walls, so only the end caps (walls normal to ``x``) receive the pressure
        load. ``False`` loads every wall; the thin silicone walls then balloon, and the
        ballooning's second-order shortening dominates the bending at a few kPa -- the
        reason fluid elastomer actuators are reinforced.
    follower : bool
        Pressure acts on the current wall geometry (default, as SOFA's surface pressure
        constraints); ``False``: dead loads on the rest geometry (constant ``B``). Dead axial
        cap forces stay parallel while the caps rotate with the bending, which adds a large
        spurious moment (about 25 % of the response at 40 kPa).
    young_soft, young_coupler : float
        Young's moduli (Pa) of the silicone body and of the couplers.
    poisson : float
        Poisson's ratio (silicone-like, moderately compressible to limit locking of linear
        tetrahedra).
    density : float
        kg/m^3.
    rayleigh_mass, rayleigh_stiffness : float
        ``alpha`` (1/s) and ``beta`` (s) of ``C = alpha M + beta K_0``.
    n_centerline : int
        Number of centerline points (20 in the paper).
    """

    resolution: int = 1
    length: float = 1.2
    width: float = 0.06
    height: float = 0.08
    segments: tuple[tuple[float, float], ...] = ((0.15, 0.40), (0.45, 0.70), (0.75, 1.00))
    couplers: tuple[tuple[float, float], ...] = ((0.40, 0.45), (0.70, 0.75))
    chamber_margin: float = 0.025
    chamber_y: float = 0.015
    chamber_z: tuple[float, float] = (0.01333, 0.02667)
    fiber_reinforced: bool = True
    follower: bool = True
    young_soft: float = 1.0e6
    young_coupler: float = 20.0e6
    poisson: float = 0.42
    density: float = 1100.0
    rayleigh_mass: float = 0.3
    rayleigh_stiffness: float = 0.02
    n_centerline: int = 20

    def grid_shape(self) -> tuple[int, int, int]:
        """Number of cells ``(nx, ny, nz)``."""
        r = int(self.resolution)
        if r != self.resolution or r < 1:
            raise ConfigError(f'resolution must be a positive integer; got {self.resolution!r}.')
        return 48 * r, 4 * r, 6 * r

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dictionary (provenance sidecars)."""
        return asdict(self)


@dataclass(frozen=True)
class Linearization:
    """The FOM linearized at rest: ``M q'' + C q' + K q = B u``, ``y = E q + y_ref``.

    ``q`` is the nodal displacement from ``q_ref`` (node-major, ``3 n_nodes``). Clamped DOFs
    are included with zero rows and columns in ``K`` and ``C`` (and ``B``); ``free`` marks the
    others. Output ``y = [x_1..x_N, z_1..z_N]`` of the centerline.

    Attributes
    ----------
    M : scipy.sparse matrix, shape (n, n)
        Lumped (diagonal) mass, kg.
    C, K : scipy.sparse matrix, shape (n, n)
        Rayleigh damping and rest stiffness.
    B : ndarray, shape (n, m)
        Force per unit chamber pressure (N/Pa).
    E : scipy.sparse matrix, shape (p, n)
        Output map.
    q_ref : ndarray, shape (n,)
    y_ref : ndarray, shape (p,)
    free : ndarray of bool, shape (n,)
    """

    M: sp.spmatrix
    C: sp.spmatrix
    K: sp.spmatrix
    B: Array
    E: sp.spmatrix
    q_ref: Array
    y_ref: Array
    free: NDArray[np.bool_]


@dataclass
class SimulationResult:
    """What :meth:`EelModel.simulate` produced.

    Attributes
    ----------
    t : ndarray, shape (k,)
        Sample times (s), ``t_j = j dt``.
    pressures : ndarray, shape (m, k)
        Chamber pressures (Pa), ``u_j`` held over ``[t_j, t_{j+1})``.
    centerline : ndarray, shape (N, 3, k)
        Centerline points (m).
    states : ndarray, shape (n_nodes, 3, k) or None
        Nodal positions (m), only with ``store_states=True``.
    info : dict
        Wall time, DOF, solver statistics.
    """

    t: Array
    pressures: Array
    centerline: Array
    states: Array | None = None
    info: dict[str, Any] = field(default_factory=dict)

    def outputs(self, components: str = 'xz') -> Array:
        """Output matrix ``Y``, shape (len(components) * N, k): component-major rows."""
        idx = ['xyz'.index(c) for c in components]
        return np.concatenate([self.centerline[:, i, :] for i in idx], axis=0)

    def to_episode(self, name: str = '', components: str = 'xz') -> Episode:
        """As a :class:`soft_rom.data.Episode` (``Q`` = nodal positions if stored)."""
        Q = None if self.states is None else self.states.reshape(-1, self.states.shape[-1])
        return Episode(t=self.t, U=self.pressures, Y=self.outputs(components), Q=Q, name=name,
                       metadata=dict(self.info))
