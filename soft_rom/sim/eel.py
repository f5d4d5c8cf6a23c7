r"""The embedded full-order model (FOM): a pneumatic anguilliform (eel) soft robot.

A small cousin of the paper's SOFA eel (Sharma et al., section 3.1): a 1.2 m body along
``x``, with a soft unactuated head and tail, three soft body segments each carrying two
antagonistic fluid chambers (above and below the neutral plane ``z = 0``, so pressure bends
the body in the ``x``-``z`` plane), and stiffer couplers between segments. Linear-elastic
material with geometric nonlinearity by the corotational formulation
(:mod:`soft_rom.sim.fem`), Rayleigh damping ``C = alpha M + beta K_0``, chamber pressures
acting on the chamber walls, so that

.. math::

    M \ddot q + C \dot q + \frac{\partial U}{\partial q}(q) = B(q)\, u .

Choices, and why:

* **Chambers are fiber-reinforced** (``fiber_reinforced=True``): the pressure loads the end
  caps of each chamber (its walls normal to ``x``); the lateral walls' pressure is carried
  by hoop fibers, as in real fluid elastomer actuators. Loading every wall of a 1-cell-thick
  silicone chamber makes it balloon, and the second-order shortening of the ballooned walls
  swamps the bending (measured: 50 % deviation from the linear model at 10 kPa).
* **Pressure loads follow the walls** (``follower=True``), as SOFA's surface pressure
  constraints: forces use the current wall area vectors. Dead axial cap forces would stay
  parallel while the caps rotate with the bending and add a spurious moment (about 25 %
  of the response at 40 kPa). The linearization uses ``B = B(q_ref)``; at ``u = 0`` the
  load stiffness vanishes, so ``(M, C, K_0, B)`` is the exact linearization at rest.
* **Boundary condition: the head is clamped** -- all nodes of the face ``x = 0`` are fixed
  (eliminated from the solve; their DOFs stay in the state vector with zero displacement).
* **No gravity**: the body is neutrally buoyant (the paper studies the soft body dynamics
  in isolation), so the reference configuration ``q_ref`` is the undeformed rest shape.

**Time stepping** is SOFA's ``EulerImplicitSolver``: one linearized backward-Euler solve per
step,

.. math::

    (M + h C + h^2 K_t)\, v_{n+1} = M v_n + h \left(f(x_n) + B(x_n) u_n\right),
    \qquad x_{n+1} = x_n + h v_{n+1},

with ``K_t`` the rest stiffness ``K_0`` (``jacobian='rest'``, default: one back-substitution
per step with the Cholesky factor of ``M + hC + h^2 K_0``, computed once: CHOLMOD's with the
``fast`` extra, else LAPACK's banded one) or SOFA's warped corotational stiffness at ``x_n``
(``jacobian='corotated'``: conjugate gradients preconditioned by that same factor,
matrix-free products, 2-6 iterations per step). Both are consistent first-order schemes for
the same ODE (the nonlinearity is entirely in ``f(x_n)``). Measured on Ep 1 against a 4x
finer time step (corotated tangent): relative deviation error 1.3 % with ``'rest'`` and 1.0
% with ``'corotated'``, the latter costing about 2.4x more per step
(``benchmarks/bench_sim.py episodes``); hence ``'rest'`` by default. Input ``u_n`` is held
over ``[t_n, t_{n+1})``; sample ``n`` records ``(t_n, u_n, x_n)``, the convention of
:mod:`soft_rom.models`.

Outputs: 20 centerline points from ``x = 0`` to the tail tip, each the mean of the nodes of
the nearest grid cross-sections, linearly interpolated along ``x`` (a fixed sparse map of the
nodal positions). The linear-model output vector is ``[x_1..x_20, z_1..z_20]`` (p = 40).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
import functools
import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
import scipy.sparse as sp

from soft_rom.data import all_finite
from soft_rom.errors import ConfigError, DimensionError, SolverError
from soft_rom.sim.eel_geometry import (
    centerline_map,
    chamber_cells,
    pressure_matrix,
    triangle_forces,
    wall_triangles,
)
from soft_rom.sim.eel_types import EelConfig, Linearization, SimulationResult, StepCallback
from soft_rom.sim.fem import CorotationalFEM
from soft_rom.sim.inputs import DEFAULT_AMPLITUDE, random_pressures
from soft_rom.sim.linsolve import (
    _pcg,
    _SPDFactor,
    cholmod_available,
    LINEAR_SOLVERS,
    memory_estimate,
)
from soft_rom.sim.mesh import box_grid, TetMesh, tetrahedralize

__all__ = ['EelConfig', 'EelModel', 'EelStepper', 'LINEAR_SOLVERS', 'Linearization',
           'SimulationResult', 'StepCallback', 'cholmod_available', 'memory_estimate',
           'simulate_episode']

Array = NDArray[np.float64]


class EelModel:
    """The eel FOM: mesh, operators, time stepper.

    Parameters
    ----------
    config : EelConfig, optional
        Defaults to ``EelConfig()``; keyword arguments override its fields
        (``EelModel(resolution=2)``).

    Attributes
    ----------
    mesh : TetMesh
    fem : CorotationalFEM
    B : scipy.sparse.csr_matrix, shape (n_dof, 6)
        Force per unit pressure of each chamber.
    centerline_map : scipy.sparse.csr_matrix, shape (N, n_nodes)
        Centerline points = ``centerline_map @ positions``.
    free : ndarray of bool, shape (n_dof,)
    """

    n_chambers = 6

    def __init__(self, config: EelConfig | None = None, **overrides: Any) -> None:
        cfg = config or EelConfig()
        if overrides:
            try:
                cfg = replace(cfg, **overrides)
            except TypeError as err:
                raise ConfigError(f'unknown EelConfig field: {err}') from err
        self.config = cfg
        nx, ny, nz = cfg.grid_shape()
        xs, ys, zs = box_grid(cfg.length, cfg.width, cfg.height, nx, ny, nz)
        region, chambers = chamber_cells(cfg, xs, ys, zs)
        self.mesh: TetMesh = tetrahedralize(xs, ys, zs, region)
        young = np.where(self.mesh.region == 1, cfg.young_coupler, cfg.young_soft)
        self.fem = CorotationalFEM(self.mesh.nodes, self.mesh.tets, young=young,
                                   poisson=cfg.poisson, density=cfg.density)
        #: chamber wall triangles (n_tri, 3) and the chamber of each
        self.wall_triangles, self.wall_chamber = wall_triangles(
            xs, ys, zs, region, chambers, self.mesh, cfg.fiber_reinforced)
        self.B = pressure_matrix(self.wall_triangles, self.wall_chamber, self.mesh.nodes,
                                 self.n_chambers)
        self.free = np.repeat(self.mesh.nodes[:, 0] > 1e-12 * cfg.length, 3)
        self.centerline_map = centerline_map(self.mesh, xs, cfg.length, cfg.n_centerline)
        self._K0: sp.csr_matrix | None = None
        self._factor: dict[tuple[float, str], tuple] = {}

    # ------------------------------------------------------------------ operators
    def _triangle_forces(self, x: Array) -> Array:
        """Force per unit pressure on each corner of each wall triangle, shape (n_tri, 3)."""
        return triangle_forces(self.wall_triangles, x)

    def pressure_force(self, x: Array, u: Array) -> Array:
        """Nodal pressure forces (n_nodes, 3) at positions ``x`` for pressures ``u`` (6,).

        Follower loads (``config.follower``): the wall area vectors of the current
        configuration; otherwise the rest ones (``B u``).
        """
        if not self.config.follower:
            return (self.B @ u).reshape(-1, 3)
        f = self._triangle_forces(x) * u[self.wall_chamber][:, None]
        out = np.zeros((self.n_nodes, 3))
        for k in range(3):
            np.add.at(out, self.wall_triangles[:, k], f)
        return out

    @property
    def n_nodes(self) -> int:
        """Number of mesh nodes."""
        return self.mesh.n_nodes

    @property
    def n_dof(self) -> int:
        """Number of DOFs ``3 n_nodes`` (clamped ones included)."""
        return self.mesh.n_dof

    @property
    def q_ref(self) -> Array:
        """Rest positions, node-major, shape (n_dof,)."""
        return self.mesh.nodes.ravel()

    def stiffness(self) -> sp.csr_matrix:
        """Rest stiffness ``K_0`` (all DOFs), cached."""
        if self._K0 is None:
            self._K0 = self.fem.stiffness()
        return self._K0

    def output_matrix(self, components: str = 'xz') -> sp.csr_matrix:
        """Output map ``E``, shape (len(components) * N, n_dof), component-major rows."""
        W = self.centerline_map.tocoo()
        blocks = []
        for c in components:
            i = 'xyz'.index(c)
            blocks.append(sp.csr_matrix((W.data, (W.row, 3 * W.col + i)),
                                        shape=(W.shape[0], self.n_dof)))
        return sp.vstack(blocks).tocsr()

    def linearization(self, components: str = 'xz') -> Linearization:
        """The FOM linearized at rest: ``(M, C, K, B, E)`` with ``q_ref``, ``y_ref``, ``free``.

        Clamped DOFs have zero rows/columns in ``K``, ``C`` and ``B`` (their displacement is
        zero in every snapshot, so any projection basis is zero there too).
        """
        cfg = self.config
        keep = sp.diags(self.free.astype(np.float64))
        K = (keep @ self.stiffness() @ keep).tocsr()
        M = sp.diags(np.repeat(self.fem.mass, 3)).tocsr()
        C = (cfg.rayleigh_mass * M + cfg.rayleigh_stiffness * K).tocsr()
        B = np.asarray((keep @ self.B).todense())
        E = self.output_matrix(components)
        return Linearization(M=M, C=C, K=K, B=B, E=E, q_ref=self.q_ref.copy(),
                             y_ref=E @ self.q_ref, free=self.free.copy())

    def _rest_factor(self, dt: float,
                     solver: str = 'auto') -> tuple[_SPDFactor, sp.csr_matrix, Array]:
        if (dt, solver) not in self._factor:
            cfg = self.config
            K = self.stiffness()[self.free][:, self.free].tocsr()
            m = np.repeat(self.fem.mass, 3)[self.free]
            A = (sp.diags(m * (1 + dt * cfg.rayleigh_mass))
                 + (dt * cfg.rayleigh_stiffness + dt * dt) * K)
            self._factor = {(dt, solver): (_SPDFactor(A, solver), K, m)}
        return self._factor[dt, solver]

    # ------------------------------------------------------------------ simulation
    def stepper(self, dt: float = 1e-3, *, jacobian: str = 'rest', linear: bool = False,
                cg_rtol: float = 1e-8, cg_maxiter: int = 50,
                linear_solver: str = 'auto') -> EelStepper:
        """A time stepper at rest (``q = q_ref``, ``v = 0``) that takes one input at a time.

        :meth:`simulate` runs the same stepper over a whole input sequence; a closed loop
        (:mod:`soft_rom.control`) computes each input from the outputs so far. Arguments as
        in :meth:`simulate`.
        """
        if jacobian not in ('corotated', 'rest'):
            raise ConfigError(f"jacobian must be 'corotated' or 'rest'; got {jacobian!r}.")
        if not dt > 0:
            raise ConfigError(f'need dt > 0; got {dt}.')
        return EelStepper(self, float(dt), jacobian=jacobian, linear=linear, cg_rtol=cg_rtol,
                          cg_maxiter=cg_maxiter, linear_solver=linear_solver)

    def simulate(self, pressures: ArrayLike | Callable[[float], ArrayLike], n_steps: int,
                 dt: float = 1e-3, *, jacobian: str = 'rest', linear: bool = False,
                 store_states: bool = False, callback: StepCallback | None = None,
                 cg_rtol: float = 1e-8, cg_maxiter: int = 50,
                 linear_solver: str = 'auto') -> SimulationResult:
        """Integrate from rest (``q = q_ref``, ``v = 0``) for ``n_steps`` samples.

        Parameters
        ----------
        pressures : ndarray, shape (6, n_steps), or callable ``t -> (6,)``
            Chamber gauge pressures (Pa); sample ``j`` is held over ``[j dt, (j+1) dt)``.
        n_steps : int
            Number of recorded samples ``k`` (``k`` solves; the state after the last solve is
            not recorded).
        dt : float
            Time step (s), 1 ms in the paper.
        jacobian : {'corotated', 'rest'}
            Tangent of the linearized solve (see the module docstring).
        linear : bool
            Integrate the linearized FOM (``f = -K_0 q``) with the same scheme instead.
        store_states : bool
            Keep all nodal positions in the result (``n_nodes * 3 * k`` floats); prefer
            ``callback`` for large meshes.
        callback : callable, optional
            ``callback(j, t_j, u_j, centerline_j (N, 3), positions_j (n_nodes, 3))`` for each
            sample, to stream states (e.g. into a bag) without holding them.
        cg_rtol, cg_maxiter : float, int
            Conjugate-gradient tolerance (relative residual) and cap (corotated tangent).
        linear_solver : {'auto', 'cholmod', 'banded'}
            Factorization of the rest system (:mod:`soft_rom.sim.linsolve`): CHOLMOD when
            installed (``'auto'``), else LAPACK's banded Cholesky. Both give the same
            trajectories to round-off; CHOLMOD is faster on large meshes.

        Returns
        -------
        SimulationResult
        """
        if jacobian not in ('corotated', 'rest'):
            raise ConfigError(f"jacobian must be 'corotated' or 'rest'; got {jacobian!r}.")
        n_steps = int(n_steps)
        if n_steps < 1 or not dt > 0:
            raise ConfigError(f'need n_steps >= 1 and dt > 0; got {n_steps}, {dt}.')
        U = self._pressures(np.stack([np.asarray(pressures(j * dt), dtype=np.float64).reshape(
            self.n_chambers) for j in range(n_steps)], axis=1) if callable(pressures)
            else pressures, n_steps)
        t0 = time.perf_counter()
        stepper = self.stepper(dt, jacobian=jacobian, linear=linear, cg_rtol=cg_rtol,
                               cg_maxiter=cg_maxiter, linear_solver=linear_solver)
        t_factor = time.perf_counter() - t0
        t = np.arange(n_steps, dtype=np.float64) * dt
        W = self.centerline_map
        centerline = np.empty((W.shape[0], 3, n_steps))
        states = np.empty((self.n_nodes, 3, n_steps)) if store_states else None
        BU = None if stepper.follower else (self.B @ U)[self.free]      # (n_free, k)
        for j in range(n_steps):
            centerline[:, :, j] = stepper.centerline()
            if states is not None:
                states[:, :, j] = stepper.x
            if callback is not None:
                callback(j, float(t[j]), U[:, j], centerline[:, :, j], stepper.x)
            stepper.step(U[:, j], None if BU is None else BU[:, j])
        info = self._info(stepper.factor.kind, n_steps, dt, 'linear' if linear else jacobian,
                          time.perf_counter() - t0, t_factor, stepper.cg_iterations,
                          stepper.cg_worst_residual)
        return SimulationResult(t=t, pressures=U, centerline=centerline, states=states, info=info)

    def _pressures(self, pressures: ArrayLike, n_steps: int) -> Array:
        """The first ``n_steps`` columns of a pressure sequence, checked: shape and finite."""
        U = np.asarray(pressures, dtype=np.float64)
        if U.ndim != 2 or U.shape[0] != self.n_chambers or U.shape[1] < n_steps:
            raise DimensionError(f'pressures must be ({self.n_chambers}, >= {n_steps}); got '
                                 f'{U.shape}. Arrays are (n_channels, n_samples).')
        U = U[:, :n_steps]
        if not all_finite(U):
            raise DimensionError('pressures contain NaN or Inf.')
        return U

    def _info(self, solver: str, n_steps: int, dt: float, jacobian: str, wall: float,
              t_factor: float, cg_iterations: int, cg_worst: float) -> dict[str, Any]:
        """The ``info`` of a :class:`SimulationResult`: sizes, scheme, timings, CG figures."""
        return {'solver': solver, 'n_dof': self.n_dof, 'n_nodes': self.n_nodes,
                'n_tets': int(len(self.fem.tets)), 'n_steps': n_steps, 'dt': dt,
                'jacobian': jacobian, 'wall_s': wall, 'factor_s': t_factor,
                'cg_iterations': cg_iterations, 'cg_worst_residual': cg_worst}

    def simulate_lockstep(self, pressures: Sequence[ArrayLike], n_steps: int,
                          dt: float = 1e-3, *,
                          callbacks: Sequence[StepCallback | None] | None = None,
                          linear_solver: str = 'auto') -> list[SimulationResult]:
        """Integrate several episodes side by side, one solve with all of them per step.

        The same scheme as :meth:`simulate` with the rest tangent (the default), so each
        episode's trajectory equals its own :meth:`simulate` to round-off; the rest system is
        solved for all episodes at once (a matrix of right-hand sides), which reads the
        factor once per step instead of once per episode: with CHOLMOD at resolution 4, six
        right-hand sides cost 2.1 single solves (``docs/simulator_speed.md``).

        Parameters
        ----------
        pressures : list of ndarray, shape (6, >= n_steps)
            One pressure sequence (Pa) per episode.
        n_steps, dt : int, float
            Samples per episode and time step (s).
        callbacks : list of callable or None, optional
            One :data:`StepCallback` per episode (e.g. its bag writer).
        linear_solver : {'auto', 'cholmod', 'banded'}

        Returns
        -------
        list of SimulationResult
            Without stored states; ``info['lockstep']`` is the number of episodes.
        """
        n_steps = int(n_steps)
        if n_steps < 1 or not dt > 0:
            raise ConfigError(f'need n_steps >= 1 and dt > 0; got {n_steps}, {dt}.')
        Us = [self._pressures(P, n_steps) for P in pressures]
        k = len(Us)
        cbs = list(callbacks) if callbacks is not None else [None] * k
        if len(cbs) != k:
            raise DimensionError(f'{k} pressure sequences but {len(cbs)} callbacks.')
        t0 = time.perf_counter()
        lu, _K0f, m = self._rest_factor(dt, linear_solver)
        t_factor = time.perf_counter() - t0
        free, h, W = self.free, dt, self.centerline_map
        follower = self.config.follower
        xs = [self.mesh.nodes.copy() for _ in range(k)]
        V: Array = np.zeros((int(free.sum()), k))
        t = np.arange(n_steps, dtype=np.float64) * dt
        centerlines = [np.empty((W.shape[0], 3, n_steps)) for _ in range(k)]
        BUs = None if follower else [(self.B @ U)[free] for U in Us]
        rhs = np.empty_like(V)
        for j in range(n_steps):
            for e in range(k):
                x = xs[e]
                centerlines[e][:, :, j] = W @ x
                cb = cbs[e]
                if cb is not None:
                    cb(j, float(t[j]), Us[e][:, j], centerlines[e][:, :, j], x)
                f = self.fem.elastic_force(x).ravel()[free]
                fp = (self.pressure_force(x, Us[e][:, j]).ravel()[free] if BUs is None
                      else BUs[e][:, j])
                rhs[:, e] = m * V[:, e] + h * (f + fp)
            V = np.asarray(lu.solve(rhs)).reshape(V.shape)
            if not all_finite(V):
                raise SolverError(f'the simulation diverged at step {j} (t = {t[j]:.4f} s); '
                                  'lower the pressures or the time step.')
            for e in range(k):
                v = np.zeros(self.n_dof)
                v[free] = V[:, e]
                xs[e] = xs[e] + h * v.reshape(-1, 3)
        info = self._info(lu.kind, n_steps, dt, 'rest', time.perf_counter() - t0, t_factor,
                          0, 0.0)
        info['lockstep'] = k
        return [SimulationResult(t=t, pressures=U, centerline=c, info=dict(info))
                for U, c in zip(Us, centerlines)]


class EelStepper:
    """One implicit-Euler step at a time of an :class:`EelModel` (see its module docstring).

    Attributes
    ----------
    x : ndarray, shape (n_nodes, 3)
        Nodal positions at the current sample (replaced, never written in place, by
        :meth:`step`).
    v : ndarray, shape (n_dof,)
        Nodal velocities.
    j : int
        Steps taken; the current sample time is ``j * dt``.
    """

    def __init__(self, model: EelModel, dt: float, *, jacobian: str = 'rest',
                 linear: bool = False, cg_rtol: float = 1e-8, cg_maxiter: int = 50,
                 linear_solver: str = 'auto') -> None:
        self.model = model
        self.dt = dt
        self.jacobian = jacobian
        self.linear = linear
        self.cg_rtol, self.cg_maxiter = cg_rtol, cg_maxiter
        self.factor, self._K0f, self._m = model._rest_factor(dt, linear_solver)
        self.follower = model.config.follower and not linear
        self.x: Array = model.mesh.nodes.copy()
        self.v = np.zeros(model.n_dof)
        self.j = 0
        self.cg_iterations = 0
        self.cg_worst_residual = 0.0

    @property
    def t(self) -> float:
        """Time of the current sample (s)."""
        return self.j * self.dt

    def centerline(self) -> Array:
        """Centerline points at the current sample, shape (N, 3)."""
        return np.asarray(self.model.centerline_map @ self.x)

    def _apply_A(self, R: list[Array], p_free: Array) -> Array:
        model, h = self.model, self.dt
        cfg = model.config
        full = np.zeros(model.n_dof)
        full[model.free] = p_free
        kw = model.fem.warped_matvec(R, full.reshape(-1, 3)).ravel()[model.free]
        return (self._m * (1 + h * cfg.rayleigh_mass) * p_free
                + h * cfg.rayleigh_stiffness * (self._K0f @ p_free) + h * h * kw)

    def step(self, u: Array, dead_load: Array | None = None) -> None:
        """Advance one step with chamber pressures ``u`` (6,) held over it.

        ``dead_load`` is ``(B u)[free]`` when the loads do not follow the walls (given by
        :meth:`EelModel.simulate`, which forms it for all steps at once).
        """
        model, h = self.model, self.dt
        free = model.free
        x = self.x
        if self.linear:
            f = -(self._K0f @ (x - model.mesh.nodes).ravel()[free])
            R = None
        elif self.jacobian == 'corotated':
            f_all, R3 = model.fem.elastic_force(x, return_rotations=True)
            R = model.fem.rotation_entries(R3)
            f = f_all.ravel()[free]
        else:
            f = model.fem.elastic_force(x).ravel()[free]
            R = None
        if self.follower:
            fp = model.pressure_force(x, u).ravel()[free]
        elif dead_load is not None:
            fp = dead_load
        else:
            fp = (model.B @ u)[free]
        rhs = self._m * self.v[free] + h * (f + fp)
        vf = self.factor.solve(rhs)
        if R is not None:
            vf, it, res = _pcg(functools.partial(self._apply_A, R), self.factor.solve, rhs, vf,
                               self.cg_rtol, self.cg_maxiter)
            self.cg_iterations += it
            self.cg_worst_residual = max(self.cg_worst_residual, res)
        if not all_finite(vf):
            raise SolverError(f'the simulation diverged at step {self.j} (t = {self.t:.4f} s); '
                              'lower the pressures or the time step.')
        self.v[free] = vf
        self.x = x + h * self.v.reshape(-1, 3)
        self.j += 1

def simulate_episode(model: EelModel, episode: int, *, seed: int = 0, n_steps: int = 2000,
                     dt: float = 1e-3, amplitude: float = DEFAULT_AMPLITUDE,
                     antagonistic: bool = True, bias: float = 0.0,
                     **kwargs: Any) -> SimulationResult:
    """Simulate episode ``Ep <episode>`` (random pressures from ``(seed, episode)``).

    Extra keyword arguments go to :meth:`EelModel.simulate` (``callback``,
    ``store_states``, ``jacobian``, ...).
    """
    U = random_pressures(n_steps, dt, seed=seed, episode=episode, amplitude=amplitude,
                         antagonistic=antagonistic, bias=bias, n_chambers=model.n_chambers)
    result = model.simulate(U, n_steps, dt, **kwargs)
    result.info.update({'episode': int(episode), 'seed': int(seed), 'amplitude_pa': amplitude,
                        'antagonistic': bool(antagonistic), 'bias_pa': bias})
    return result


