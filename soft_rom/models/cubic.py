"""Nonlinear Lagrangian ROM with a quartic potential, and its energy-consistent integrator.

.. math::

    \\ddot q + C \\dot q + \\nabla V(q) = B u, \\qquad y = E q + y_{ref},

    V(q) = \\tfrac12 q^T K q + \\tfrac16 G(q, q, q) + \\tfrac1{24} H(q, q, q, q),

with fully symmetric tensors ``G (r, r, r)`` and ``H (r, r, r, r)``: the restoring force
``∇V = K q + ½ G(q, q, ·) + ⅙ H(q, q, q, ·)`` is the gradient of a scalar potential, the
stiffness is its Hessian ``K + G(q, ·, ·) + ½ H(q, q, ·, ·)``.

Time stepping (:meth:`CubicSecondOrderModel.step`): with ``x = [q; q̇]``, the step of length
``h`` with the input held (zero-order hold) is

.. math::

    x_{n+1} = A_d x_n + B_d u_n + \\Gamma\\, \\bar g(q_n, q_{n+1}), \\qquad
    \\bar g(a, b) = \\int_0^1 \\nabla V_{nl}(a + s (b - a))\\, ds,

where ``A_d, B_d`` are the exact ZOH matrices of the linear part (those of
:class:`~soft_rom.models.SecondOrderModel`), ``Γ = (A_d - I) P^{-1} [I; 0]`` with
``P = diag(K, I)`` is the exact response to a force held over the step, and ``ḡ`` is the
average-vector-field discrete gradient of the nonlinear potential (integrated in closed form,
exact for the cubic ``∇V_nl``). Properties:

* exact for the linear part (``V_nl = 0`` gives the ZOH map of the linear model);
* with ``u = 0`` the discrete energy ``½|q̇|² + V(q)`` never increases: the scheme is the
  discrete-gradient method ``x_{n+1} - x_n = h S̄ ∇̄H`` with ``S̄ = Ã P^{-1}``,
  ``h Ã / 2`` the Cayley inverse of ``A_d``; ``A_d`` is a ``P``-contraction, so the symmetric
  part of ``S̄`` is negative semidefinite;
* second order (symmetric), implicit in ``q_{n+1}``: ``r`` unknowns, solved by Newton's method
  warm-started from the previous step, with step halving as a fallback; its exact derivative
  (:meth:`CubicSecondOrderModel.step_jacobian`) serves the extended Kalman correction.
"""

from __future__ import annotations

from collections.abc import Callable
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import as_signal, check_finite, step_length
from soft_rom.errors import DimensionError, SolverError
from soft_rom.gain import gain_issue
from soft_rom.models.base import _arr, _leading, _state_and_input, DiscreteSystem, LinearROM
from soft_rom.models.files import register_model_class
from soft_rom.models.linear import SecondOrderModel
from soft_rom.models.tensors import is_symmetric, quartic_certified_positive, symmetric_index

__all__ = ['CUBIC_FORMAT_VERSION', 'CubicSecondOrderModel', 'StepCache']

Array = NDArray[np.float64]

#: Format version written in the files of this model (the linear models keep version 1).
CUBIC_FORMAT_VERSION = 2

_GAUSS = (0.5 - math.sqrt(3.0) / 6.0, 0.5 + math.sqrt(3.0) / 6.0)
_S = np.array([_GAUSS])                                          # (1, 2)
_W01 = np.array([[0.5 * (1.0 - _GAUSS[0]), 0.5 * _GAUSS[0]],
                 [0.5 * (1.0 - _GAUSS[1]), 0.5 * _GAUSS[1]]])    # d ḡ / d(q0, q1) weights


def _vector(name: str, value: ArrayLike, n: int) -> Array:
    """``value`` as a float64 vector of ``n`` entries (one state or input at a time)."""
    a = _leading(name, value, n)
    if a.ndim != 1:
        raise DimensionError(f'{name} must have shape ({n},); got shape {a.shape}.')
    return a


# ------------------------------------------------------------------ step matrices
class StepCache:
    """Matrices of the step of length ``h`` (built once per step length).

    Attributes
    ----------
    h : float
    Ad, Bd : ndarray, shapes (2r, 2r), (2r, m)
        Exact ZOH matrices of the linear part.
    W : ndarray, shape (2r, r)
        ``Γ = (A_d - I) P^{-1} [I; 0]``: response to the discrete-gradient force.
    """

    __slots__ = ('h', 'Ad', 'Bd', 'W', 'Wq', 'Wv', 'Jinv')

    def __init__(self, h: float, Ad: Array, Bd: Array, W: Array) -> None:
        r = W.shape[1]
        self.h, self.Ad, self.Bd, self.W = h, Ad, Bd, W
        self.Wq = np.ascontiguousarray(W[:r])
        self.Wv = np.ascontiguousarray(W[r:])
        self.Jinv: Array | None = None


@register_model_class
class CubicSecondOrderModel(LinearROM):
    """Second-order ROM whose restoring force is the gradient of a quartic potential.

    .. math::

        \\ddot q + C \\dot q + K q + \\tfrac12 G(q, q, \\cdot) + \\tfrac16 H(q, q, q, \\cdot)
        = B u, \\qquad y = E q + y_{ref}

    The state used by :meth:`step` is ``x = [q; q̇]`` (length ``2r``), as for
    :class:`~soft_rom.models.SecondOrderModel`; :meth:`discretize` and :attr:`system` give the
    linearization about the reference configuration (used for the stability margin and as
    the start of the Kalman filter), :meth:`step` and :meth:`simulate` the nonlinear model.

    Parameters
    ----------
    K, C : ndarray, shape (r, r)
        Stiffness at the reference and damping (symmetric positive definite when learned).
    G : ndarray, shape (r, r, r)
        Fully symmetric cubic coefficients of the potential.
    H : ndarray, shape (r, r, r, r)
        Fully symmetric quartic coefficients (``H(q, q, q, q) > 0`` for ``q ≠ 0`` when learned,
        so the potential is bounded below and grows at infinity).
    B : ndarray, shape (r, m)
    E : ndarray, shape (p, r)
    dt : float
        Native sample time (s).
    y_ref : ndarray, shape (p,)
    newton_tol : float
        Relative tolerance of the implicit solve (default 1e-12).
    """

    method = 'lopinf'
    _matrix_names = ('K', 'C', 'G', 'H', 'B', 'E')
    _file_methods = ('lopinf',)
    _format_version = CUBIC_FORMAT_VERSION

    def __init__(self, K: ArrayLike, C: ArrayLike, G: ArrayLike, H: ArrayLike, B: ArrayLike,
                 E: ArrayLike, *, dt: float, y_ref: ArrayLike | None = None,
                 newton_tol: float = 1e-12, **kwargs: Any) -> None:
        lin = SecondOrderModel(K, C, B, E, dt=dt, y_ref=y_ref)
        r = lin.r
        super().__init__(dt=dt, y_ref=lin.y_ref, n_inputs=lin.n_inputs,
                         n_outputs=lin.n_outputs, **kwargs)
        self.K, self.C, self.B, self.E = lin.K, lin.C, lin.B, lin.E
        self.G = _arr('G', G, (r, r, r))
        self.H = _arr('H', H, (r, r, r, r))
        for name, T in (('G', self.G), ('H', self.H)):
            if not is_symmetric(T):
                raise DimensionError(f'{name} must be a fully symmetric tensor.')
        self._linear = SecondOrderModel(self.K, self.C, self.B, self.E, dt=self.dt,
                                        y_ref=self.y_ref)
        self.newton_tol = float(newton_tol)
        # Flattened operators: force_nl(q) = F2 kron(q, q) + F3 kron(q, q, q); Hessian_nl(q)
        # = (M1 q + M2 kron(q, q)).reshape(r, r).
        self._F2 = np.ascontiguousarray(0.5 * self.G.reshape(r, r * r))
        self._F3 = np.ascontiguousarray(self.H.reshape(r, r ** 3) / 6.0)
        self._M1 = np.ascontiguousarray(self.G.reshape(r * r, r))
        self._M2 = np.ascontiguousarray(0.5 * self.H.reshape(r * r, r * r))
        self._caches: dict[float, StepCache] = {}

    # -- sizes ---------------------------------------------------------------------------
    @property
    def r(self) -> int:
        return int(self.K.shape[0])

    @property
    def n_states(self) -> int:
        return 2 * self.r

    @property
    def is_nonlinear(self) -> bool:
        """True: :meth:`step` is not the affine map of :attr:`system`."""
        return True

    def linear_part(self) -> SecondOrderModel:
        """The model without the cubic and quartic terms (the linearization at ``q = 0``)."""
        return self._linear

    # -- potential -----------------------------------------------------------------------
    def potential(self, q: ArrayLike) -> float:
        """``V(q)`` (``q`` of shape (r,))."""
        q = np.asarray(q, dtype=np.float64)
        q2 = np.outer(q, q).ravel()
        return float(0.5 * q @ self.K @ q + (self._F2 @ q2) @ q / 3.0
                     + (self._F3 @ np.outer(q2, q).ravel()) @ q / 4.0)

    def force(self, q: ArrayLike) -> Array:
        """Restoring force ``∇V(q)``, shape (r,)."""
        q = np.asarray(q, dtype=np.float64)
        return self.K @ q + self._force_nl(q)

    def _force_nl(self, q: Array) -> Array:
        q2 = np.outer(q, q).ravel()
        return self._F2 @ q2 + self._F3 @ np.outer(q2, q).ravel()

    def stiffness(self, q: ArrayLike) -> Array:
        """Tangent stiffness ``∇²V(q)``, shape (r, r)."""
        q = np.asarray(q, dtype=np.float64)
        r = self.r
        return self.K + (self._M1 @ q + self._M2 @ np.outer(q, q).ravel()).reshape(r, r)

    def energy(self, x: ArrayLike) -> float:
        """Mechanical energy ``½|q̇|² + V(q)`` of the state ``x = [q; q̇]``."""
        x = np.asarray(x, dtype=np.float64)
        r = self.r
        return float(0.5 * x[r:] @ x[r:]) + self.potential(x[:r])

    # -- linearization -----------------------------------------------------------------
    def first_order(self) -> tuple[Array, Array, Array]:
        """Continuous first-order form of the linearization at the reference."""
        return self._linear.first_order()

    def eigenvalues(self) -> NDArray[np.complex128]:
        """Continuous eigenvalues of the linearization at the reference."""
        return self._linear.eigenvalues()

    def discretize(self, dt: float | None = None) -> DiscreteSystem:
        """The exact ZOH discretization of the linearization at the reference."""
        return self._linear.discretize(dt)

    def state_from_output(self, y: ArrayLike, u: ArrayLike | None = None) -> Array:
        return self._linear.state_from_output(y, u)

    # -- stepping ------------------------------------------------------------------------
    def step_cache(self, dt: float | None = None) -> StepCache:
        """The matrices of a step of length ``dt`` (cached)."""
        h = self.dt if dt is None else step_length(dt)
        cache = self._caches.get(h)
        if cache is None:
            sys_ = self._linear.discretize(h)
            r = self.r
            Pinv_Eq = np.zeros((2 * r, r))
            Pinv_Eq[:r] = np.linalg.inv(self.K)
            W = (sys_.A - np.eye(2 * r)) @ Pinv_Eq
            cache = StepCache(h, np.asarray(sys_.A), np.asarray(sys_.B), W)
            if len(self._caches) > 64:
                self._caches.clear()
            self._caches[h] = cache
        return cache

    def _gbar(self, q0: Array, q1: Array) -> Array:
        """AVF discrete gradient of the nonlinear potential, in closed form.

        With ``m = (q0 + q1)/2`` and ``d = q1 - q0`` the segment is ``m + (s - ½) d`` and
        ``∫ q⊗q ds = m⊗m + d⊗d/12``, ``∫ q⊗q⊗q ds = m⊗m⊗m + (m⊗d⊗d + d⊗m⊗d + d⊗d⊗m)/12``;
        ``H`` is symmetric, so the cubic term is ``⅙ H(·, m⊗m + d⊗d/4, m)``.
        """
        m = 0.5 * (q0 + q1)
        d = q1 - q0
        mm = np.outer(m, m).ravel()
        dd = np.outer(d, d).ravel()
        return self._F2 @ (mm + dd / 12.0) + self._F3 @ np.outer(mm + 0.25 * dd, m).ravel()

    def _gbar_jac(self, q0: Array, q1: Array) -> tuple[Array, Array]:
        """Derivatives of ``ḡ(q0, q1)`` with respect to ``q0`` and ``q1``, shape (r, r) each."""
        r = q0.shape[0]
        Qg = q0[:, None] + (q1 - q0)[:, None] * _S
        Q2 = (Qg[:, None, :] * Qg[None, :, :]).reshape(r * r, 2)
        J = self._M1 @ (Qg @ _W01) + self._M2 @ (Q2 @ _W01)
        return J[:, 0].reshape(r, r), J[:, 1].reshape(r, r)

    def _newton_inverse(self, cache: StepCache, q0: Array, q1: Array) -> Array:
        _J0, J1 = self._gbar_jac(q0, q1)
        return np.asarray(np.linalg.inv(np.eye(self.r) - cache.Wq @ J1), dtype=np.float64)

    def _solve_step(self, cache: StepCache, x: Array, bu: Array, g_prev: Array | None
                    ) -> tuple[Array, Array] | None:
        """Solve ``q1 = z_q + W_q ḡ(q0, q1)``; returns ``(x1, ḡ)`` or ``None`` if no convergence.

        Simplified Newton: the inverse Newton matrix of an earlier step is reused (cached per
        step length) and refreshed when the iteration contracts slowly; the first iterate uses
        the previous step's discrete force (``g_prev``).
        """
        r = self.r
        z = cache.Ad @ x + bu
        q0 = x[:r]
        zq = z[:r]
        Wq = cache.Wq
        q1 = zq + Wq @ (self._gbar(q0, q0) if g_prev is None else g_prev)
        tol = self.newton_tol * (1.0 + float(np.abs(zq).max()))
        Jinv = cache.Jinv
        if Jinv is None:
            Jinv = cache.Jinv = self._newton_inverse(cache, q0, q1)
        last = np.inf
        fresh = False
        for _ in range(40):
            g = self._gbar(q0, q1)
            F = q1 - zq - Wq @ g
            err = float(np.abs(F).max())
            if err <= tol:
                return z + cache.W @ g, g
            if not err < 1e300:
                return None
            if err > 0.1 * last and not fresh:          # slow: refresh the Newton matrix
                Jinv = cache.Jinv = self._newton_inverse(cache, q0, q1)
                fresh = True
            elif err > 0.5 * last:                      # diverging even with a fresh one
                return None
            else:
                fresh = False
            last = err
            q1 = q1 - Jinv @ F
        return None

    def _advance(self, x: Array, u: Array, h: float, depth: int = 0) -> Array:
        cache = self.step_cache(h)
        out = self._solve_step(cache, x, cache.Bd @ u, None)
        if out is not None:
            return out[0]
        if depth >= 12:
            raise SolverError(f'the implicit step of the cubic LOpInf model did not converge '
                              f'(state norm {float(np.linalg.norm(x)):.3g}).')
        half = self._advance(x, u, 0.5 * h, depth + 1)
        return self._advance(half, u, 0.5 * h, depth + 1)

    def stepper(self, h: float) -> Callable[[Array, Array], Array]:
        """One ZOH step of ``h`` seconds as a function ``x_next = f(x, u)`` (predictor API).

        The function remembers the last discrete force for its warm start only; the result
        depends on ``(x, u)`` alone (to the Newton tolerance).
        """
        cache = self.step_cache(h)
        state: list[Array | None] = [None]

        def step(x: Array, u: Array) -> Array:
            out = self._solve_step(cache, x, cache.Bd @ u, state[0])
            if out is None:
                state[0] = None
                return self._advance(np.asarray(x, dtype=np.float64),
                                     np.asarray(u, dtype=np.float64), h)
            state[0] = out[1]
            return out[0]

        return step

    def linearize(self, x: ArrayLike, u: ArrayLike, h: float
                  ) -> tuple[Array, Array, Array, Array]:
        """Discrete Jacobians ``(A, B, C, D)`` of the step at ``(x, u)`` (extended Kalman)."""
        _x1, A, Bu = self.step_jacobian(x, u, h)
        C = np.zeros((self.n_outputs, self.n_states))
        C[:, :self.r] = self.E
        return A, Bu, C, np.zeros((self.n_outputs, self.n_inputs))

    def step(self, x: ArrayLike, u: ArrayLike, dt: float | None = None) -> Array:
        """Advance the state ``x = [q; q̇]`` by one step with ``u`` held (nonlinear).

        Parameters
        ----------
        x : ndarray, shape (2r,)
        u : ndarray, shape (m,)
            Absolute inputs.
        dt : float, optional
            Step length; default the native :attr:`dt`.
        """
        h = self.dt if dt is None else step_length(dt)
        return self._advance(*self._finite_step_args(x, u, h), h)

    def _finite_step_args(self, x: ArrayLike, u: ArrayLike, h: float) -> tuple[Array, Array]:
        """``x``, ``u`` as vectors; refused when not finite, and a ``dt`` that is not positive.

        The implicit step has no answer for them (its sub-stepping would end in a misleading
        "did not converge").
        """
        xs, us = _vector('x', x, self.n_states), _vector('u', u, self.n_inputs)
        for name, a in (('x', xs), ('u', us)):
            if not np.all(np.isfinite(a)):
                raise DimensionError(f'{name} must be finite; got {a.tolist()!r}.')
        if not (np.isfinite(h) and h > 0):
            raise DimensionError(f'dt must be positive; got {h!r}.')
        return xs, us

    def step_jacobian(self, x: ArrayLike, u: ArrayLike, dt: float | None = None
                      ) -> tuple[Array, Array, Array]:
        """The step and its exact derivatives: ``x_next, ∂x_next/∂x, ∂x_next/∂u``.

        Returns
        -------
        x_next : ndarray, shape (2r,)
        A : ndarray, shape (2r, 2r)
        Bu : ndarray, shape (2r, m)
        """
        h = self.dt if dt is None else step_length(dt)
        x, u = self._finite_step_args(x, u, h)
        cache = self.step_cache(h)
        out = self._solve_step(cache, x, cache.Bd @ u, None)
        if out is None:               # fall back to the sub-stepped map, linearized
            x1 = self._advance(x, u, h)
            return x1, cache.Ad, cache.Bd
        x1 = out[0]
        r = self.r
        J0, J1 = self._gbar_jac(x[:r], x1[:r])
        # q1 = zq + Wq g(q0, q1) -> dq1 = S (dzq + Wq J0 dq0), S = (I - Wq J1)^-1
        S = np.linalg.inv(np.eye(r) - cache.Wq @ J1)
        dq1_dx = S @ (cache.Ad[:r] + np.hstack([cache.Wq @ J0, np.zeros((r, r))]))
        dq1_du = S @ cache.Bd[:r]
        dg_dx = np.hstack([J0, np.zeros((r, r))]) + J1 @ dq1_dx
        A = cache.Ad + cache.W @ dg_dx
        Bu = cache.Bd + cache.W @ (J1 @ dq1_du)
        return x1, A, Bu

    def output(self, x: ArrayLike, u: ArrayLike | None = None) -> Array:
        """Absolute output ``y = E q + y_ref``: (p,) for x (2r,), (p, k) for x (2r, k)."""
        xs = _leading('x', x, self.n_states) if u is None else _state_and_input(
            x, u, self.n_states, self.n_inputs)[0]
        return self.E @ xs[:self.r] + (self.y_ref if xs.ndim == 1 else self.y_ref[:, None])

    def simulate(self, U: ArrayLike, x0: ArrayLike | None = None, *,
                 return_states: bool = False, dt: float | None = None
                 ) -> Array | tuple[Array, Array]:
        """Simulate the nonlinear model for inputs held over each step.

        Parameters
        ----------
        U : ndarray, shape (m, k)
            Absolute inputs, one column per sample.
        x0 : ndarray, shape (2r,), optional
            Initial state; default at rest in the reference configuration.
        return_states : bool
            Also return the states.
        dt : float, optional
            Step length (default the native :attr:`dt`).

        Returns
        -------
        Y : ndarray, shape (p, k)
        X : ndarray, shape (2r, k)
            Only with ``return_states``.
        """
        U = as_signal('U', U, rows=self.n_inputs)
        check_finite('U', U, 'simulating')      # else a misleading "did not converge"
        h = self.dt if dt is None else step_length(dt)
        cache = self.step_cache(h)
        k = U.shape[1]
        n = self.n_states
        x = self.initial_state() if x0 is None else _arr('x0', x0, (n,)).copy()
        X = np.empty((n, k))
        BU = cache.Bd @ U
        r = self.r
        g: Array | None = None
        for j in range(k):
            X[:, j] = x
            if j == k - 1:
                break
            out = self._solve_step(cache, x, BU[:, j], g)
            if out is None:
                x, g = self._advance(x, U[:, j], h), None
            else:
                x, g = out
        Y = self.E @ X[:r] + self.y_ref[:, None]
        return (Y, X) if return_states else Y

    # -- files ---------------------------------------------------------------------------
    def header(self) -> dict[str, Any]:
        head = super().header()
        head['format_version'] = CUBIC_FORMAT_VERSION
        r = self.r
        head['potential'] = {
            'degrees': [2, 3, 4],
            'form': 'V(q) = 1/2 K(q,q) + 1/6 G(q,q,q) + 1/24 H(q,q,q,q), G and H symmetric',
            'independent_entries': {'K': r * (r + 1) // 2, 'G': len(symmetric_index(r, 3)),
                                    'H': len(symmetric_index(r, 4))},
            'norm_K': float(np.linalg.norm(self.K)),
            'norm_G': float(np.linalg.norm(self.G)),
            'norm_H': float(np.linalg.norm(self.H)),
            'integrator': 'exact-ZOH linear part + AVF discrete gradient (energy-consistent)',
        }
        return head

    def matrices(self) -> dict[str, Array]:
        """The defining arrays; ``H`` as ``(r, r, r²)`` (files hold arrays of at most 3 axes)."""
        out = super().matrices()
        r = self.r
        out['H'] = self.H.reshape(r, r, r * r)
        return out

    @classmethod
    def _from_file(cls, arrays: dict[str, Array], **common: Any) -> LinearROM:
        common.pop('method', None)
        K, H = arrays['K'], arrays['H']
        r = K.shape[0] if K.ndim == 2 else -1
        if r < 1 or H.shape != (r, r, r * r):
            raise DimensionError(f'H must have shape (r, r, r*r) = ({r}, {r}, {r * r}) in a '
                                 f'file; got {H.shape}.')
        return cls(K, arrays['C'], arrays['G'], H.reshape(r, r, r, r), arrays['B'],
                   arrays['E'], **common)

    def _check_trust(self) -> list[str]:
        issues = self._linear._check_trust()
        if not any(i.startswith('unstable') for i in issues):
            gain = gain_issue(self)          # its equilibria, not its linear part's
            if gain is not None:
                issues.append(gain)
        if self.r <= 16 and not quartic_certified_positive(self.H):   # cost grows like r^6
            issues.append('the quartic part of the potential is not certified positive '
                          '(the potential may be unbounded below)')
        return issues

    def __repr__(self) -> str:
        return (f'{type(self).__name__}(method={self.method!r}, forces=cubic, r={self.r}, '
                f'm={self.n_inputs}, p={self.n_outputs}, dt={self.dt:g})')
