"""How the predictor steps a model: the linear fast path and the protocol for other models.

A :class:`~soft_rom.models.LinearROM` (unless it sets ``is_linear = False``) is stepped by
precomputed matrices ``x <- A_h x + B_h u`` for the step ``h``. Any other model must
provide (the *predictor model protocol*):

* ``method``, ``r``, ``n_states``, ``n_inputs``, ``n_outputs``, ``dt``, ``y_ref``,
  ``input_names``, ``output_names``, ``input_units``, ``output_units``, ``metadata``;
* ``initial_state() -> x`` (shape (n_states,));
* ``stepper(h) -> step`` with ``step(x, u) -> x_next``: one zero-order-hold step of ``h``
  seconds (may be implicit); must not modify its arguments -- or, instead,
  ``step(x, u, dt) -> x_next``;
* ``output(x, u) -> y`` (absolute output, shape (p,));
* ``linearize(x, u, h) -> (A, B, C, D)``: discrete Jacobians at ``(x, u)`` (Kalman gain)
  -- or, instead, ``step_jacobian(x, u, dt) -> (x_next, A, B)`` with ``C``, ``D`` taken
  from ``discretize(h)``;
* ``simulate(U) -> Y`` and ``state_from_output(y, u) -> x``; optionally
  ``stability_margin()``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
import scipy.linalg as sla

from soft_rom.data import all_finite
from soft_rom.errors import ConfigError, ModelFileError, SolverError
from soft_rom.models import DiscreteModel, file_sha256, LinearROM

__all__ = ['Dynamics', 'is_linear', 'kalman_gain', 'model_info']

Array = NDArray[np.float64]


#: What every model the predictor runs has (the rest of the protocol is checked on use).
_PROTOCOL = ('dt', 'y_ref', 'n_states', 'n_inputs', 'n_outputs', 'input_names',
             'output_names', 'initial_state', 'output')


def is_linear(model: Any) -> bool:
    """Whether ``model`` takes the linear fast path.

    A :class:`~soft_rom.models.LinearROM` unless it says otherwise (``is_linear`` false or
    ``is_nonlinear`` true).
    """
    return (isinstance(model, LinearROM) and getattr(model, 'is_linear', True) is not False
            and not getattr(model, 'is_nonlinear', False))


def _stepper(model: Any, h: float) -> Any:
    if callable(getattr(model, 'stepper', None)):
        return model.stepper(h)
    return lambda x, u: model.step(x, u, h)


def _linearize(model: Any, x: Array, u: Array, h: float) -> tuple[Array, ...]:
    if callable(getattr(model, 'linearize', None)):
        return tuple(np.asarray(a, dtype=np.float64) for a in model.linearize(x, u, h))
    _, A, B = model.step_jacobian(x, u, h)
    sys_h = model.discretize(h)
    return (np.asarray(A, dtype=np.float64), np.asarray(B, dtype=np.float64),
            np.asarray(sys_h.C, dtype=np.float64), np.asarray(sys_h.D, dtype=np.float64))


def kalman_gain(A: Array, C: Array, Q: Array, R: Array) -> Array:
    """Steady-state Kalman (filter-form) gain for ``x+ = A x + w``, ``y = C x + v``.

    The a-priori error covariance ``P`` solves the discrete algebraic Riccati equation
    ``P = A P Aᵀ - A P Cᵀ (C P Cᵀ + R)⁻¹ C P Aᵀ + Q``; the gain ``L = P Cᵀ (C P Cᵀ + R)⁻¹``
    corrects the state with ``x ← x + L (y - ŷ)``.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    C : ndarray, shape (p, n)
    Q : ndarray, shape (n, n)
        Process noise covariance (positive semi-definite).
    R : ndarray, shape (p, p)
        Measurement noise covariance (positive definite).

    Returns
    -------
    L : ndarray, shape (n, p)
    """
    try:
        P = sla.solve_discrete_are(A.T, C.T, Q, R)
    except (np.linalg.LinAlgError, ValueError) as err:
        raise SolverError(
            f'Kalman design failed (discrete Riccati equation: {err}); the ROM may be '
            'undetectable from its outputs. Change the noise covariances or run open loop.'
        ) from err
    S = C @ P @ C.T + R
    L = np.linalg.solve(S.T, (P @ C.T).T).T
    if not all_finite(L):
        raise SolverError('Kalman design produced a non-finite gain; run open loop.')
    return L


def model_info(model: Any, path: str | os.PathLike[str] | None = None,
               sha256: str | None = None) -> dict[str, Any]:
    """JSON-able description of a model, published latched by the node as ``~/model_info``."""
    if sha256 is None and path is not None and Path(path).is_file():
        sha256 = file_sha256(path)
    margin = getattr(model, 'stability_margin', None)
    trust = getattr(model, 'trust_issues', None)
    return {
        'method': model.method,
        'class': type(model).__name__,
        'r': model.r,
        'n_states': model.n_states,
        'dt': model.dt,
        'input_names': list(model.input_names),
        'input_units': list(model.input_units),
        'output_names': list(model.output_names),
        'output_units': list(model.output_units),
        'y_ref': np.asarray(model.y_ref).tolist(),
        'stability_margin': float(margin()) if callable(margin) else None,
        'path': None if path is None else str(path),
        'sha256': sha256,
        'trust': list(trust()) if callable(trust) else [],
    }


class Dynamics:
    """Everything derived from one model and one config, built before it is swapped in.

    Attributes
    ----------
    h : float
        Step in seconds; ``h_ns`` the same in (possibly fractional) nanoseconds.
    linear : bool
        Linear fast path (``A``, ``B``, ``C``, ``D`` set) or the model protocol (``stepper``).
    L : ndarray, shape (n, p), or None
        Kalman gain.
    """

    def __init__(self, model: Any, config: Any,
                 path: str | os.PathLike[str] | None = None) -> None:
        missing = [a for a in _PROTOCOL if not hasattr(model, a)]
        if missing:
            raise TypeError(f'the predictor needs a model (a LinearROM, a model file path or a '
                            f'model of the predictor protocol); got {type(model).__name__} '
                            f'{str(model)[:40]!r}, without {", ".join(missing[:4])}.')
        self.model = model
        self.path = None if path is None else str(path)
        self.sha256 = file_sha256(path) if path is not None else None
        dt = float(model.dt)
        self.discrete = isinstance(model, DiscreteModel)
        h = dt
        if config.rate_hz > 0 and config.stepping != 'input':
            h = 1.0 / config.rate_hz
            if self.discrete:
                ratio = h / dt
                if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
                    raise ConfigError(
                        f'rate_hz={config.rate_hz:g}: a {model.method} model steps by whole '
                        f'multiples of its dt={dt:g} s only; use rate_hz = {1 / dt:g} / j '
                        'for a whole j, or 0 for the native rate.')
                h = round(ratio) * dt
        self.h = float(h)
        self.h_ns = self.h * 1e9
        self.h_ns_int = int(round(self.h_ns)) if abs(self.h_ns - round(self.h_ns)) < 1e-6 \
            else 0
        self.linear = is_linear(model)
        self.y_ref = np.array(model.y_ref, dtype=np.float64)
        self.n, self.m, self.p = model.n_states, model.n_inputs, model.n_outputs
        self.L: Array | None = None
        if self.linear:
            sys_h = model.discretize(self.h)
            self.A = np.ascontiguousarray(sys_h.A)
            self.B = np.ascontiguousarray(sys_h.B)
            self.C = np.ascontiguousarray(sys_h.C)
            self.D = np.ascontiguousarray(sys_h.D)
            self.has_D = bool(np.any(self.D))
            self._cache: dict[int, tuple[Array, Array]] = {int(round(self.h_ns)): (self.A,
                                                                                   self.B)}
            self.stepper = None
            A_k, C_k = self.A, self.C
        else:
            self.stepper = _stepper(model, self.h)
            self.has_D = True
            x0 = np.asarray(model.initial_state(), dtype=np.float64)
            A_k, _B, C_k, D_k = _linearize(model, x0, np.zeros(self.m), self.h)
            self.C, self.D = C_k, D_k
        if config.kalman:
            Q = config.process_noise * np.eye(self.n)
            R = config.measurement_noise * np.eye(self.p)
            self.L = kalman_gain(A_k, C_k, Q, R)
        self.info = model_info(model, path, self.sha256)
        margin = self.info.get('stability_margin')
        self.unstable = isinstance(margin, float) and margin < 0
        self.trust_issues: list[str] = list(self.info['trust'])
        if config.strict_model and self.trust_issues:
            raise ModelFileError(f'model not trusted (strict_model): '
                                 f'{"; ".join(self.trust_issues)}')

    def matrices_for(self, dt_ns: int) -> tuple[Array, Array]:
        """``(A, B)`` for an exact step of ``dt_ns`` nanoseconds (continuous linear models)."""
        hit = self._cache.get(dt_ns)
        if hit is None:
            s = self.model.discretize(dt_ns * 1e-9)
            hit = (np.ascontiguousarray(s.A), np.ascontiguousarray(s.B))
            if len(self._cache) >= 256:
                self._cache.pop(next(iter(self._cache)))
            self._cache[dt_ns] = hit
        return hit

    def initial_state(self) -> Array:
        """Deviation state at the reference."""
        if self.linear:
            return np.zeros(self.n)
        return np.array(self.model.initial_state(), dtype=np.float64)
