"""The linear ROM families: LOpInf's second-order model and the discrete DMDc/ERA model.

* :class:`SecondOrderModel` -- the LOpInf ROM, continuous in time,

  .. math::

      \\ddot{q}(t) + C \\dot{q}(t) + K q(t) = B u(t), \\qquad y(t) = E q(t) + y_{ref},

  discretized exactly for inputs held constant over each step (zero-order hold).
* :class:`DiscreteModel` -- DMDc and ERA/OKID ROMs, discrete in time,

  .. math::

      x_{k+1} = A x_k + B u_k, \\qquad y_k = C x_k + D u_k + y_{ref}.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
import scipy.linalg as sla

from soft_rom.data import step_length
from soft_rom.errors import DimensionError
from soft_rom.models.base import (
    _arr,
    _eigvals,
    _finite_system,
    _state_input_output,
    DiscreteSystem,
    LinearROM,
    TRUST_TOL,
)
from soft_rom.models.files import register_model_class

__all__ = ['DiscreteModel', 'SecondOrderModel']

Array = NDArray[np.float64]


@lru_cache(maxsize=64)
def _zoh_cached(key: bytes, r: int, m: int, dt: float) -> tuple[Array, Array]:
    buf = np.frombuffer(key, dtype=np.float64)
    Ac = buf[: 4 * r * r].reshape(2 * r, 2 * r)
    Bc = buf[4 * r * r:].reshape(2 * r, m)
    n = 2 * r
    M = np.zeros((n + m, n + m))
    M[:n, :n] = Ac * dt
    M[:n, n:] = Bc * dt
    try:
        with np.errstate(all='ignore'):
            F = sla.expm(M)
    except (np.linalg.LinAlgError, ValueError, OverflowError, ArithmeticError) as err:
        raise DimensionError(f'the matrix exponential at dt = {dt:g} s fails ({err}).') from None
    Ad, Bd = F[:n, :n].copy(), F[:n, n:].copy()
    Ad.setflags(write=False)
    Bd.setflags(write=False)
    return Ad, Bd


class SecondOrderModel(LinearROM):
    """Continuous second-order (Lagrangian) ROM learned by LOpInf.

    .. math::

        \\ddot{q} + C \\dot{q} + K q = B u, \\qquad y = E q + y_{ref}

    The state used by :meth:`step` is ``x = [q; q̇]`` (length ``2r``). Discretization is
    exact for inputs held constant over a step (matrix exponential of the augmented
    first-order system), see Sharma et al., *Data-driven Model Reduction for Soft Robots
    via Lagrangian Operator Inference*, eq. (L_rom).

    Parameters
    ----------
    K, C : ndarray, shape (r, r)
        Stiffness and damping (symmetric positive definite when learned by LOpInf).
    B : ndarray, shape (r, m)
    E : ndarray, shape (p, r)
    dt : float
        Native sample time (that of the training data), seconds.
    y_ref : ndarray, shape (p,)
    """

    method = 'lopinf'
    _matrix_names = ('K', 'C', 'B', 'E')
    _file_methods = ('lopinf',)     # a file saying 'era' is refused, not loaded as LOpInf

    def __init__(self, K: ArrayLike, C: ArrayLike, B: ArrayLike, E: ArrayLike, *, dt: float,
                 y_ref: ArrayLike | None = None, **kwargs: Any) -> None:
        K, B, E, r = _state_input_output(('K', K), ('B', B), ('E', E))
        super().__init__(dt=dt, y_ref=y_ref, n_inputs=B.shape[1], n_outputs=E.shape[0],
                         **kwargs)
        self.K = _arr('K', K, (r, r))
        self.C = _arr('C', C, (r, r))
        self.B = _arr('B', B)
        self.E = _arr('E', E)

    @property
    def r(self) -> int:
        return int(self.K.shape[0])

    @property
    def n_states(self) -> int:
        return 2 * self.r

    def first_order(self) -> tuple[Array, Array, Array]:
        """Continuous first-order form ``ẋ = Ac x + Bc u``, ``y - y_ref = Cc x``."""
        r, m = self.r, self.n_inputs
        Ac = np.zeros((2 * r, 2 * r))
        Ac[:r, r:] = np.eye(r)
        Ac[r:, :r] = -self.K
        Ac[r:, r:] = -self.C
        Bc = np.zeros((2 * r, m))
        Bc[r:] = self.B
        Cc = np.zeros((self.n_outputs, 2 * r))
        Cc[:, :r] = self.E
        return Ac, Bc, Cc

    def eigenvalues(self) -> NDArray[np.complex128]:
        """Continuous-time eigenvalues of ``[[0, I], [-K, -C]]``."""
        return np.asarray(np.linalg.eigvals(self.first_order()[0]), dtype=np.complex128)

    def discretize(self, dt: float | None = None) -> DiscreteSystem:
        dt = self.dt if dt is None else step_length(dt)
        Ac, Bc, Cc = self.first_order()
        key = np.concatenate([Ac.ravel(), Bc.ravel()]).tobytes()
        Ad, Bd = _zoh_cached(key, self.r, self.n_inputs, dt)
        return _finite_system(
            DiscreteSystem(Ad, Bd, Cc, np.zeros((self.n_outputs, self.n_inputs)), dt),
            'LOpInf model')

    def _check_trust(self) -> list[str]:
        issues = super()._check_trust()
        try:
            ev = _eigvals(self.first_order()[0])
        except DimensionError:
            ev = np.zeros(0, dtype=np.complex128)
        if ev.size:
            scale = max(1.0, float(np.max(np.abs(ev))))
            worst = float(np.max(ev.real))
            if worst > TRUST_TOL * scale and not any(i.startswith('unstable') for i in issues):
                issues.append(f'unstable: a continuous eigenvalue has real part {worst:.3g} > 0')
        for name in ('K', 'C'):
            M = getattr(self, name)
            norm = float(np.linalg.norm(M))
            if norm == 0.0:
                continue
            if float(np.linalg.norm(M - M.T)) > TRUST_TOL * norm:
                issues.append(f'{name} is not symmetric')
            try:
                lam = np.linalg.eigvalsh(0.5 * (M + M.T))
            except np.linalg.LinAlgError:
                issues.append(f'the eigenvalues of {name} cannot be computed')
                continue
            if lam[0] < -TRUST_TOL * max(abs(lam[0]), abs(lam[-1])):
                kind = 'negative definite' if lam[-1] < 0 else 'indefinite'
                issues.append(f'{name} is {kind} (eigenvalues in [{lam[0]:.3g}, {lam[-1]:.3g}]'
                              '); LOpInf stiffness and damping are positive')
        return issues

    def state_from_output(self, y: ArrayLike, u: ArrayLike | None = None) -> Array:
        dy = _arr('y', y, (self.n_outputs,)) - self.y_ref
        if u is not None:
            _arr('u', u, (self.n_inputs,))
        q, *_ = np.linalg.lstsq(self.E, dy, rcond=None)
        return np.concatenate([q, np.zeros(self.r)])


class DiscreteModel(LinearROM):
    """Discrete-time state-space ROM (DMDc, ERA/OKID).

    .. math:: x_{k+1} = A x_k + B u_k, \\qquad y_k = C x_k + D u_k + y_{ref}

    Parameters
    ----------
    A : ndarray, shape (r, r)
    B : ndarray, shape (r, m)
    C : ndarray, shape (p, r)
    D : ndarray, shape (p, m), optional
        Feedthrough (ERA/OKID); zero by default (DMDc).
    dt : float
        Sample time of the model, seconds.
    method : str
        ``'dmdc'`` or ``'era'`` (stored in the file).
    """

    method = 'discrete'
    _matrix_names = ('A', 'B', 'C', 'D')

    def __init__(self, A: ArrayLike, B: ArrayLike, C: ArrayLike, D: ArrayLike | None = None, *,
                 dt: float, method: str = 'discrete', y_ref: ArrayLike | None = None,
                 **kwargs: Any) -> None:
        A, B, C, r = _state_input_output(('A', A), ('B', B), ('C', C))
        super().__init__(dt=dt, y_ref=y_ref, n_inputs=B.shape[1], n_outputs=C.shape[0],
                         **kwargs)
        self.method = str(method)  # type: ignore[misc]
        self.A = _arr('A', A)
        self.B = _arr('B', B)
        self.C = _arr('C', C)
        self.D = _arr('D', np.zeros((C.shape[0], B.shape[1])) if D is None else D,
                      (C.shape[0], B.shape[1]))

    @property
    def r(self) -> int:
        return int(self.A.shape[0])

    @property
    def n_states(self) -> int:
        return self.r

    def discretize(self, dt: float | None = None) -> DiscreteSystem:
        """Return the system at ``dt``, which must be a whole multiple of :attr:`dt`.

        A multiple ``j`` gives ``A^j`` and ``(A^{j-1} + ... + I) B`` (input held for ``j``
        native steps).
        """
        if dt is None:
            return DiscreteSystem(self.A, self.B, self.C, self.D, self.dt)
        dt = step_length(dt)
        if abs(dt - self.dt) <= 1e-9 * self.dt:
            return DiscreteSystem(self.A, self.B, self.C, self.D, self.dt)
        ratio = dt / self.dt
        j = int(round(ratio))
        if j < 1 or abs(ratio - j) > 1e-6:
            raise DimensionError(
                f'{self.method} model has sample time {self.dt:g} s; it can step by whole '
                f'multiples of it only, not {dt:g} s. Step at the model rate instead.')
        r, m = self.B.shape
        # [[A, B], [0, I]]^j = [[A^j, (A^{j-1} + ... + I) B], [0, I]]: log2(j) products
        aug = np.block([[self.A, self.B], [np.zeros((m, r)), np.eye(m)]])
        with np.errstate(all='ignore'):
            P = np.linalg.matrix_power(aug, j)
            sys_ = DiscreteSystem(P[:r, :r], P[:r, r:], self.C, self.D, j * self.dt)
        return _finite_system(sys_, f'{self.method} model')

    @classmethod
    def _from_file(cls, arrays: dict[str, Array], **common: Any) -> LinearROM:
        return cls(*(arrays[name] for name in cls._matrix_names), **common)


register_model_class(SecondOrderModel)
register_model_class(DiscreteModel)
