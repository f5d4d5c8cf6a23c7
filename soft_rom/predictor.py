"""ROS-free real-time predictor: a loaded ROM, its state, held inputs and an error monitor.

This is everything the predictor node (:mod:`soft_rom.ros.predictor_node`) does, without
ROS: the node converts messages, calls a :class:`Predictor` and converts back;
``soft-rom replay`` runs the same object offline over a bag.

Time and stepping
-----------------
The ROM is advanced with the inputs held constant between updates (zero-order hold), the
assumption under which every model in :mod:`soft_rom.models` is discretized:

.. math:: x_{j+1} = A_h x_j + B_h u_j, \\qquad \\hat y_j = C x_j + D u_j + y_{ref}.

Two stepping modes (:attr:`PredictorConfig.stepping`):

* ``'fixed'`` -- a fixed integration step ``h`` (default the model's ``dt``);
  :meth:`Predictor.advance_to` takes every whole step up to the given time.
* ``'input'`` -- driven by input stamps: each new input first advances the model over the
  elapsed time with the previous input held. A :class:`~soft_rom.models.SecondOrderModel`
  is discretized exactly for the elapsed time (cached per nanosecond step); a
  :class:`~soft_rom.models.DiscreteModel` can only step by whole native steps, so it takes
  ``floor(elapsed / dt)`` of them and carries the remainder to the next update.

Bad inputs (defined behaviour, each counted in :attr:`Predictor.counters`)
--------------------------------------------------------------------------
* wrong length or channel index: dropped, counted ``wrong_length``; the held value stays.
* NaN or Inf: dropped, counted ``nonfinite``; the held value stays.
* stamp older than the channel's previous stamp: dropped, counted ``backwards``; older by
  more than ``clock_reset_s`` (a restarted clock, e.g. a bag played again): the predictor
  resets and takes it, counted ``clock_reset``.
* stamp older than the model time (another channel already advanced the model past it):
  the value is taken from the current model time on, counted ``late``.
* a channel silent for longer than ``input_timeout_s``: its last value is held and the
  health is ``STALE`` with the channel named; so it is before the first value arrives
  (inputs start at zero, the reference).
* a non-finite state (an unstable model that diverged): the state is reset to the reference,
  counted ``diverged``, and the health is ``ERROR`` until the next reset.

Any drop within the last ``input_timeout_s`` makes the health at least ``WARN``.

Error monitor and state correction
----------------------------------
Each measured output (:meth:`Predictor.measure`) is compared with the prediction *before*
any correction; the windowed relative errors

.. math:: e = \\sqrt{\\sum \\|y - \\hat y\\|^2 / \\sum \\|y\\|^2}, \\qquad
          e_{dev} = \\sqrt{\\sum \\|y - \\hat y\\|^2 / \\sum \\|y - y_{ref}\\|^2}

over the last ``error_window`` measurements drive the health (``error_metric`` chooses
which one is held against ``warn_threshold`` / ``error_threshold``). With
``kalman=True`` the state is then corrected by a steady-state Kalman filter designed on
the discretized ROM (gain from :func:`scipy.linalg.solve_discrete_are`), which keeps the
prediction locked to the measurements; open-loop prediction (the paper's) is the default.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, replace
import enum
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
import scipy.linalg as sla

from soft_rom.data import as_signal, Episode
from soft_rom.errors import ConfigError, DimensionError, ModelFileError, SolverError
from soft_rom.models import DiscreteModel, file_sha256, LinearROM, load_model

__all__ = [
    'Health',
    'Level',
    'Predictor',
    'PredictorConfig',
    'ReplayResult',
    'kalman_gain',
    'kalman_vs_open_loop',
    'model_info',
    'replay_episode',
]

Array = NDArray[np.float64]

_COUNTERS = ('wrong_length', 'nonfinite', 'backwards', 'clock_reset', 'late', 'measured_dropped',
             'diverged',
             'steps', 'inputs', 'measurements', 'catchup_skipped')


_TINY = float(np.finfo(float).tiny)


class Level(enum.IntEnum):
    """Health level; values equal ``diagnostic_msgs/msg/DiagnosticStatus`` levels."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


_SEVERITY = {Level.OK: 0, Level.WARN: 1, Level.STALE: 2, Level.ERROR: 3}


@dataclass(frozen=True)
class PredictorConfig:
    """Run-time settings of a :class:`Predictor` (the node's parameters, minus ROS ones).

    Parameters
    ----------
    stepping : {'fixed', 'input'}
        Fixed integration step, or stepping driven by input stamps.
    rate_hz : float
        Integration rate for ``'fixed'`` stepping; ``0`` means the model's native ``1/dt``.
        A discrete-time model (DMDc, ERA) accepts only integer divisors of its rate.
    input_timeout_s : float
        An input silent for longer than this makes the health ``STALE`` (value held).
    error_window : int
        Number of measurements in the windowed relative error.
    error_metric : {'deviation', 'absolute'}
        Which windowed error is compared with the thresholds.
    warn_threshold, error_threshold : float
        Windowed relative error above which the health is ``WARN`` / ``ERROR``.
    initial_state : {'reference', 'measured'}
        Start (and restart after :meth:`Predictor.reset`) at the reference configuration,
        or at the least-squares state of the first measured output.
    kalman : bool
        Correct the state with a steady-state Kalman filter at each measurement.
    process_noise, measurement_noise : float
        Kalman design covariances ``Q = process_noise * I`` (per state, per integration
        step) and ``R = measurement_noise * I`` (per output), in squared state/output units.
    max_catchup_steps : int
        Most steps taken in one :meth:`Predictor.advance_to` call; beyond that the model
        time jumps forward with the state held (counted ``catchup_skipped``), so a stalled
        clock can never block the caller.
    clock_reset_s : float
        An input stamp older than the newest one by more than this is a restarted clock
        (a bag played again): the predictor resets (counted ``clock_reset``) and takes it.
        Smaller steps back are dropped (``backwards``). ``0`` disables the reset.

    Notes
    -----
    The Kalman gain is designed for the integration step ``h`` and assumes about one
    measurement per step; with rarer measurements it is conservative, not optimal.
    """

    stepping: str = 'fixed'
    rate_hz: float = 0.0
    input_timeout_s: float = 0.5
    error_window: int = 100
    error_metric: str = 'deviation'
    warn_threshold: float = 0.1
    error_threshold: float = 0.3
    initial_state: str = 'reference'
    kalman: bool = False
    process_noise: float = 1e-6
    measurement_noise: float = 1e-4
    max_catchup_steps: int = 10000
    clock_reset_s: float = 1.0

    def __post_init__(self) -> None:
        def bad(name: str, expected: str) -> ConfigError:
            return ConfigError(f'predictor {name} must be {expected}; got '
                               f'{getattr(self, name)!r}.')

        if self.stepping not in ('fixed', 'input'):
            raise bad('stepping', "'fixed' or 'input'")
        if self.error_metric not in ('deviation', 'absolute'):
            raise bad('error_metric', "'deviation' or 'absolute'")
        if self.initial_state not in ('reference', 'measured'):
            raise bad('initial_state', "'reference' or 'measured'")
        for name in ('rate_hz', 'input_timeout_s', 'warn_threshold', 'error_threshold',
                     'clock_reset_s'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise bad(name, 'a finite number >= 0')
        for name in ('process_noise', 'measurement_noise'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise bad(name, 'a finite number > 0')
        if self.warn_threshold > self.error_threshold:
            raise ConfigError(f'warn_threshold ({self.warn_threshold}) must not exceed '
                              f'error_threshold ({self.error_threshold}).')
        for name in ('error_window', 'max_catchup_steps'):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise bad(name, 'an integer >= 1')

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> PredictorConfig:
        """Build from a dict (e.g. a YAML section), refusing unknown keys."""
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f'unknown predictor settings {unknown}; known: {sorted(known)}.')
        return cls(**dict(values))

    def replace(self, **changes: Any) -> PredictorConfig:
        """A copy with some settings changed (validated)."""
        return replace(self, **changes)


@dataclass(frozen=True)
class Health:
    """What the monitor says now.

    Attributes
    ----------
    level : Level
    message : str
        One line: the reasons joined, or ``'ok'``.
    reasons : tuple of str
    values : dict
        Figures for diagnostics (errors, counters, input ages, model time).
    """

    level: Level
    message: str
    reasons: tuple[str, ...] = ()
    values: dict[str, float | int | str] = field(default_factory=dict)


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
    if not np.all(np.isfinite(L)):
        raise SolverError('Kalman design produced a non-finite gain; run open loop.')
    return L


def model_info(model: LinearROM, path: str | os.PathLike[str] | None = None,
               sha256: str | None = None) -> dict[str, Any]:
    """JSON-able description of a model, published latched by the node as ``~/model_info``."""
    if sha256 is None and path is not None and Path(path).is_file():
        sha256 = file_sha256(path)
    return {
        'method': model.method,
        'class': type(model).__name__,
        'r': model.r,
        'n_states': model.n_states,
        'dt': model.dt,
        'input_names': model.input_names,
        'input_units': model.input_units,
        'output_names': model.output_names,
        'output_units': model.output_units,
        'y_ref': model.y_ref.tolist(),
        'stability_margin': model.stability_margin(),
        'path': None if path is None else str(path),
        'sha256': sha256,
    }


class _Runtime:
    """Everything derived from one model and one config, built before it is swapped in."""

    def __init__(self, model: LinearROM, config: PredictorConfig,
                 path: str | os.PathLike[str] | None = None) -> None:
        self.model = model
        self.path = None if path is None else str(path)
        self.sha256 = file_sha256(path) if path is not None else None
        dt = model.dt
        if config.stepping == 'fixed' and config.rate_hz > 0:
            h = 1.0 / config.rate_hz
            if isinstance(model, DiscreteModel):
                ratio = h / dt
                if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
                    raise ConfigError(
                        f'rate_hz={config.rate_hz:g}: a {model.method} model steps by whole '
                        f'multiples of its dt={dt:g} s only; use rate_hz = {1 / dt:g} / j '
                        'for a whole j, or 0 for the native rate.')
                h = round(ratio) * dt
        else:
            h = dt
        self.h = float(h)
        self.discrete = isinstance(model, DiscreteModel)
        sys_h = model.discretize(self.h)
        self.A = np.ascontiguousarray(sys_h.A)
        self.B = np.ascontiguousarray(sys_h.B)
        self.C = np.ascontiguousarray(sys_h.C)
        self.D = np.ascontiguousarray(sys_h.D)
        self.has_D = bool(np.any(self.D))
        self.y_ref = np.array(model.y_ref)
        self.n, self.m, self.p = model.n_states, model.n_inputs, model.n_outputs
        self._cache: dict[int, tuple[Array, Array]] = {int(round(self.h * 1e9)): (self.A,
                                                                                   self.B)}
        self.L: Array | None = None
        if config.kalman:
            Q = config.process_noise * np.eye(self.n)
            R = config.measurement_noise * np.eye(self.p)
            self.L = kalman_gain(self.A, self.C, Q, R)
        self.info = model_info(model, path, self.sha256)

    def matrices_for(self, dt: float) -> tuple[Array, Array]:
        """``(A, B)`` for an exact step of ``dt`` seconds (continuous models only)."""
        key = int(round(dt * 1e9))
        hit = self._cache.get(key)
        if hit is None:
            s = self.model.discretize(key * 1e-9)
            hit = (np.ascontiguousarray(s.A), np.ascontiguousarray(s.B))
            if len(self._cache) >= 256:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = hit
        return hit


class Predictor:
    """A ROM running in real time: held inputs, state, error monitor, optional Kalman filter.

    Parameters
    ----------
    model : LinearROM or path
        A model object or a model file (see :func:`soft_rom.models.load_model`).
    config : PredictorConfig, optional

    Attributes
    ----------
    x : ndarray, shape (n_states,)
        Current state (deviation from the reference), at :attr:`t`.
    u : ndarray, shape (m,)
        Held absolute inputs.
    t : float or None
        Model time in seconds (``None`` until the first input or :meth:`advance_to`).
    counters : dict of str to int
        ``wrong_length``, ``nonfinite``, ``backwards``, ``late``, ``measured_dropped``,
        ``diverged``, ``steps``, ``inputs``, ``measurements``, ``catchup_skipped``.

    Examples
    --------
    >>> p = Predictor(model)                        # doctest: +SKIP
    >>> p.set_input(u, stamp=0.0); p.advance_to(0.1); y = p.output()  # doctest: +SKIP
    """

    def __init__(self, model: LinearROM | str | os.PathLike[str],
                 config: PredictorConfig | None = None) -> None:
        self.config = PredictorConfig() if config is None else config
        path = None
        if not isinstance(model, LinearROM):
            path = model
            model = load_model(model)
        self._rt = _Runtime(model, self.config, path)
        self._init_buffers()
        self.counters = dict.fromkeys(_COUNTERS, 0)
        self.reset()

    # -- construction / reload -----------------------------------------------------------
    def _init_buffers(self) -> None:
        rt = self._rt
        self.x = np.zeros(rt.n)
        self._xn = np.zeros(rt.n)
        self.u = np.zeros(rt.m)
        self._Bu = np.zeros(rt.n)
        self._y = np.zeros(rt.p)
        self._dy = np.zeros(rt.p)
        self._stamp = np.full(rt.m, -np.inf)     # last accepted stamp per input channel
        self._arrival = np.full(rt.m, -np.inf)   # time of last accepted value per channel
        w = self.config.error_window
        self._dev = np.zeros(rt.p)
        self._clear_window(w)
        self._last_drop = -np.inf
        self._drop_reason = ''
        self._diverged = False

    @property
    def model(self) -> LinearROM:
        """The running model."""
        return self._rt.model

    @property
    def h(self) -> float:
        """Integration step in seconds (``'fixed'`` stepping)."""
        return self._rt.h

    @property
    def info(self) -> dict[str, Any]:
        """:func:`model_info` of the running model."""
        return dict(self._rt.info)

    def reload(self, model: LinearROM | str | os.PathLike[str],
               config: PredictorConfig | None = None, *,
               validate: Callable[[LinearROM], None] | None = None) -> None:
        """Swap in another model (and/or config) atomically.

        Everything (file, discretization, Kalman gain) is built first; on any failure the
        running model, state and config stay and the error propagates
        (:class:`FileNotFoundError`, :class:`~soft_rom.errors.ModelFileError`,
        :class:`~soft_rom.errors.ConfigError`, :class:`~soft_rom.errors.SolverError`).
        On success the state restarts (:meth:`reset`); held inputs are kept if the new
        model has the same number of inputs. ``validate(model)``, if given, may raise to
        refuse the new model before anything changes (e.g. the node checks its topics).
        """
        config = self.config if config is None else config
        path = None
        if not isinstance(model, LinearROM):
            path = model
            try:
                model = load_model(model)
            except (FileNotFoundError, ModelFileError):
                raise
            except (OSError, ValueError) as err:
                raise ModelFileError(f'{path}: cannot load model ({err}).') from err
        if validate is not None:
            validate(model)
        self._swap(_Runtime(model, config, path), config)

    def _swap(self, rt: _Runtime, config: PredictorConfig) -> None:
        old_u, old_stamp, old_arrival = self.u, self._stamp, self._arrival
        self._rt, self.config = rt, config
        self._init_buffers()
        if old_u.shape == self.u.shape:
            self.u[:] = old_u
            self._stamp[:] = old_stamp
            self._stamp_max = float(old_stamp.max())
            self._arrival[:] = old_arrival
        t = self.t
        self.reset()
        self._set_time(t)

    def set_config(self, config: PredictorConfig) -> None:
        """Change settings; atomic like :meth:`reload`.

        Changing only the monitor thresholds, metric or input timeout keeps the state;
        a new ``error_window`` clears the monitor; changing the stepping, rate or Kalman
        design rebuilds the discretization (:meth:`reload` of the running model, same file).
        """
        old = self.config
        rebuild = ('stepping', 'rate_hz', 'kalman', 'process_noise', 'measurement_noise')
        if any(getattr(old, k) != getattr(config, k) for k in rebuild):
            rt = _Runtime(self.model, config, None)
            rt.path, rt.sha256 = self._rt.path, self._rt.sha256
            rt.info = dict(self._rt.info)
            self._swap(rt, config)
            return
        self.config = config
        if config.error_window != old.error_window:
            self._clear_window(config.error_window)

    def reset(self) -> None:
        """Back to the initial state (reference, or next measurement); clears the monitor.

        Held inputs are kept; the model time restarts at the next update and the
        stamps-going-backwards check forgets earlier stamps (so a restarted clock, e.g. a
        bag played again, is accepted after a reset).
        """
        self.x[:] = 0.0
        self._set_time(None)
        self._clear_window(self.config.error_window)
        self._diverged = False
        self._awaiting_init = self.config.initial_state == 'measured'
        self._stamp[:] = -np.inf
        self._stamp_max = -math.inf
        self._update_Bu()

    def _update_Bu(self) -> None:
        np.dot(self._rt.B, self.u, out=self._Bu)

    # -- inputs --------------------------------------------------------------------------
    def _drop(self, counter: str, stamp: float | None, why: str) -> bool:
        self.counters[counter] += 1
        if stamp is not None and math.isfinite(stamp):
            self._last_drop = stamp
        elif self.t is not None:
            self._last_drop = self.t
        self._drop_reason = why
        return False

    def set_input(self, u: ArrayLike, stamp: float) -> bool:
        """Latch a whole input vector stamped ``stamp`` seconds; returns whether it was used.

        In ``'input'`` stepping the model first advances to ``stamp`` with the previous
        input held. See the module notes for the defined behaviour on bad inputs.
        """
        u = np.asarray(u, dtype=np.float64)
        m = self._rt.m
        if u.shape != (m,):
            return self._drop('wrong_length', stamp,
                              f'input of length {u.size}, expected {m}')
        if not (math.isfinite(u.sum()) and math.isfinite(stamp)):
            return self._drop('nonfinite', stamp, 'input with NaN/Inf')
        if stamp < self._stamp_max:
            if not self._clock_restarted(stamp):
                return self._drop('backwards', stamp, 'input stamp went backwards')
        self._before_input(stamp)
        self.u[:] = u
        self._stamp[:] = stamp
        self._stamp_max = stamp
        self._arrival[:] = stamp
        self.counters['inputs'] += 1
        self._update_Bu()
        return True

    def set_channel(self, index: int, value: float, stamp: float) -> bool:
        """Latch one input channel (per-chamber topics); returns whether it was used."""
        m = self._rt.m
        if not (isinstance(index, (int, np.integer)) and 0 <= index < m):
            return self._drop('wrong_length', stamp, f'input channel {index} not in 0..{m - 1}')
        value = float(value)
        if not (math.isfinite(value) and math.isfinite(stamp)):
            return self._drop('nonfinite', stamp, f'input {index} NaN/Inf')
        if stamp < self._stamp[index]:
            if not self._clock_restarted(stamp):
                return self._drop('backwards', stamp, f'input {index} stamp went backwards')
        self._before_input(stamp)
        self.u[index] = value
        self._stamp[index] = stamp
        self._stamp_max = max(self._stamp_max, stamp)
        self._arrival[index] = stamp
        self.counters['inputs'] += 1
        self._update_Bu()
        return True

    def _clock_restarted(self, stamp: float) -> bool:
        # A jump back by more than clock_reset_s is a restarted clock (bag played again,
        # simulation restarted): start over instead of dropping every later message.
        limit = self.config.clock_reset_s
        last = self._stamp_max
        if limit > 0 and stamp < last - limit:
            self.counters['clock_reset'] += 1
            self.reset()
            return True
        return False

    def _before_input(self, stamp: float) -> None:
        # The previous input is held up to ``stamp`` (whole steps in 'fixed' stepping).
        if self.t is None:
            self._set_time(float(stamp))
        elif stamp < self.t:
            self.counters['late'] += 1
        else:
            self.advance_to(stamp)

    # -- stepping ------------------------------------------------------------------------
    def step(self) -> None:
        """One integration step ``h`` with the held inputs (the hot path)."""
        np.dot(self._rt.A, self.x, out=self._xn)
        self._xn += self._Bu
        self.x, self._xn = self._xn, self.x
        self.counters['steps'] += 1
        if self.t is not None:
            self._k += 1
            self.t = self._t0 + self._k * self._rt.h

    def _set_time(self, t: float | None) -> None:
        # Model time is anchored (t0 + k h) so that long runs do not accumulate rounding.
        self.t = t
        self._t0 = 0.0 if t is None else t
        self._k = 0

    def advance_to(self, t: float) -> int:
        """Advance the model to time ``t`` (seconds) with held inputs; returns steps taken.

        ``'fixed'`` stepping takes every whole step ``h`` with ``t_model + h <= t``;
        ``'input'`` stepping integrates exactly to ``t`` (a discrete-time model: whole
        native steps, remainder carried). Times in the past do nothing.
        """
        if self.t is None:
            self._set_time(float(t))
            return 0
        rt = self._rt
        elapsed = t - self.t
        if not elapsed > 0:
            return 0
        if self.config.stepping == 'fixed' or rt.discrete:
            n = int(math.floor(elapsed / rt.h + 1e-9))
            if n > self.config.max_catchup_steps:
                skipped = n - self.config.max_catchup_steps
                self.counters['catchup_skipped'] += skipped
                self._set_time(self.t + skipped * rt.h)
                n = self.config.max_catchup_steps
            for _ in range(n):
                self.step()
            if n:
                self._check_state()
            return n
        A, B = rt.matrices_for(elapsed)
        self.x = A @ self.x + B @ self.u
        self._set_time(float(t))
        self.counters['steps'] += 1
        self._check_state()
        return 1

    def _check_state(self) -> None:
        if not math.isfinite(self.x.sum()):
            self.counters['diverged'] += 1
            self._diverged = True
            self.x[:] = 0.0

    # -- outputs -------------------------------------------------------------------------
    def output(self, out: Array | None = None) -> Array:
        """Predicted absolute output ``C x + D u + y_ref`` at the model time, shape (p,)."""
        rt = self._rt
        y = self._y if out is None else out
        np.dot(rt.C, self.x, out=y)
        if rt.has_D:
            y += rt.D @ self.u
        y += rt.y_ref
        return y if out is not None else y.copy()

    def measure(self, y: ArrayLike, stamp: float) -> float | None:
        """Compare a measured absolute output with the prediction at ``stamp``.

        The model is first advanced to ``stamp``. The error is taken before any
        correction; then the state is initialised from it (``initial_state='measured'``,
        first measurement after a reset) or corrected by the Kalman filter (``kalman``).

        Returns
        -------
        float or None
            The windowed relative error (the configured metric), or ``None`` if the
            measurement was dropped (wrong length or NaN/Inf: counted
            ``measured_dropped``).
        """
        y = np.asarray(y, dtype=np.float64)
        rt = self._rt
        if y.shape != (rt.p,) or not (math.isfinite(y.sum()) and math.isfinite(stamp)):
            self.counters['measured_dropped'] += 1
            return None
        self.advance_to(stamp)
        if self._awaiting_init:
            self.x[:] = self.model.state_from_output(y, self.u)
            self._awaiting_init = False
        yhat = self.output(self._y)
        np.subtract(y, yhat, out=self._dy)
        np.subtract(y, rt.y_ref, out=self._dev)
        self._push_window(float(self._dy @ self._dy), float(y @ y),
                          float(self._dev @ self._dev))
        if rt.L is not None:
            self.x += rt.L @ self._dy
        self.counters['measurements'] += 1
        return self.windowed_error()

    def _clear_window(self, w: int) -> None:
        # Ring buffers of |e|^2, |y|^2, |y - y_ref|^2 with running sums (recomputed exactly
        # each time the ring wraps, so rounding cannot accumulate).
        self._we, self._wy, self._wd = [0.0] * w, [0.0] * w, [0.0] * w
        self._se = self._sy = self._sd = 0.0
        self._win_n = 0
        self._win_i = 0

    def _push_window(self, e2: float, y2: float, d2: float) -> None:
        i = self._win_i
        self._se += e2 - self._we[i]
        self._sy += y2 - self._wy[i]
        self._sd += d2 - self._wd[i]
        self._we[i], self._wy[i], self._wd[i] = e2, y2, d2
        i += 1
        if i == len(self._we):
            i = 0
            self._se, self._sy, self._sd = sum(self._we), sum(self._wy), sum(self._wd)
        self._win_i = i
        if self._win_n < len(self._we):
            self._win_n += 1

    def windowed_errors(self) -> tuple[float, float]:
        """``(absolute, deviation)`` windowed relative errors (``nan`` before a measurement)."""
        if self._win_n == 0:
            return math.nan, math.nan
        se = max(self._se, 0.0)
        return (math.sqrt(se / max(self._sy, _TINY)), math.sqrt(se / max(self._sd, _TINY)))

    def windowed_error(self) -> float:
        """The windowed relative error chosen by ``error_metric``."""
        a, d = self.windowed_errors()
        return d if self.config.error_metric == 'deviation' else a

    # -- health --------------------------------------------------------------------------
    def health(self, now: float | None = None) -> Health:
        """Monitor state at time ``now`` (default the model time)."""
        cfg = self.config
        now = self.t if now is None else now
        reasons: list[tuple[Level, str]] = []
        ages = (now - self._arrival) if now is not None else np.full(self._rt.m, np.inf)
        names = self.model.input_names
        never = [names[i] for i in np.flatnonzero(~np.isfinite(self._arrival))]
        if never:
            reasons.append((Level.STALE, f'no value yet on input(s) {", ".join(never)} '
                                         '(holding 0)'))
        silent = [f'{names[i]} {ages[i]:.2f} s' for i in np.flatnonzero(
            np.isfinite(self._arrival) & (ages > cfg.input_timeout_s))]
        if silent:
            reasons.append((Level.STALE, f'input(s) silent: {", ".join(silent)} '
                                         f'(timeout {cfg.input_timeout_s:g} s; holding last '
                                         'value)'))
        if now is not None and now - self._last_drop <= cfg.input_timeout_s:
            reasons.append((Level.WARN, f'dropped messages (last: {self._drop_reason})'))
        if self._diverged:
            reasons.append((Level.ERROR, 'state diverged (non-finite); reset to reference'))
        err = self.windowed_error()
        if math.isfinite(err):
            if err > cfg.error_threshold:
                reasons.append((Level.ERROR, f'{cfg.error_metric} error {err:.3g} > '
                                             f'{cfg.error_threshold:g}'))
            elif err > cfg.warn_threshold:
                reasons.append((Level.WARN, f'{cfg.error_metric} error {err:.3g} > '
                                            f'{cfg.warn_threshold:g}'))
        level = max((lv for lv, _ in reasons), key=_SEVERITY.__getitem__, default=Level.OK)
        e_abs, e_dev = self.windowed_errors()
        values: dict[str, float | int | str] = {
            'error_absolute': e_abs,
            'error_deviation': e_dev,
            'window': self._win_n,
            'model_time': math.nan if self.t is None else self.t,
            'method': self.model.method,
            'r': self.model.r,
            'kalman': int(self._rt.L is not None),
        }
        values.update(self.counters)
        for i, name in enumerate(names):
            values[f'input_age.{name}'] = float(ages[i])
        text = '; '.join(msg for _, msg in reasons) or 'ok'
        return Health(level, text, tuple(msg for _, msg in reasons), values)


# -- offline use ----------------------------------------------------------------------------
@dataclass(frozen=True)
class ReplayResult:
    """Predictions of a :class:`Predictor` run over an episode.

    Attributes
    ----------
    t : ndarray, shape (k,)
    Y : ndarray, shape (p, k)
        Predicted absolute outputs (before any Kalman correction at each sample).
    errors : ndarray, shape (k,)
        Windowed relative error after each sample (``nan`` without measurements).
    levels : ndarray of int, shape (k,), or None
        Health level after each sample (only with ``track_health``).
    summary : dict
        ``relative_error`` and ``relative_deviation_error`` over the whole episode
        (``nan`` without measurements), counters, config.
    """

    t: Array
    Y: Array
    errors: Array
    levels: NDArray[np.int64] | None
    summary: dict[str, Any]


def replay_episode(predictor: Predictor, episode: Episode, *, measured: bool = True,
                   callback: Any = None, track_health: bool = False) -> ReplayResult:
    """Run ``predictor`` over an episode's inputs (and measured outputs), sample by sample.

    For each sample ``j``: advance to ``t_j``, latch ``U[:, j]``, predict ``ŷ_j``, then
    (``measured``) hand ``Y[:, j]`` to :meth:`Predictor.measure`. With uniform samples at
    the model's ``dt`` and no Kalman filter this equals ``model.simulate(U)``.

    Parameters
    ----------
    predictor : Predictor
        Used as is (call :meth:`Predictor.reset` first for a fresh run).
    episode : Episode
    measured : bool
        Feed the episode's outputs as measurements.
    callback : callable, optional
        ``callback(j, t_j, yhat_j, predictor)`` after each sample (e.g. to write messages).
    track_health : bool
        Record :meth:`Predictor.health` level after each sample (costs ~50 µs a sample).
    """
    t = np.asarray(episode.t, dtype=np.float64)
    U = as_signal('U', episode.U, rows=predictor.model.n_inputs)
    Y = as_signal('Y', episode.Y, cols=t.size)
    p = predictor.model.n_outputs
    if measured and Y.shape[0] != p:
        raise DimensionError(f'episode {episode.name!r} has {Y.shape[0]} outputs; the model '
                             f'predicts {p}. Check the output mapping/components.')
    k = t.size
    Yhat = np.empty((p, k))
    errors = np.full(k, np.nan)
    levels = np.zeros(k, dtype=np.int64) if track_health else None
    ybuf = np.empty(p)
    Ut = np.ascontiguousarray(U.T)          # one contiguous row per sample
    Yt = np.ascontiguousarray(Y.T) if measured else None
    for j, tj in enumerate(t.tolist()):
        predictor.advance_to(tj)
        predictor.set_input(Ut[j], tj)
        Yhat[:, j] = predictor.output(ybuf)
        if Yt is not None:
            e = predictor.measure(Yt[j], tj)
            errors[j] = math.nan if e is None else e
        if levels is not None:
            levels[j] = int(predictor.health(tj).level)
        if callback is not None:
            callback(j, tj, Yhat[:, j], predictor)
    summary: dict[str, Any] = {
        'episode': episode.name,
        'samples': k,
        'relative_error': math.nan,
        'relative_deviation_error': math.nan,
        'counters': dict(predictor.counters),
        'config': asdict(predictor.config),
        'model': predictor.info,
    }
    if measured:
        E = Y - Yhat
        D = Y - predictor.model.y_ref[:, None]
        summary['relative_error'] = float(np.linalg.norm(E) / max(np.linalg.norm(Y), 1e-300))
        summary['relative_deviation_error'] = float(
            np.linalg.norm(E) / max(np.linalg.norm(D), 1e-300))
    return ReplayResult(t, Yhat, errors, levels, summary)


def kalman_vs_open_loop(model: LinearROM, episode: Episode, *,
                        config: PredictorConfig | None = None,
                        Y_true: ArrayLike | None = None) -> dict[str, float]:
    """Prediction errors of ``model`` on ``episode`` open loop and with the Kalman filter.

    Both runs see the episode's (possibly noisy) outputs as measurements; errors are
    measured against ``Y_true`` (default the episode's outputs) with the prediction taken
    *before* each correction, so the Kalman figure is an honest one-step-ahead error.

    Returns
    -------
    dict
        ``open_loop`` and ``kalman`` relative errors on deviations, ``open_loop_abs`` and
        ``kalman_abs`` absolute relative errors, and ``ratio`` = kalman / open_loop.
    """
    base = PredictorConfig() if config is None else config
    Yt = as_signal('Y_true', episode.Y if Y_true is None else Y_true)
    D = np.linalg.norm(Yt - model.y_ref[:, None])
    N = np.linalg.norm(Yt)
    out: dict[str, float] = {}
    for key, kal in (('open_loop', False), ('kalman', True)):
        cfg = base.replace(kalman=kal, stepping='fixed', rate_hz=0.0)
        res = replay_episode(Predictor(model, cfg), episode, measured=True)
        err = np.linalg.norm(Yt - res.Y)
        out[key] = float(err / max(D, 1e-300))
        out[f'{key}_abs'] = float(err / max(N, 1e-300))
    out['ratio'] = out['kalman'] / out['open_loop'] if out['open_loop'] > 0 else math.nan
    return out

