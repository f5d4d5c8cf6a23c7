"""The controller core: estimator + MPC + reference, with the safety rules of the node.

:class:`Controller` is what both the in-process closed loop (:mod:`soft_rom.control.loop`)
and the ROS node (``ros2 run soft_rom controller``) run. It never raises on bad data and
never returns a command outside the bounds or not finite:

* a measurement of the wrong size, with NaN/Inf, or older than the last one is dropped
  (counted, with the reason);
* a reference of the wrong size, with NaN/Inf, ending before the current time, or moving
  at or above the control step's Nyquist rate is refused; the one in force stays; a static
  target out of the model's reach within the bounds is taken, with a
  :class:`~soft_rom.errors.ReferenceReachWarning` (once per target), and so does a
  reference faster than the training data's outputs moved (``envelope.y_band_hz``);
* without a measurement yet (``missing``), or with none for ``stale_after`` seconds
  (``stale``), the last command is held (clipped into the bounds); with an external state
  estimate (``external_state``, the predictor node's ``~/state``) the same holds for it;
* an infeasible or failed QP holds the last command (clipped into the bounds);
* a step time that is not finite, earlier than the last step's, or more than
  ``stale_after`` before the last measurement (``bad_time``: two clocks?) holds the last
  command; a step or measurement more than ``clock_reset`` before the last one is a
  restarted clock (a simulation started again): the controller starts a new run;
* steps closer together than the control step move the command by at most the rate bound
  times the time since the last step.

A measurement is a vector in the model's output order: an array of another shape (a
``(points, components)`` centerline) or farther from the rest output than 100 times the
training data's largest deviation (the predictor's output envelope; wrong units) is
dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.control.estimator import EstimatorConfig, OffsetFreeEstimator
from soft_rom.control.mpc import MPC, MPCConfig
from soft_rom.control.reference import (
    reach_miss,
    REACH_TOLERANCE,
    Reference,
    sampling_problem,
    training_band,
)
from soft_rom.envelope import BAND_SHARE
from soft_rom.errors import DimensionError, ReferenceReachWarning, warn

__all__ = ['Command', 'Controller']

#: A measurement farther than this many times the training data's largest output deviation
#: from the rest output is dropped (the predictor's default output envelope).
MEASUREMENT_FACTOR = 100.0

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Command:
    """One control step's result.

    Attributes
    ----------
    u : ndarray, shape (m,)
        The command (finite, within the bounds).
    status : str
        ``'ok'``, ``'missing'`` (no measurement yet), ``'stale'``, ``'no_reference'``,
        ``'bad_time'`` (the step time: not finite, going back, or before the measurements),
        ``'infeasible'`` or ``'failed'`` (QP).
    solve_s : float
        QP solve wall time (0 when none ran).
    step_s : float
        Whole control step wall time (estimate, reference, solve).
    step_cpu_s : float
        The same in thread CPU time (what the step costs, without preemption by other
        processes on a loaded machine).
    saturated : int
        Inputs at a bound.
    tracking_error : float
        ``||y_est - r|| / sqrt(p)`` at the step (RMS over outputs, output units; NaN
        without a reference).
    detail : str
    """

    u: Array
    status: str
    solve_s: float = 0.0
    step_s: float = 0.0
    step_cpu_s: float = 0.0
    saturated: int = 0
    tracking_error: float = float('nan')
    detail: str = ''


@dataclass
class _Counters:
    measurements: int = 0
    measurements_dropped: int = 0
    states_dropped: int = 0
    references_refused: int = 0
    steps: int = 0
    qp_failed: int = 0
    qp_infeasible: int = 0
    held: int = 0
    clock_resets: int = 0
    last_problem: str = ''
    last_dropped: str = ''      # the last measurement, state or reference dropped, and why
    by_status: dict[str, int] = field(default_factory=dict)


class Controller:
    """MPC with an offset-free estimator on a linear ROM.

    Parameters
    ----------
    model : LinearROM
    mpc : MPCConfig, optional
    estimator : EstimatorConfig, optional
    stale_after : float
        Seconds without a measurement after which the command is held (default 0.1 s).
    external_state : bool
        The ROM state comes from outside (:meth:`set_state`: the predictor node running the
        model on the applied commands); the measurements then correct the disturbance
        only, which is the offset-free estimator with state noise 0 (internal model
        control). The state is carried to each control time on the commands applied since.
    clock_reset : float
        A step or measurement time this many seconds before the last one starts a new run
        (:meth:`start`; default 1 s, the predictor's ``clock_reset_s``).
    """

    def __init__(self, model: Any, mpc: MPCConfig | None = None,
                 estimator: EstimatorConfig | None = None, *, stale_after: float = 0.1,
                 external_state: bool = False, clock_reset: float = 1.0) -> None:
        self.model = model
        self.external_state = bool(external_state)
        self.state: tuple[float, Array] | None = None
        self._history: list[tuple[float, Array]] = []
        self.mpc = MPC(model, mpc)
        self.estimator = OffsetFreeEstimator(model, estimator)
        self.stale_after = float(stale_after)
        if not (math.isfinite(self.stale_after) and self.stale_after > 0):
            raise ValueError(f'stale_after must be a positive number of seconds; got '
                             f'{stale_after!r}.')
        self.clock_reset = float(clock_reset)
        if not (self.clock_reset > 0):
            raise ValueError(f'clock_reset must be a positive number of seconds; got '
                             f'{clock_reset!r}.')
        self.reference: Reference | None = None
        self.u = self.mpc.fallback(np.zeros(self.mpc.m))
        self.t_measured: float | None = None
        self.t_step: float | None = None
        self.started = False
        self.counters = _Counters()
        self._y_bound = MEASUREMENT_FACTOR * self.mpc.y_scale
        self._reach_checked: Array | None = None      # the static target last checked
        self._band_checked: float | None = None        # the reference frequency last checked
        self._stable: bool | None = None               # the model at the step (reach checks)

    @property
    def h(self) -> float:
        """Control step (s)."""
        return self.mpc.h

    def start(self, t: float) -> None:
        """Start a run at time ``t``: the estimator at rest with the current command held.

        The measurements, state estimate and command times of an earlier run are forgotten
        (its clock may have started again from 0); the reference and command stay.
        """
        self.estimator.reset(t, self.u)
        self.t_measured = self.t_step = self.state = None
        self._history.clear()
        self.started = True

    # -- inputs -------------------------------------------------------------------------
    def set_reference(self, ref: Reference, now: float | None = None) -> str:
        """Use ``ref`` from now on; returns ``''`` or why it was refused (the old one stays)."""
        why = self.check_reference(ref, now)
        if why:
            self.counters.references_refused += 1
            return self.refused('reference refused', why)
        self.reference = ref
        return ''

    def check_reference(self, ref: Reference, now: float | None = None) -> str:
        """Why :meth:`set_reference` would refuse ``ref``, or ``''``; nothing is changed.

        A static target out of the model's reach within the input bounds is not refused:
        it gives a :class:`~soft_rom.errors.ReferenceReachWarning` (once per target).
        """
        why = ''
        if not isinstance(ref, Reference):
            why = (f'not a Reference but {type(ref).__name__} (parse a text with '
                   'soft_rom.control.parse_reference)')
        elif ref.n_outputs != self.mpc.p:
            why = f'reference has {ref.n_outputs} outputs; the model has {self.mpc.p}'
        elif not (np.all(np.isfinite(ref.Y)) and np.all(np.isfinite(ref.t))):
            why = 'reference has NaN/Inf'
        elif now is not None and ref.t[-1] < now and ref.t.size > 1:
            why = f'reference ends at {ref.t[-1]:.3f} s, before now ({now:.3f} s)'
        else:
            why = sampling_problem(ref, self.h)
        if not why:
            self._check_reach(ref)
            self._check_band(ref)
        return why

    def _check_band(self, ref: Reference) -> None:
        """Warn (once per frequency) when ``ref`` moves faster than the training data did."""
        f, band = ref.frequency, training_band(self.model)
        if f is None or band is None or not f > band or f == self._band_checked:
            return
        self._band_checked = f
        warn(f'the reference {ref.label or "given"!r} moves at {f:g} Hz, faster than the '
             f"model's training data: {100 * BAND_SHARE:g} % of their output motion lies "
             f'below {band:.3g} Hz. The model was not fitted there; expect its error at '
             f'{f:g} Hz to be larger than on the training data.', ReferenceReachWarning)

    def _check_reach(self, ref: Reference) -> None:
        """Warn (once per static target) when the model cannot reach it within the bounds.

        Not for an unstable model: it has no steady state to reach (and is not trusted).
        """
        target = ref.Y[:, -1]
        if self._reach_checked is not None and np.array_equal(target, self._reach_checked):
            return
        self._reach_checked = target.copy()
        if self._stable is None:
            eig = np.linalg.eigvals(self.mpc.system.A)
            self._stable = bool(np.all(np.isfinite(eig)) and np.max(np.abs(eig), initial=0.0)
                                < 1.0 - 1e-9)
        if not self._stable:
            return
        miss = reach_miss(ref, self.mpc.steady_gain(), self.mpc.lo, self.mpc.hi,
                          self.estimator.y_ref)
        if miss is not None and miss[2] > REACH_TOLERANCE:
            warn(f'the reference {ref.label or "given"!r} is out of reach within the input '
                 "bounds: the model's best steady state within them misses its static target "
                 f'by {100 * miss[0]:.0f} % of the commanded deviation ({100 * miss[1]:.0f} % '
                 'with unbounded inputs); the inputs will sit at their bounds short of it.',
                 ReferenceReachWarning)

    def refused(self, kind: str, why: str) -> str:
        """Record an input refused (``kind``: ``'measurement dropped'``...) for ``why``.

        ``counters.last_problem`` (which a held command overwrites at every step) and
        ``counters.last_dropped`` (``'<kind>: <why>'``, kept until the next one); returns
        ``why``. The counts are the caller's.
        """
        self.counters.last_problem = why
        self.counters.last_dropped = f'{kind}: {why}'
        return why

    def measure(self, y: ArrayLike, t: float) -> str:
        """A measured absolute output at time ``t``; returns ``''`` or why it was dropped."""
        why = ''
        try:
            y = np.asarray(y, dtype=np.float64)
        except (TypeError, ValueError):
            y = np.zeros(0)
        shape = y.shape
        if y.ndim == 2 and 1 in shape:       # a row or column vector
            y = y.reshape(-1)
        if y.shape != (self.mpc.p,):
            why = (f'measurement of shape {shape}; the model has {self.mpc.p} outputs '
                   '(one vector in its output order)')
        elif not np.all(np.isfinite(y)):
            why = f'measurement with {int(np.count_nonzero(~np.isfinite(y)))} NaN/Inf value(s)'
        elif (dev := float(np.max(np.abs(y - self.estimator.y_ref)))) > self._y_bound:
            why = (f'measurement {dev:.3g} from the rest output, more than {MEASUREMENT_FACTOR:g}'
                   f" x the training data's largest deviation ({self.mpc.y_scale:.3g}): wrong "
                   'units?')
        elif not math.isfinite(t):
            why = 'measurement time not finite'
        elif self.t_measured is not None and self.t_measured - self.clock_reset <= t <= \
                self.t_measured:
            why = f'measurement at {t:.4f} s is not newer than the last ({self.t_measured:.4f} s)'
        if why:
            self.counters.measurements_dropped += 1
            return self.refused('measurement dropped', why)
        if not self.started or self._restarted(self.t_measured, t):
            self.start(t)
        try:
            self.estimator.predict_to(t)
        except DimensionError as e:          # an unstable model carried over a long gap
            self.counters.measurements_dropped += 1
            return self.refused('measurement dropped', f'measurement at {t:.4f} s: {e}')
        self.estimator.correct(y)
        self.t_measured = t
        self.counters.measurements += 1
        return ''

    def set_state(self, x: ArrayLike, t: float) -> str:
        """An external state estimate at time ``t``; returns ``''`` or why it was dropped."""
        why = ''
        try:
            x = np.asarray(x, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            x = np.zeros(0)
        if x.shape != (self.mpc.n,):
            why = f'state of {x.size} values; the model has {self.mpc.n} states'
        elif not np.all(np.isfinite(x)):
            why = 'state with NaN/Inf'
        elif not math.isfinite(t):
            why = 'state time not finite'
        elif self.state is not None and t < self.state[0]:
            why = f'state at {t:.4f} s is older than the last ({self.state[0]:.4f} s)'
        if why:
            self.counters.states_dropped += 1
            return self.refused('state dropped', why)
        self.state = (float(t), x.copy())
        return ''

    def _carry_state(self, t: float) -> None:
        """The external state carried to ``t`` on the commands applied since its time."""
        if self.state is None:
            return
        ts, x = self.state
        est = self.estimator
        u = self._history[0][1] if self._history else self.u
        later = []
        for tc, uc in self._history:
            if tc <= ts + 1e-9:
                u = uc
            else:
                later.append((tc, uc))
        est.x, est.t, est.u = x.copy(), ts, u.copy()
        for tc, uc in later:
            if tc > t:
                break
            est.predict_to(tc)
            est.u = uc.copy()
        est.predict_to(t)

    # -- the control step ---------------------------------------------------------------
    def _restarted(self, last: float | None, t: float) -> bool:
        """Whether ``t`` is more than ``clock_reset`` before ``last`` (counted)."""
        if last is None or not t < last - self.clock_reset:
            return False
        self.counters.clock_resets += 1
        return True

    def _hold_reason(self, t: float) -> tuple[str, str]:
        """``(status, detail)`` of a step at ``t`` that holds the command, else ``('ok', '')``."""
        if not math.isfinite(t):
            return 'bad_time', f'step time {t!r} is not finite: command held'
        if self.t_step is not None and t < self.t_step - 1e-9:
            return 'bad_time', (f'step at {t:.4f} s is before the last one ({self.t_step:.4f} '
                                's): command held')
        if self.t_measured is None:
            return 'missing', 'no measurement yet: command held'
        if self.t_measured - t > self.stale_after:
            return 'bad_time', (f'the last measurement is stamped {self.t_measured:.4f} s, '
                                f'after the step at {t:.4f} s (two clocks?): command held')
        if t - self.t_measured > self.stale_after:
            return 'stale', (f'last measurement {t - self.t_measured:.3f} s old '
                             f'(> {self.stale_after:g} s): command held')
        if self.external_state and self.state is None:
            return 'missing', 'no state estimate yet: command held'
        if self.external_state and self.state is not None and \
                t - self.state[0] > self.stale_after:
            return 'stale', (f'state estimate {t - self.state[0]:.3f} s old '
                             f'(> {self.stale_after:g} s): command held')
        if self.reference is None:
            return 'no_reference', 'no reference: command held'
        return 'ok', ''

    def _solve(self, t: float, ref: Reference) -> tuple[str, str, Array, float, int, float]:
        """The MPC at ``t``: status, detail, command, solve time, saturated, tracking error."""
        est = self.estimator
        if self.external_state:
            self._carry_state(t)
        est.predict_to(t)
        times = t + self.h * np.arange(1, self.mpc.N + 1)
        R = ref.at(times)
        err = float(np.linalg.norm(est.output() - ref.at([t])[:, 0]) / math.sqrt(self.mpc.p))
        try:
            res = self.mpc.solve(est.x, est.d, R, self.u)
        except DimensionError as e:       # cannot happen with checked inputs; be safe
            return 'failed', str(e), self.mpc.fallback(self.u), 0.0, 0, err
        if not res.qp.ok:
            status = res.qp.status if res.qp.status == 'infeasible' else 'failed'
            return (status, f'QP {res.qp.status} ({res.qp.detail}): command held', res.u,
                    res.qp.seconds, res.saturated, err)
        return 'ok', '', res.u, res.qp.seconds, res.saturated, err

    def step(self, t: float) -> Command:
        """The command to apply from time ``t`` for one control step."""
        t0 = time.perf_counter()
        c0 = time.thread_time()
        self.counters.steps += 1
        t = float(t)
        if math.isfinite(t) and self._restarted(self.t_step, t):
            self.start(t)
        status, detail = self._hold_reason(t)
        solve_s, sat, err = 0.0, 0, float('nan')
        if status != 'ok' or self.reference is None:
            u = self.mpc.fallback(self.u)
        else:
            status, detail, u, solve_s, sat, err = self._solve(t, self.reference)
        if not np.all(np.isfinite(u)):         # belt and braces: never a NaN command
            u = self.mpc.centre.copy()
        u = np.clip(u, self.mpc.lo, self.mpc.hi)
        if self.t_step is not None and status != 'bad_time' and \
                t - self.t_step < self.h * (1 - 1e-6):
            # steps closer than h: the rate bound (per second) over the time since the last
            limit = self.mpc.rate * max(t - self.t_step, 0.0) / self.h
            u = np.clip(u, self.u - limit, self.u + limit)
        if status in ('failed', 'infeasible'):
            setattr(self.counters, f'qp_{status}', getattr(self.counters, f'qp_{status}') + 1)
        if status != 'ok':
            self.counters.held += 1
            self.counters.last_problem = detail
        self.counters.by_status[status] = self.counters.by_status.get(status, 0) + 1
        self.u = u
        if status != 'bad_time':
            self.t_step = t
            self._history.append((t, u.copy()))
            del self._history[:-64]
            if self.started:
                self.estimator.predict_to(t)
                self.estimator.set_input(u)
        return Command(u=u.copy(), status=status, solve_s=solve_s,
                       step_s=time.perf_counter() - t0, step_cpu_s=time.thread_time() - c0,
                       saturated=sat, tracking_error=err,
                       detail=detail)
