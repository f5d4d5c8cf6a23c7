"""Lagrangian Operator Inference (LOpInf): a second-order ROM with SPD stiffness and damping.

.. math::

    \\ddot{\\hat q} + C \\dot{\\hat q} + K \\hat q = B u, \\qquad y = E \\hat q + y_{ref},
    \\qquad \\hat q = V_r^T (q - q_{ref}),

learned from snapshots by (i) a POD basis :math:`V_r`, (ii) finite-difference time
derivatives of the reduced coordinates, per episode, (iii) the constrained least-squares
problem

.. math::

    \\min_{K, C, B} \\|\\ddot{\\hat Q} + C\\dot{\\hat Q} + K\\hat Q - B U\\|_F \\quad
    \\text{s.t.}\\ K = K^T \\succ 0,\\ C = C^T \\succ 0,

and (iv) the output operator :math:`E` by least squares. Reference: Sharma et al.,
*Data-driven Model Reduction for Soft Robots via Lagrangian Operator Inference*, sec. 2.2.

Unit invariance: before solving, the reduced coordinates are divided by one scalar (their
RMS) and every input channel by its RMS. A scalar change of the units of ``q`` leaves ``K``
and ``C`` unchanged (only ``B`` and ``E`` scale), and so does a per-channel change of the
units of ``u``; the operators are mapped back exactly, so predictions do not depend on the
units (Pa vs kPa, m vs mm) and ``eps`` keeps its meaning (1/s² for K, 1/s for C).
"""

from __future__ import annotations

from collections.abc import Sequence
import copy
import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.basis import BasisBuilder, POD, project
from soft_rom.data import as_signal, check_finite, Episode
from soft_rom.ddt import as_estimator, DerivativeEstimator, FiniteDifference
from soft_rom.envelope import training_envelope
from soft_rom.errors import ConfigError, DimensionError, NotFittedError
from soft_rom.learners import lopinf_margins as margins
from soft_rom.learners.lopinf_solvers import DEFAULT_EPS, FastSPDSolver, OperatorSolver
from soft_rom.models import SecondOrderModel

__all__ = ['LOpInf']

Array = NDArray[np.float64]

_NAME_KEYS = ('input_names', 'output_names', 'input_units', 'output_units')


def _rms(X: Array, axis: int | None = None) -> Array:
    s = np.atleast_1d(np.sqrt(np.mean(X ** 2, axis=axis))) if X.size else np.ones(1)
    return np.where(s > 0, s, 1.0)


class LOpInf:
    """Learner of second-order ROMs with symmetric positive definite ``K`` and ``C``.

    Parameters
    ----------
    r : int, optional
        Reduced dimension; if ``None``, chosen by ``energy`` (ignored when ``basis`` is given).
    energy : float
        POD energy fraction used when ``r`` is ``None`` (default 0.95).
    ddt : int or DerivativeEstimator
        Derivative estimator, or an order (2, 4, 6, 8) for :class:`~soft_rom.ddt.
        FiniteDifference` (default 8). Edges of every episode are trimmed.
    solver : OperatorSolver, optional
        Default :class:`~soft_rom.learners.lopinf_solvers.FastSPDSolver`; e.g.
        ``CvxpySolver('CLARABEL')`` for the reference.
    basis : BasisBuilder, optional
        A basis builder *object* (default ``POD(r, energy)``); it is copied before fitting.
    eps : float
        ``K`` and ``C`` have eigenvalues ``≥ eps`` (default
        :data:`~soft_rom.learners.lopinf_solvers.DEFAULT_EPS`).
    scale : bool
        Scale states and inputs by their RMS before solving (unit invariance; keep True).
    forces : {'linear', 'cubic'}
        ``'cubic'``: restoring force the gradient of a quartic potential, model
        :class:`~soft_rom.models_cubic.CubicSecondOrderModel` (see
        :mod:`soft_rom.learners.lopinf_cubic`; ``solver`` is then its linear block's solver).
    cubic_options : dict, optional
        ``reg``, ``eps4`` of :func:`~soft_rom.learners.lopinf_cubic.fit_cubic`.
    mass : {'identity', 'learned'}
        ``'learned'``: learn an SPD mass ``M`` too (:mod:`soft_rom.learners.lopinf_mass`;
        exact in any coordinates of a mechanical system, e.g. measured outputs) and fit the
        SPD ``K, C`` in ``z = Lᵀ q`` (``M = L Lᵀ``): the model has identity mass in ``z``,
        and ``mass_factor_`` is ``Lᵀ``. Linear forces only.
    min_damping_ratio : float
        Every mode of the ROM has at least this damping ratio (default
        :data:`~soft_rom.learners.lopinf_margins.DEFAULT_MIN_DAMPING_RATIO`; 0: only the
        absolute margin ``eps``, the paper's formulation). See
        :mod:`soft_rom.learners.lopinf_margins`.
    damping_frequency : float, optional
        ``ω_*`` (rad/s) where the damping bound is tight; default from the data.
    regularization : float or 'auto', optional
        Dimensionless Tikhonov weight ``γ``; ``'auto'``: selected on held-out episode tails
        from ``reg_grid`` (:func:`~soft_rom.learners.lopinf_margins.select_regularization`);
        ``None`` (default): none.
    reg_grid : sequence of float
        Candidates for ``regularization='auto'``.
    refine : {'none', 'output-error'}
        ``'output-error'``: start from the operators above and minimize the simulation error
        of the training episodes over ``K, C, B`` (and each episode's initial state), the
        constraints kept (:mod:`soft_rom.learners.lopinf_refine`): unbiased for noise on
        measured coordinates, where the equation error is not. Linear forces only.

    Attributes
    ----------
    model_ : SecondOrderModel
        The learned ROM (continuous; ``dt`` of the data; zero initial deviation).
    K_, C_ : ndarray, shape (r, r)
    B_ : ndarray, shape (r, m)
    E_ : ndarray, shape (p, r)
    basis_ : BasisBuilder or None
        The fitted basis builder (``None`` after :meth:`fit_reduced`).
    q_ref_ : ndarray, shape (n,) or None
    y_ref_ : ndarray, shape (p,)
    solver_info_ : dict
        The solver's report (objective, method, steps, ...).
    diagnostics_ : dict
        What is stored in ``model_.metadata['diagnostics']``.

    Examples
    --------
    >>> rom = LOpInf(r=12).fit(episodes).model_                  # doctest: +SKIP
    >>> Y = rom.simulate(test.U)                                 # doctest: +SKIP
    """

    def __init__(self, r: int | None = None, energy: float = 0.95, *,
                 ddt: int | DerivativeEstimator = 8, solver: OperatorSolver | None = None,
                 basis: BasisBuilder | None = None, eps: float = DEFAULT_EPS,
                 scale: bool = True, forces: str = 'linear',
                 cubic_options: dict[str, Any] | None = None, mass: str = 'identity',
                 min_damping_ratio: float = margins.DEFAULT_MIN_DAMPING_RATIO,
                 damping_frequency: float | None = None,
                 regularization: float | str | None = None,
                 reg_grid: Sequence[float] = margins.DEFAULT_REG_GRID,
                 refine: str = 'none') -> None:
        self.r = r
        self.energy = energy
        self.ddt = ddt
        self.solver = solver
        self.basis = basis
        self.eps = eps
        self.scale = scale
        self.forces = forces
        self.cubic_options = cubic_options
        self.mass = mass
        self.min_damping_ratio = min_damping_ratio
        self.damping_frequency = damping_frequency
        self.regularization = regularization
        self.reg_grid = reg_grid
        self.refine = refine

    def __repr__(self) -> str:
        return (f'LOpInf(r={self.r!r}, energy={self.energy!r}, ddt={self.ddt!r}, '
                f'solver={self.solver!r}, eps={self.eps!r}, '
                f'min_damping_ratio={self.min_damping_ratio!r}, '
                f'regularization={self.regularization!r}, refine={self.refine!r})')

    # ---------------------------------------------------------------------------------
    def fit(self, episodes: Episode | Sequence[Episode], q_ref: ArrayLike | None = None,
            y_ref: ArrayLike | None = None, *, input_names: Sequence[str] | None = None,
            output_names: Sequence[str] | None = None,
            input_units: Sequence[str] | None = None,
            output_units: Sequence[str] | None = None,
            metadata: dict[str, Any] | None = None) -> LOpInf:
        """Learn the ROM from episodes with full states.

        Parameters
        ----------
        episodes : Episode or sequence of Episode
            Each with ``Q (n, k_i)`` (may be lazy), ``U (m, k_i)``, ``Y (p, k_i)``, uniformly
            sampled with the same ``dt``. Derivatives never straddle two episodes.
        q_ref : ndarray, shape (n,), optional
            Reference configuration; default the first snapshot of the first episode.
        y_ref : ndarray, shape (p,), optional
            Output reference; default the first output of the first episode.
        input_names, output_names, input_units, output_units : sequence of str, optional
            Default: the first episode's metadata entries of those names, if any.
        metadata : dict, optional
            Extra JSON metadata merged into the model's.

        Returns
        -------
        self
        """
        eps_list = [episodes] if isinstance(episodes, Episode) else list(episodes)
        if not eps_list:
            raise DimensionError('LOpInf.fit needs at least one episode.')
        for ep in eps_list:
            if ep.Q is None:
                raise DimensionError(f'episode {ep.name!r} has no states Q; LOpInf needs the '
                                     'full states (or call fit_reduced with POD coordinates).')
        n = int(eps_list[0].Q.shape[0])
        for ep in eps_list:
            if int(ep.Q.shape[0]) != n:
                raise DimensionError(f'episode {ep.name!r} has {ep.Q.shape[0]} states; the '
                                     f'first episode has {n}.')
        if q_ref is None:
            q_ref = np.asarray(eps_list[0].Q[:, 0:1], dtype=np.float64)[:, 0]
        q_ref_a = as_signal('q_ref', np.reshape(np.asarray(q_ref, dtype=np.float64), (-1, 1)),
                            rows=n)[:, 0].copy()
        check_finite('q_ref', q_ref_a)
        builder = POD(r=self.r, energy=self.energy) if self.basis is None else copy.deepcopy(
            self.basis)
        if not callable(getattr(builder, 'fit', None)):
            raise ConfigError(f'basis must be a BasisBuilder object (fit, basis_, '
                              f'singular_values_); got {type(builder).__name__}.')
        dt = self._common_dt(eps_list)          # validate before the expensive POD
        t0 = time.perf_counter()
        builder.fit([ep.Q for ep in eps_list], q_ref_a)
        if not isinstance(builder, BasisBuilder):
            raise ConfigError(f'the basis builder {type(builder).__name__} has no basis_ or '
                              'singular_values_ after fit().')
        V = np.asarray(builder.basis_, dtype=np.float64)
        if V.ndim != 2 or V.shape[0] != n:
            raise DimensionError(f'the basis builder returned basis_ of shape {V.shape}; '
                                 f'expected ({n}, r).')
        Qhat = [project(ep.Q, V, q_ref_a) for ep in eps_list]
        t_basis = time.perf_counter() - t0
        s = np.asarray(builder.singular_values_, dtype=np.float64)
        r = V.shape[1]
        energy = getattr(builder, 'energy_', None)
        captured = (float(np.asarray(energy)[r - 1]) if energy is not None
                    else float(np.sum(s[:r] ** 2) / np.sum(s ** 2)))
        meta = self._names_from(eps_list[0], dict(input_names=input_names,
                                                  output_names=output_names,
                                                  input_units=input_units,
                                                  output_units=output_units))
        self.fit_reduced(Qhat, [ep.U for ep in eps_list], [ep.Y for ep in eps_list],
                         dt, y_ref,
                         names=[ep.name for ep in eps_list], energy_captured=captured,
                         time_ranges=[[float(ep.t[0]), float(ep.t[-1])] for ep in eps_list],
                         metadata=metadata, **meta)
        self.basis_ = builder  # type: BasisBuilder | None
        self.q_ref_ = q_ref_a
        diag = self.diagnostics_
        diag['n_full'] = n
        diag['basis_seconds'] = t_basis
        diag['singular_values'] = [float(x) for x in s[:max(r, min(s.size, 100))]]
        self._rebuild_model()
        return self

    def fit_reduced(self, Qhat: Sequence[Array], U: Sequence[Array],
                    Y: Sequence[Array], dt: float, y_ref: ArrayLike | None = None, *,
                    input_names: Sequence[str] | None = None,
                    output_names: Sequence[str] | None = None,
                    input_units: Sequence[str] | None = None,
                    output_units: Sequence[str] | None = None,
                    names: Sequence[str] | None = None,
                    energy_captured: float | None = None,
                    time_ranges: Sequence[Sequence[float]] | None = None,
                    metadata: dict[str, Any] | None = None) -> LOpInf:
        """Learn the operators from already reduced coordinates (one array per episode).

        This is what out-of-core code (:mod:`soft_rom.scale`) calls after a streaming POD.

        Parameters
        ----------
        Qhat : sequence of ndarray, each shape (r, k_i)
            Reduced coordinates ``Vᵀ (Q_i - q_ref)`` of each episode.
        U : sequence of ndarray, each shape (m, k_i)
        Y : sequence of ndarray, each shape (p, k_i)
            Absolute outputs.
        dt : float
            Sample time (s), the same for every episode.
        y_ref : ndarray, shape (p,), optional
            Default the first output of the first episode.
        input_names, output_names, input_units, output_units : sequence of str, optional
        names : sequence of str, optional
            Episode names (provenance).
        energy_captured : float, optional
            POD energy fraction of the basis (diagnostics).
        time_ranges : sequence of [t_start, t_end], optional
            Provenance.
        metadata : dict, optional
            Extra JSON metadata merged into the model's.

        Returns
        -------
        self
        """
        self._reduced: dict[str, Any] = dict(
            Qhat=list(Qhat), U=list(U), Y=list(Y), dt=dt, y_ref=y_ref, input_names=input_names,
            output_names=output_names, input_units=input_units, output_units=output_units,
            names=names, time_ranges=time_ranges, metadata=metadata)
        t0 = time.perf_counter()
        Qhat = [as_signal('Qhat', q) for q in Qhat]
        U = [as_signal('U', u) for u in U]
        Y = [as_signal('Y', y) for y in Y]
        if not Qhat or not len(Qhat) == len(U) == len(Y):
            raise DimensionError(f'Qhat, U and Y need one array per episode; got {len(Qhat)}, '
                                 f'{len(U)} and {len(Y)}.')
        r, m, p = Qhat[0].shape[0], U[0].shape[0], Y[0].shape[0]
        for i, (q, u, y) in enumerate(zip(Qhat, U, Y)):
            if q.shape[0] != r or u.shape[0] != m or y.shape[0] != p:
                raise DimensionError(f'episode {i} has (r, m, p) = ({q.shape[0]}, {u.shape[0]}, '
                                     f'{y.shape[0]}); the first has ({r}, {m}, {p}).')
            if not q.shape[1] == u.shape[1] == y.shape[1]:
                raise DimensionError(f'episode {i}: Qhat, U and Y must have the same number of '
                                     f'samples; got {q.shape[1]}, {u.shape[1]}, {y.shape[1]}.')
            for name, a in (('Qhat', q), ('U', u), ('Y', y)):
                check_finite(f'{name} of episode {i}', a)
        dt = float(dt)
        if not np.isfinite(dt) or dt <= 0:
            raise DimensionError(f'dt must be a positive number of seconds; got {dt!r}.')
        if y_ref is None:
            y_ref = Y[0][:, 0]
        y_ref_a = as_signal('y_ref', np.reshape(np.asarray(y_ref, dtype=np.float64), (-1, 1)),
                            rows=p)[:, 0].copy()
        estimator = as_estimator(self.ddt)
        solver = FastSPDSolver() if self.solver is None else self.solver
        if not isinstance(solver, OperatorSolver):
            raise ConfigError(f'solver must have a solve(Q, Qd, Qdd, U, eps=) method; got '
                              f'{type(solver).__name__}.')

        # Scale (unit invariance): one scalar for the states, one RMS per input channel.
        all_q = np.concatenate(Qhat, axis=1)
        all_u = np.concatenate(U, axis=1)
        if not np.any(all_q):
            raise DimensionError('the reduced states are identically zero: the body never '
                                 'moved away from q_ref, so there is nothing to learn.')
        s_q = float(_rms(all_q)[0]) if self.scale else 1.0
        s_u = _rms(all_u, axis=1) if self.scale else np.ones(m)
        need = 2 * _half_width(estimator)
        too_short = [i for i, q in enumerate(Qhat) if q.shape[1] <= need]
        if too_short:
            label = ', '.join(
                f'{names[i]!r}' if names is not None and i < len(names) else str(i)
                for i in too_short)
            counts = ', '.join(str(Qhat[i].shape[1]) for i in too_short)
            raise DimensionError(
                f'episode(s) {label} ({counts} samples) too short for the derivative '
                f'estimator {estimator!r}, which needs more than {need} samples per episode; '
                'drop them or use a shorter estimator (soft-rom fit --ddt fd2, or '
                'savgol:WINDOW with a smaller window).')
        Qs, Qd, Qdd, (Us,) = _episodes(estimator, [q / s_q for q in Qhat], dt,
                                       [[u / s_u[:, None] for u in U]])
        self.nonlinear_: dict[str, Any] | None = None
        self.mass_factor_: Array | None = None
        if self.mass not in ('identity', 'learned') or (self.mass == 'learned'
                                                         and self.forces != 'linear'):
            raise ConfigError(f"mass must be 'identity' or 'learned' (linear forces only); got "
                              f'{self.mass!r} with forces={self.forces!r}.')
        if self.mass == 'learned':
            from soft_rom.learners.lopinf_mass import solve_learned_mass
            msol, Lt = solve_learned_mass(Qs, Qd, Qdd, Us, eps=self.eps, dt=dt, episodes=[
                (np.asarray(q) / s_q, np.asarray(u) / s_u[:, None]) for q, u in zip(Qhat, U)])
            Qs, Qd, Qdd, all_q, self.mass_factor_ = Lt @ Qs, Lt @ Qd, Lt @ Qdd, Lt @ all_q, Lt
        if self.refine not in ('none', 'output-error') or (self.refine != 'none'
                                                            and self.forces != 'linear'):
            raise ConfigError(f"refine must be 'none' or 'output-error' (linear forces only); "
                              f'got {self.refine!r} with forces={self.forces!r}.')
        refined: dict[str, Any] | None = None
        if self.forces == 'cubic':
            from soft_rom.learners.lopinf_cubic import fit_scaled
            sol, self.nonlinear_ = fit_scaled(Qs, Qd, Qdd, Us, s_q, solver, self.eps,
                                              self.cubic_options)
            K, C, Bs = 0.5 * (sol.K + sol.K.T), 0.5 * (sol.C + sol.C.T), sol.B
            sol_info: dict[str, Any] = dict(sol.info)
            reg: dict[str, Any] = {'mode': 'none', 'gamma': 0.0}
            residual = float(sol.info['objective'])
        elif self.forces == 'linear':
            K, C, Bs, sol_info, reg = self._solve(solver, Qs, Qd, Qdd, Us, dt,
                                                  [q.shape[1] - 2 * _half_width(estimator)
                                                   for q in Qhat])
            if self.refine == 'output-error':
                from soft_rom.learners.lopinf_refine import refine_output_error
                K, C, Bs, refined = refine_output_error(
                    K, C, Bs, [(np.asarray(q) / s_q, np.asarray(u) / s_u[:, None])
                               for q, u in zip(Qhat, U)], dt, Lt=self.mass_factor_,
                    free_mass=self.mass_factor_ is not None,
                    margin=sol_info.get('margin'), eps=self.eps)
                Lt_new = refined.pop('mass_factor')
                if self.mass_factor_ is not None:   # the coordinates z = Lt q moved with it
                    T = Lt_new @ np.linalg.inv(self.mass_factor_)
                    Qs, Qd, Qdd, all_q = T @ Qs, T @ Qd, T @ Qdd, T @ all_q
                    self.mass_factor_ = Lt_new
            residual = float(np.linalg.norm(Qdd + C @ Qd + K @ Qs - Bs @ Us))
        else:
            raise ConfigError(f"forces must be 'linear' or 'cubic'; got {self.forces!r}.")
        B = Bs * s_q / s_u[None, :]
        rel_residual = residual / max(float(np.linalg.norm(Qdd)), 1e-300)

        # Output operator: min ||(Y - y_ref) - E Qhat||_F over all samples.
        dY = np.concatenate(Y, axis=1) - y_ref_a[:, None]
        Et, *_ = np.linalg.lstsq((all_q / s_q).T, dY.T, rcond=None)
        E = Et.T / s_q
        out_res = float(np.linalg.norm(dY - E @ all_q)) / max(float(np.linalg.norm(dY)), 1e-300)

        self.K_, self.C_, self.B_, self.E_ = K, C, B, E
        self.y_ref_ = y_ref_a
        self.dt_ = dt
        self.basis_ = None
        self.q_ref_ = None
        self.state_scale_ = s_q
        self.input_scale_ = s_u
        self.solver_info_ = sol_info
        lam_k, lam_c = np.linalg.eigvalsh(K), np.linalg.eigvalsh(C)
        self.diagnostics_ = {
            'r': int(r),
            'training_residual': residual * s_q,
            'training_residual_relative': rel_residual,
            'output_residual_relative': out_res,
            'energy_captured': None if energy_captured is None else float(energy_captured),
            'eigenvalues_K': [float(x) for x in lam_k],
            'eigenvalues_C': [float(x) for x in lam_c],
            'eps': float(self.eps),
            'margin': sol_info.get('margin'),
            'regularization': reg,
            'refinement': refined if refined is not None else {'criterion': 'none'},
            'least_damped_mode': margins.least_damped_mode(K, C),
            'ddt': repr(estimator),
            'mass': self.mass,
            'mass_info': None if self.mass_factor_ is None else msol.info['mass'],
            'solver': repr(solver),
            'solver_info': self.solver_info_,
            'state_scale': s_q,
            'input_scale': [float(x) for x in s_u],
            'n_samples_used': int(Qs.shape[1]),
            'fit_seconds': time.perf_counter() - t0,
        }
        self._provenance = {
            'method': 'lopinf',
            'episodes': [str(x) for x in (names if names is not None else
                                          [f'episode{i}' for i in range(len(Qhat))])],
            'time_ranges': None if time_ranges is None else [[float(a), float(b)]
                                                             for a, b in time_ranges],
            'n_samples': [int(q.shape[1]) for q in Qhat],
        }
        self._names = dict(input_names=input_names, output_names=output_names,
                           input_units=input_units, output_units=output_units)
        self._extra_meta = dict(metadata or {})
        self._extra_meta.setdefault('envelope', training_envelope(zip(U, Y), y_ref))
        self._extra_meta.setdefault('mass', self.mass)
        self._extra_meta.setdefault('refine', self.refine)
        self._rebuild_model()
        return self

    def _solve(self, solver: OperatorSolver, Qs: Array, Qd: Array, Qdd: Array, Us: Array,
               dt: float, lengths: Sequence[int]
               ) -> tuple[Array, Array, Array, dict[str, Any], dict[str, Any]]:
        """Operators with the damping margin and the (selected) Tikhonov weight."""
        kw: dict[str, Any] = dict(eps=self.eps, min_damping_ratio=float(self.min_damping_ratio),
                                  frequency=self.damping_frequency)
        reg: dict[str, Any] = {'mode': 'none', 'gamma': 0.0}
        gamma = 0.0
        if isinstance(self.regularization, str):
            if self.regularization != 'auto':
                raise ConfigError(f"regularization must be a number >= 0, 'auto' or None; got "
                                  f'{self.regularization!r}.')
            cuts = np.cumsum(lengths)[:-1]
            parts = [np.split(x, cuts, axis=1) for x in (Qs, Qd, Qdd, Us)]

            def fit(q: list[Array], qd: list[Array], qdd: list[Array], u: list[Array],
                    g: float) -> tuple[Array, Array, Array]:
                K_, C_, B_, _ = margins.constrained_solve(
                    solver, np.hstack(q), np.hstack(qd), np.hstack(qdd), np.hstack(u),
                    gamma=g, **kw)
                return K_, C_, B_

            gamma, table = margins.select_regularization(fit, parts[0], parts[1], parts[2],
                                                         parts[3], dt, grid=self.reg_grid)
            reg = {'mode': 'auto', 'gamma': gamma, 'candidates': table}
        elif self.regularization is not None:
            gamma = float(self.regularization)
            reg = {'mode': 'fixed', 'gamma': gamma}
        K, C, B, info = margins.constrained_solve(solver, Qs, Qd, Qdd, Us, gamma=gamma, **kw)
        reg['lambda'] = info.get('regularization', {}).get('lambda')
        return K, C, B, info, reg

    def model_for(self, r: int, *, energy_captured: float | None = None) -> Any:
        """The ROM of a smaller reduced dimension from the same fit (like DMDc and ERA/OKID).

        The basis and the reduced coordinates of :meth:`fit` (or :meth:`fit_reduced`) are
        reused: the leading ``r`` coordinates are taken and only the operators are solved
        again, so a sweep over r costs one POD. ``model_for(self.model_.r)`` is the fitted
        model itself.

        Parameters
        ----------
        r : int
            ``1 <= r <=`` the fitted dimension.
        energy_captured : float, optional
            POD energy fraction of the first r modes (diagnostics); default from the basis
            of :meth:`fit`, if there is one.

        Returns
        -------
        SecondOrderModel (or the cubic model for ``forces='cubic'``)
        """
        self._check()
        r_fit = int(self.model_.r)
        if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or not 1 <= r <= r_fit:
            raise ConfigError(f'model_for needs 1 <= r <= {r_fit} (the fitted dimension); '
                              f'got {r!r}.')
        if int(r) == r_fit:
            return self.model_
        red: dict[str, Any] = dict(self._reduced)
        captured = energy_captured
        builder = self.basis_
        if builder is not None and captured is None:
            energy = getattr(builder, 'energy_', None)
            sv = np.asarray(builder.singular_values_, dtype=np.float64)
            captured = (float(np.asarray(energy)[r - 1]) if energy is not None
                        else float(np.sum(sv[:r] ** 2) / np.sum(sv ** 2)))
        other = copy.copy(self)
        other.r = int(r)
        other.fit_reduced([q[:r] for q in red.pop('Qhat')], red.pop('U'), red.pop('Y'),
                          red.pop('dt'), red.pop('y_ref'), energy_captured=captured, **red)
        if builder is not None:
            other.model_.metadata['diagnostics'].update(
                {k: self.diagnostics_[k] for k in ('n_full', 'singular_values')
                 if k in self.diagnostics_})
        return other.model_

    # ---------------------------------------------------------------------------------
    @property
    def model(self) -> SecondOrderModel:
        """The fitted model (raises :class:`~soft_rom.errors.NotFittedError` before fit)."""
        self._check()
        return self.model_

    def predict(self, U: ArrayLike, x0: ArrayLike | None = None) -> Array:
        """Absolute outputs (p, k) for inputs ``U`` (m, k) from ``x0`` (default at rest)."""
        Y = self.model.simulate(U, x0)
        assert not isinstance(Y, tuple)
        return Y

    def _check(self) -> None:
        if not hasattr(self, 'model_'):
            raise NotFittedError('this LOpInf is not fitted yet: call fit(episodes) or '
                                 'fit_reduced(...) first.')

    def _rebuild_model(self) -> None:
        diag = dict(self.diagnostics_)
        meta = {'provenance': self._provenance, 'diagnostics': diag}
        meta.update(self._extra_meta)
        kw = {k: v for k, v in self._names.items() if v is not None}
        model = self._make_model(meta, kw)
        diag['stability_margin'] = model.stability_margin()
        ev = model.eigenvalues()
        diag['eigenvalues'] = [[float(z.real), float(z.imag)] for z in ev]
        meta['diagnostics'] = diag
        self.diagnostics_ = diag
        self.model_ = self._make_model(meta, kw)

    def _make_model(self, meta: dict[str, Any], kw: dict[str, Any]) -> Any:
        nl = getattr(self, 'nonlinear_', None)
        if nl is not None:
            from soft_rom.models_cubic import CubicSecondOrderModel
            return CubicSecondOrderModel(self.K_, self.C_, nl['G'], nl['H'], self.B_, self.E_,
                                         dt=self.dt_, y_ref=self.y_ref_, metadata=meta, **kw)
        return SecondOrderModel(self.K_, self.C_, self.B_, self.E_, dt=self.dt_,
                                y_ref=self.y_ref_, metadata=meta, **kw)

    @staticmethod
    def _names_from(ep: Episode, given: dict[str, Any]) -> dict[str, Any]:
        out = {}
        for key in _NAME_KEYS:
            val = given.get(key)
            if val is None:
                val = ep.metadata.get(key) if isinstance(ep.metadata, dict) else None
            if val is not None:
                out[key] = list(val)
        return out

    @staticmethod
    def _common_dt(episodes: Sequence[Episode]) -> float:
        dts = []
        for ep in episodes:
            if ep.n_samples < 2 or not ep.is_uniform():
                raise DimensionError(f'episode {ep.name!r} is not uniformly sampled (or has '
                                     'fewer than 2 samples); resample it first.')
            dts.append(ep.dt)
        dt = dts[0]
        if any(abs(d - dt) > 1e-6 * dt for d in dts):
            raise DimensionError(f'episodes have different sample times {dts}; resample first.')
        return float(dt)


def _half_width(estimator: DerivativeEstimator) -> int:
    return int(getattr(estimator, 'half_width', getattr(estimator, 'order', 8) // 2))


def _episodes(estimator: DerivativeEstimator, Qs: Sequence[Array], dt: float,
              others: Sequence[Sequence[Array]]) -> tuple[Array, Array, Array, list[Array]]:
    if isinstance(estimator, FiniteDifference):
        return estimator.episodes(Qs, dt, others)
    parts = [estimator.derivatives(q, dt) for q in Qs]
    stacked = [np.concatenate([pp[j] for pp in parts], axis=1) for j in range(3)]
    trimmed = [np.concatenate([estimator.trim(x) for x in sig], axis=1) for sig in others]
    return stacked[0], stacked[1], stacked[2], trimmed
