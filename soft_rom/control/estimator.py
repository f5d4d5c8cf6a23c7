"""Offset-free state estimation: the ROM state plus a constant output disturbance.

The model is augmented with an output disturbance ``d`` (a random walk, one per output),

.. math::

    x_{k+1} = A x_k + B u_k + w_k, \\qquad d_{k+1} = d_k + w^d_k, \\qquad
    y_k = C x_k + D u_k + d_k + y_{ref} + v_k,

and ``(x, d)`` is estimated by a steady-state Kalman filter, the predictor's filter
(:func:`soft_rom.predictor.dynamics.kalman_gain`) on the augmented system. Whatever the
model's error at steady state, the innovation there is zero (``d`` absorbs it), so an MPC
that holds ``d`` over its horizon tracks a reachable reference without offset (Pannocchia
& Rawlings 2003, *Disturbance models for offset-free model-predictive control*; the
augmented pair is detectable when ``(A, C)`` is and ``A`` has no eigenvalue at 1).

Time is event time, as in the predictor: the estimate lives at a time ``t``, is carried to
each measurement's stamp with the input held (:meth:`predict_to`; exact zero-order-hold
steps for LOpInf, whole native steps for discrete models) and corrected there
(:meth:`correct`). The gain is designed for the sensor period (the nearest whole number of
model steps), so a 120 Hz motion-capture stream is weighted as what it is.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.control.mpc import require_linear
from soft_rom.errors import ConfigError, DimensionError
from soft_rom.models import DiscreteModel
from soft_rom.predictor.dynamics import kalman_gain

__all__ = ['EstimatorConfig', 'OffsetFreeEstimator', 'slow_modes']

Array = NDArray[np.float64]


@dataclass(frozen=True)
class EstimatorConfig:
    """Noise levels of the offset-free Kalman filter (standard deviations, output units).

    Parameters
    ----------
    measurement_noise : float
        Measurement noise per output (default 0.5 mm, motion capture).
    disturbance_noise : float
        Change of the output disturbance per square root of a second (random walk; default
        0.1 m/√s: the disturbance follows the model's error within a few sensor periods).
    process_noise : float
        State noise per square root of a second, in output units through ``C`` (default
        0.003 m/√s). Both defaults were chosen on a training reference (an FOM response to
        random pressures) with the LOpInf ROM; ``docs/control.md`` has the sweep.
    sensor_rate : float
        Measurements per second the gain is designed for (default 120 Hz).
    input_noise : float
        State noise entering as the inputs do, in input units per square root of a second
        (an unknown pressure acting on the model: ``Q += input_noise² B_T B_Tᵀ / T``);
        default 0.
    slow_mode_noise : float
        State noise on the model's slow modes (stable ones decaying slower than
        ``slow_mode_rate``), per square root of a second, in output units of each mode's
        output shape (default 0: off). A fitted model's slow modes are where its error
        lasts longest (the eel LOpInf r = 16 has a real mode at -0.32/s that the FOM does
        not have); with this noise the filter corrects them from the measurements instead of
        carrying them open loop, so the output disturbance does not have to follow their
        seconds-long decay. 0.03 m/√s lowers the error of the control study's static bend
        after 1 s (LOpInf r = 16 4.6 % to 4.3 %, r = 4 8.8 % to 7.4 %) but moves the study's
        choice of rate weight; ``docs/control.md`` has the measurements.
    slow_mode_rate : float
        Decay rate (1/s) below which a mode is slow (default 1/s: the horizon's 0.2 s and
        the 1 s settling asked of a static bend are both shorter than such a mode's time
        constant).
    """

    measurement_noise: float = 5e-4
    disturbance_noise: float = 0.1
    process_noise: float = 0.003
    sensor_rate: float = 120.0
    input_noise: float = 0.0
    slow_mode_noise: float = 0.0
    slow_mode_rate: float = 1.0

    def __post_init__(self) -> None:
        for name in ('measurement_noise', 'sensor_rate'):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f'estimator {name} must be > 0; got {v!r}.')
        for name in ('disturbance_noise', 'process_noise', 'input_noise', 'slow_mode_noise',
                     'slow_mode_rate'):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f'estimator {name} must be >= 0; got {v!r}.')


class OffsetFreeEstimator:
    """Event-time Kalman filter of ``(x, d)`` for a linear ROM.

    Parameters
    ----------
    model : LinearROM
    config : EstimatorConfig

    Attributes
    ----------
    x : ndarray, shape (n,)
        State estimate (deviations) at :attr:`t`.
    d : ndarray, shape (p,)
        Output disturbance estimate.
    t : float
        Time of the estimate (s).
    u : ndarray, shape (m,)
        Input held since :attr:`t`.
    L : ndarray, shape (n + p, p)
        Kalman gain of the augmented system.
    """

    def __init__(self, model: Any, config: EstimatorConfig | None = None) -> None:
        require_linear(model, 'the offset-free estimator')
        cfg = config or EstimatorConfig()
        self.model = model
        self.config = cfg
        self.dt = float(model.dt)
        self.discrete = isinstance(model, DiscreteModel)
        sys_ = model.discretize(self.dt)
        self.C = np.asarray(sys_.C, dtype=np.float64)
        self.D = np.asarray(sys_.D, dtype=np.float64)
        self.n, self.m, self.p = sys_.A.shape[0], sys_.B.shape[1], self.C.shape[0]
        self.y_ref = np.asarray(model.y_ref, dtype=np.float64)
        j = max(1, int(round(1.0 / (cfg.sensor_rate * self.dt))))
        T = j * self.dt
        sys_T = model.discretize(T)
        A_T = np.asarray(sys_T.A, dtype=np.float64)
        B_T = np.asarray(sys_T.B, dtype=np.float64)
        n, p = self.n, self.p
        Aa = np.block([[A_T, np.zeros((n, p))], [np.zeros((p, n)), np.eye(p)]])
        Ca = np.hstack([self.C, np.eye(p)])
        # state noise shaped through C's pseudo-inverse: its size is stated in output units
        Cp = np.linalg.pinv(self.C)
        Qx = (cfg.process_noise ** 2 * T) * (Cp @ Cp.T) + 1e-12 * np.eye(n)
        Qx += (cfg.input_noise ** 2 / T) * (B_T @ B_T.T)
        if cfg.slow_mode_noise > 0:
            Vs = slow_modes(A_T, self.C, T, cfg.slow_mode_rate)
            Qx += (cfg.slow_mode_noise ** 2 * T) * (Vs @ Vs.T)
        Qd = (cfg.disturbance_noise ** 2 * T) * np.eye(p)
        Qa = np.block([[Qx, np.zeros((n, p))], [np.zeros((p, n)), Qd]])
        Ra = cfg.measurement_noise ** 2 * np.eye(p)
        self.L = kalman_gain(Aa, Ca, Qa, Ra)
        self._cache: dict[int, tuple[Array, Array]] = {}
        # the step counts between measurements and control times, discretized now: a cold
        # discretization (matrix exponential) costs 1-8 ms, a control step 0.3 ms
        for steps in range(1, 2 * j + 2):
            self._matrices(steps)
        self.reset()

    def reset(self, t: float = 0.0, u: ArrayLike | None = None) -> None:
        """Back to the reference state, no disturbance, at time ``t`` with input ``u``."""
        self.x = np.zeros(self.n)
        self.d = np.zeros(self.p)
        self.t = float(t)
        self.u = np.zeros(self.m) if u is None else np.array(u, dtype=np.float64)

    def _matrices(self, steps: int) -> tuple[Array, Array]:
        hit = self._cache.get(steps)
        if hit is None:
            s = self.model.discretize(steps * self.dt)
            hit = (np.asarray(s.A, dtype=np.float64), np.asarray(s.B, dtype=np.float64))
            if len(self._cache) > 64:
                self._cache.clear()
            self._cache[steps] = hit
        return hit

    def predict_to(self, t: float) -> None:
        """Carry the estimate to time ``t`` with the held input (whole model steps).

        A time at or before :attr:`t` leaves the estimate as it is.
        """
        steps = int(math.floor((t - self.t) / self.dt + 1e-6))
        if steps <= 0:
            return
        A, B = self._matrices(steps)
        self.x = A @ self.x + B @ self.u
        self.t += steps * self.dt

    def set_input(self, u: ArrayLike) -> None:
        """The input applied from :attr:`t` on."""
        u = np.array(u, dtype=np.float64).reshape(-1)
        if u.shape != (self.m,) or not np.all(np.isfinite(u)):
            raise DimensionError(f'input must be {self.m} finite values; got {u.tolist()}.')
        self.u = u

    def output(self) -> Array:
        """Estimated absolute output ``C x + D u + d + y_ref`` at :attr:`t`."""
        return self.C @ self.x + self.D @ self.u + self.d + self.y_ref

    def correct(self, y: ArrayLike) -> Array:
        """Correct ``(x, d)`` with a measured absolute output at :attr:`t`; returns the innovation.

        Raises
        ------
        DimensionError
            ``y`` of the wrong size or not finite (the estimate is left as it was).
        """
        y = np.asarray(y, dtype=np.float64).reshape(-1)
        if y.shape != (self.p,) or not np.all(np.isfinite(y)):
            raise DimensionError(f'measurement must be {self.p} finite values; got shape '
                                 f'{y.shape}.')
        e = y - self.output()
        dz = self.L @ e
        self.x = self.x + dz[:self.n]
        self.d = self.d + dz[self.n:]
        return e


def slow_modes(A: Array, C: Array, T: float, rate: float) -> Array:
    """A real basis of the modes of ``A`` that decay slower than ``rate``.

    Parameters
    ----------
    A : ndarray, shape (n, n)
        Discrete state matrix at step ``T``.
    C : ndarray, shape (p, n)
    T : float
        Step of ``A`` (s).
    rate : float
        Decay rate (1/s): a mode with eigenvalue ``λ`` is slow when ``0 < -ln|λ| / T < rate``
        (stable and slow; an unstable mode is not one).

    Returns
    -------
    ndarray, shape (n, k)
        One column per slow real mode, two (real and imaginary parts) per slow complex
        pair, each scaled to a unit output norm ``‖C v‖ = 1`` (a column with no output is
        left as it is); ``k = 0`` when no mode is slow.
    """
    lam, V = np.linalg.eig(A)
    decay = -np.log(np.maximum(np.abs(lam), 1e-300)) / T
    cols = []
    for i in np.flatnonzero((decay > 0) & (decay < rate)):
        if lam[i].imag < -1e-12:
            continue                                    # its conjugate gives the pair
        cols.append(V[:, i].real)
        if abs(lam[i].imag) > 1e-12:
            cols.append(V[:, i].imag)
    if not cols:
        return np.zeros((A.shape[0], 0))
    Vs = np.array(cols).T
    norms = np.linalg.norm(C @ Vs, axis=0)
    return np.asarray(Vs / np.where(norms > 0, norms, 1.0), dtype=np.float64)
