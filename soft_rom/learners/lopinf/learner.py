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
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.basis import BasisBuilder
from soft_rom.data import Episode
from soft_rom.ddt import as_estimator, DerivativeEstimator
from soft_rom.envelope import training_envelope
from soft_rom.errors import ConfigError, NotFittedError
from soft_rom.learners.lopinf import margins
from soft_rom.learners.lopinf.operators import (
    check_settings,
    FitSettings,
    scaled_derivatives,
    solve_operators,
)
from soft_rom.learners.lopinf.solvers import DEFAULT_EPS, FastSPDSolver, OperatorSolver
from soft_rom.models import CubicSecondOrderModel, SecondOrderModel
from soft_rom.reduce import InMemoryPOD, ReducedData, training_data

__all__ = ['LOpInf']

Array = NDArray[np.float64]


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
        Default :class:`~soft_rom.learners.lopinf.solvers.FastSPDSolver`; e.g.
        ``CvxpySolver('CLARABEL')`` for the reference.
    basis : BasisBuilder, optional
        A basis builder *object* (default ``POD(r, energy)``); it is copied before fitting.
    eps : float
        ``K`` and ``C`` have eigenvalues ``≥ eps`` (default
        :data:`~soft_rom.learners.lopinf.solvers.DEFAULT_EPS`).
    scale : bool
        Scale states and inputs by their RMS before solving (unit invariance; keep True).
    forces : {'linear', 'cubic'}
        ``'cubic'``: restoring force the gradient of a quartic potential, model
        :class:`~soft_rom.models.cubic.CubicSecondOrderModel` (see
        :mod:`soft_rom.learners.lopinf.cubic`; ``solver`` is then its linear block's solver).
    cubic_options : dict, optional
        ``reg``, ``eps4`` of :func:`~soft_rom.learners.lopinf.cubic.fit_cubic`.
    mass : {'identity', 'learned'}
        ``'learned'``: learn an SPD mass ``M`` too (:mod:`soft_rom.learners.lopinf.mass`;
        exact in any coordinates of a mechanical system, e.g. measured outputs) and fit the
        SPD ``K, C`` in ``z = Lᵀ q`` (``M = L Lᵀ``): the model has identity mass in ``z``,
        and ``mass_factor_`` is ``Lᵀ``. Linear forces only.
    min_damping_ratio : float
        Every mode of the ROM has at least this damping ratio (default
        :data:`~soft_rom.learners.lopinf.margins.DEFAULT_MIN_DAMPING_RATIO`; 0: only the
        absolute margin ``eps``, the paper's formulation). See
        :mod:`soft_rom.learners.lopinf.margins`.
    damping_frequency : float, optional
        ``ω_*`` (rad/s) where the damping bound is tight; default from the data.
    regularization : float or 'auto', optional
        Dimensionless Tikhonov weight ``γ``; ``'auto'``: selected on held-out episode tails
        from ``reg_grid`` (:func:`~soft_rom.learners.lopinf.margins.select_regularization`);
        ``None`` (default): none.
    reg_grid : sequence of float
        Candidates for ``regularization='auto'``.
    refine : {'none', 'output-error'}
        ``'output-error'``: start from the operators above and minimize the simulation error
        of the training episodes over ``K, C, B`` (and each episode's initial state), the
        constraints kept (:mod:`soft_rom.learners.lopinf.refine`): unbiased for noise on
        measured coordinates, where the equation error is not. Linear forces only.

    Attributes
    ----------
    model_ : SecondOrderModel
        The learned ROM (continuous; ``dt`` of the data; zero initial deviation).
    K_, C_ : ndarray, shape (r, r)
    B_ : ndarray, shape (r, m)
    E_ : ndarray, shape (p, r)
    basis_ : ndarray, shape (n, r) or None
        The POD modes (``None`` when the reduced data do not hold them, e.g. streamed).
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

    #: What the learner needs from a reducer (:mod:`soft_rom.reduce`): POD coordinates.
    reduction: ClassVar[str] = 'pod'
    #: The method name of its models and of ``soft-rom fit --method``.
    method: ClassVar[str] = 'lopinf'

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

    def coordinates_needed(self, r_max: int | None, n_inputs: int) -> int | None:
        """POD coordinates a reducer must keep for models up to ``r_max`` (``None``: by energy)."""
        return r_max

    def _settings(self) -> FitSettings:
        return FitSettings(eps=self.eps, forces=self.forces, mass=self.mass, refine=self.refine,
                           cubic_options=self.cubic_options,
                           min_damping_ratio=self.min_damping_ratio,
                           damping_frequency=self.damping_frequency,
                           regularization=self.regularization, reg_grid=self.reg_grid)

    # ---------------------------------------------------------------------------------
    def fit(self, data: ReducedData | Episode | Sequence[Episode],
            q_ref: ArrayLike | None = None, y_ref: ArrayLike | None = None, *,
            input_names: Sequence[str] | None = None,
            output_names: Sequence[str] | None = None,
            input_units: Sequence[str] | None = None,
            output_units: Sequence[str] | None = None,
            metadata: dict[str, Any] | None = None) -> LOpInf:
        """Learn the ROM from reduced data, or from episodes with full states.

        Parameters
        ----------
        data : ReducedData, Episode or sequence of Episode
            POD coordinates (:class:`~soft_rom.reduce.data.ReducedData`, ``basis='pod'``;
            the leading ``r`` are used, default all), or episodes with ``Q (n, k_i)`` (may
            be lazy), ``U (m, k_i)``, ``Y (p, k_i)``, uniformly sampled with the same
            ``dt``, reduced here by :class:`~soft_rom.reduce.memory.InMemoryPOD` (with
            ``basis`` as builder). Derivatives never straddle two episodes.
        q_ref : ndarray, shape (n,), optional
            Episodes only: reference configuration; default the first snapshot.
        y_ref : ndarray, shape (p,), optional
            Episodes only: output reference; default the first output of the first episode.
        input_names, output_names, input_units, output_units : sequence of str, optional
            Episodes only; default the first episode's metadata entries of those names.
        metadata : dict, optional
            Extra JSON metadata merged into the model's.

        Returns
        -------
        self
        """
        t0 = time.perf_counter()
        if not isinstance(data, ReducedData):
            if isinstance(data, Episode):
                data = [data]
            td = training_data(data, q_ref, y_ref, names=dict(
                input_names=input_names, output_names=output_names, input_units=input_units,
                output_units=output_units))
            check_settings(self._settings())
            data = InMemoryPOD(self.energy, builder=self.basis).reduce(
                td, basis='pod', r=self.r, what='LOpInf')
        if data.basis != 'pod':
            raise ConfigError(f'LOpInf fits on POD coordinates; these reduced data have basis '
                              f'{data.basis!r}.')
        t_basis = time.perf_counter() - t0
        r = int(self.r) if self.r is not None else data.n_coordinates
        self._data = data
        self._metadata = dict(metadata or {})
        self._fit(data, r, data.energy_captured(r))
        if data.singular_values is not None:
            s = data.singular_values
            self.diagnostics_['singular_values'] = [float(x)
                                                    for x in s[:max(r, min(s.size, 100))]]
            self.diagnostics_['n_full'] = data.n_states
            self.diagnostics_['basis_seconds'] = t_basis
            self._rebuild_model()
        self.basis_ = None if data.modes is None else data.modes[:, :r]
        self.q_ref_ = data.q_ref
        return self

    def _fit(self, data: ReducedData, r: int, energy_captured: float | None) -> None:
        """The operators of dimension ``r`` from the leading ``r`` coordinates of ``data``."""
        t0 = time.perf_counter()
        Qhat, U, Y = data.leading(r), list(data.U), list(data.Y)
        dt, y_ref = data.dt, data.y_ref
        estimator = as_estimator(self.ddt)
        solver = FastSPDSolver() if self.solver is None else self.solver
        if not isinstance(solver, OperatorSolver):
            raise ConfigError(f'solver must have a solve(Q, Qd, Qdd, U, eps=) method; got '
                              f'{type(solver).__name__}.')
        check_settings(self._settings())
        sd = scaled_derivatives(Qhat, U, dt, estimator, self.scale, data.names)
        ops = solve_operators(sd, Qhat, U, dt, solver, self._settings())
        self.nonlinear_ = ops.nonlinear
        self.mass_factor_ = ops.mass_factor
        K, C, s_q, s_u = ops.K, ops.C, sd.s_q, sd.s_u
        B = ops.Bs * s_q / s_u[None, :]
        rel_residual = ops.residual / max(float(np.linalg.norm(sd.Qdd)), 1e-300)

        # Output operator: min ||(Y - y_ref) - E Qhat||_F over all samples.
        dY = np.concatenate(Y, axis=1) - y_ref[:, None]
        Et, *_ = np.linalg.lstsq((sd.all_q / s_q).T, dY.T, rcond=None)
        E = Et.T / s_q
        out_res = float(np.linalg.norm(dY - E @ sd.all_q)) / max(float(np.linalg.norm(dY)),
                                                                 1e-300)
        self.K_, self.C_, self.B_, self.E_ = K, C, B, E
        self.y_ref_ = y_ref
        self.dt_ = dt
        self.state_scale_ = s_q
        self.input_scale_ = s_u
        self.solver_info_ = ops.info
        lam_k, lam_c = np.linalg.eigvalsh(K), np.linalg.eigvalsh(C)
        self.diagnostics_ = {
            'r': int(r),
            'training_residual': ops.residual * s_q,
            'training_residual_relative': rel_residual,
            'output_residual_relative': out_res,
            'energy_captured': None if energy_captured is None else float(energy_captured),
            'eigenvalues_K': [float(x) for x in lam_k],
            'eigenvalues_C': [float(x) for x in lam_c],
            'eps': float(self.eps),
            'margin': ops.info.get('margin'),
            'regularization': ops.reg,
            'refinement': ops.refined if ops.refined is not None else {'criterion': 'none'},
            'least_damped_mode': margins.least_damped_mode(K, C),
            'ddt': repr(estimator),
            'mass': self.mass,
            'mass_info': ops.mass_info,
            'solver': repr(solver),
            'solver_info': self.solver_info_,
            'state_scale': s_q,
            'input_scale': [float(x) for x in s_u],
            'n_samples_used': int(sd.Qs.shape[1]),
            'fit_seconds': time.perf_counter() - t0,
        }
        self._provenance = {'method': 'lopinf', 'episodes': list(data.names),
                            'time_ranges': data.time_ranges,
                            'n_samples': [int(q.shape[1]) for q in Qhat]}
        self._extra_meta = {**data.metadata, **self._metadata}
        self._extra_meta.setdefault('envelope', training_envelope(zip(U, Y), y_ref, dt))
        self._extra_meta.setdefault('mass', self.mass)
        self._extra_meta.setdefault('refine', self.refine)
        self._names = data.model_names()
        self._rebuild_model()

    def model_for(self, r: int, *, energy_captured: float | None = None) -> Any:
        """The ROM of a smaller reduced dimension from the same fit (like DMDc and ERA/OKID).

        The reduced coordinates of :meth:`fit` are reused: the leading ``r`` coordinates are
        taken and only the operators are solved again, so a sweep over r costs one POD.
        ``model_for(self.model_.r)`` is the fitted model itself.

        Parameters
        ----------
        r : int
            ``1 <= r <=`` the fitted dimension.
        energy_captured : float, optional
            POD energy fraction of the first r modes (diagnostics); default from the
            reduced data.

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
        other = copy.copy(self)
        other.r = int(r)
        captured = self._data.energy_captured(int(r)) if energy_captured is None \
            else energy_captured
        other._fit(self._data, int(r), captured)
        if 'singular_values' in self.diagnostics_:
            other.diagnostics_.update({k: self.diagnostics_[k]
                                       for k in ('n_full', 'singular_values')})
            other._rebuild_model()
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
            raise NotFittedError('this LOpInf is not fitted yet: call fit(data) first.')

    def _rebuild_model(self) -> None:
        diag = dict(self.diagnostics_)
        meta = {'provenance': self._provenance, 'diagnostics': diag}
        meta.update(self._extra_meta)
        model = self._make_model(meta, self._names)
        diag['stability_margin'] = model.stability_margin()
        ev = model.eigenvalues()
        diag['eigenvalues'] = [[float(z.real), float(z.imag)] for z in ev]
        meta['diagnostics'] = diag
        self.diagnostics_ = diag
        self.model_ = self._make_model(meta, self._names)

    def _make_model(self, meta: dict[str, Any], kw: dict[str, Any]) -> Any:
        nl = getattr(self, 'nonlinear_', None)
        if nl is not None:
            return CubicSecondOrderModel(self.K_, self.C_, nl['G'], nl['H'], self.B_, self.E_,
                                         dt=self.dt_, y_ref=self.y_ref_, metadata=meta, **kw)
        return SecondOrderModel(self.K_, self.C_, self.B_, self.E_, dt=self.dt_,
                                y_ref=self.y_ref_, metadata=meta, **kw)
