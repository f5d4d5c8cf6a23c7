"""The ROS-free real-time predictor: a model, its state, held inputs, envelopes and a monitor.

Time
----
Every time is an ``int`` of nanoseconds inside (``*_ns`` methods); the float-second methods
convert with ``round(t * 1e9)``. Model time is anchored, ``t_k = origin + k h`` in integer
nanoseconds (``h`` a whole number of ns; else rounded per step from the anchor), so no
epoch (stamps near 1.7e18 ns) loses or gains a step. Non-finite times, and times outside
``±2**62`` ns, are refused (counted ``bad_time``): nothing freezes, nothing raises.

Stepping (:attr:`PredictorConfig.stepping`)
-------------------------------------------
``'event'`` (default): steps of ``h`` on a grid anchored at the first stamp; a stamp
belongs to the nearest grid step (so stamp jitter up to ``h/2`` around the grid of the
first input does not move a sample). Inputs are queued and the model
advances to the *watermark* -- the smallest over inputs of their newest step -- and never
past it, so inputs arriving in any order across inputs whose step is not yet taken are
applied at their stamp: the outputs equal ``model.simulate(U)``. Each input's own messages
are assumed in stamp order (a ROS topic delivers a publisher's messages in order); an
older stamp of the same input is still applied at its step if that step is not taken.
An input whose newest stamp trails the newest stamp of all inputs by more than
``input_timeout_s`` stops holding the model back (value held, ``STALE``, counted
``timeouts``); ``max_lag_s`` caps how far the model trails
the newest stamp (counted ``lag_forced``). Measurements are compared with the prediction
at their own step once the model has reached it (the last 512 steps are kept for
measurements that arrive after the model passed their step).
Inputs for a step already taken are applied from the current step on (``late``).

``'fixed'``: a clock drives the model (:meth:`Predictor.advance_to_ns` takes every whole
step due); inputs are latched on arrival. ``'input'``: each input first advances the model
exactly to its stamp (a discrete-time model: whole native steps, remainder carried).

Bad values (each counted in :attr:`Predictor.counters`)
-------------------------------------------------------
* wrong length / channel: ``wrong_length``; NaN/Inf value: ``nonfinite``; bad time:
  ``bad_time`` -- dropped, held value stays;
* outside the input envelope (:class:`~soft_rom.predictor.envelope.Envelopes`): clipped
  (``input_clipped``) or dropped (``input_out_of_envelope``), ``WARN``;
* stamp older than the channel's newest whose step is taken: ``backwards`` (dropped); older
  than the newest stamp by more than ``clock_reset_s``: a restarted clock, ``clock_reset``
  (so is, with ``'fixed'`` stepping, a clock passed to :meth:`Predictor.advance_to_ns` that
  went back by more than ``clock_reset_s``): the predictor resets, model time starts over
  at that time and :attr:`Predictor.restarts` counts up (the runtime loop re-anchors its
  publish schedule on it);
* a prediction outside the output envelope or non-finite: ``diverged``, ``ERROR``, state
  reset to the reference when ``auto_reset``;
* more than ``max_catchup_steps`` due at once (clock stall or jump): ``catchup_skipped``
  steps skipped, ``clock_jump`` counted, ``WARN``;
* measurements with a bad time, of wrong size, non-finite (one NaN, e.g. an occluded
  marker, drops the whole measurement), outside the output envelope, too old for the
  history, or stamped more than ``clock_reset_s`` ahead of the model time (a clock the
  model will not reach soon; ``0``: no horizon): ``measured_dropped``; all but the
  too-old ones with the reason (``WARN``). At most :data:`MAX_QUEUED_MEASUREMENTS`
  measurements wait for their step (``'event'``); one more is dropped the same way.

With ``kalman=True`` a measurement at the current step corrects the state with a
steady-state Kalman gain designed on the discretized model.
"""

from __future__ import annotations

from collections.abc import Callable
import math
import os
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.errors import ModelFileError
from soft_rom.models import load_model
from soft_rom.predictor.channels import ChannelStats
from soft_rom.predictor.config import Health, Level, PredictorConfig, REBUILD_FIELDS, SEVERITY
from soft_rom.predictor.dynamics import Dynamics
from soft_rom.predictor.envelope import Envelopes
from soft_rom.predictor.health import assess
from soft_rom.predictor.measuring import _finite, MAX_QUEUED_MEASUREMENTS, Measuring
from soft_rom.predictor.monitor import ErrorMonitor
from soft_rom.predictor.stepping import _HISTORY, _ok_ns, time_problem, to_ns
from soft_rom.predictor.thresholds import Thresholds

__all__ = ['COUNTERS', 'MAX_QUEUED_MEASUREMENTS', 'Predictor', 'to_ns']

Array = NDArray[np.float64]

COUNTERS = ('wrong_length', 'nonfinite', 'bad_time', 'backwards', 'clock_reset', 'late',
            'timeouts', 'lag_forced', 'input_clipped', 'input_out_of_envelope', 'input_ahead',
            'measured_dropped', 'diverged', 'clock_jump', 'catchup_skipped', 'steps',
            'inputs', 'measurements')
_NONE = -(2 ** 63)

class Predictor(Measuring):
    """A ROM running in real time: held inputs, state, envelopes, monitor, optional Kalman.

    Parameters
    ----------
    model : LinearROM, a model of the predictor protocol, or path
        See :mod:`soft_rom.predictor.dynamics`.
    config : PredictorConfig, optional

    Attributes
    ----------
    x : ndarray, shape (n_states,)
        State (deviation from the reference) at :attr:`t_ns`.
    u : ndarray, shape (m,)
        Held absolute inputs (after the envelope).
    counters : dict of str to int
    channels : ChannelStats
        Per-input figures (received, late, dropped, clipped, newest stamp, timed out).
    emit_outputs : bool
        Record ``(t_ns, y)`` of every completed step for :meth:`take_emitted` (the runtime
        loop sets it).
    restarts : int
        Counts every :meth:`reset` (a restarted clock, ``reset()``, a reload): model time
        starts over, possibly earlier than before. Whoever schedules on model time (the
        runtime loop) compares it with the value it last saw and re-anchors.

    Notes
    -----
    Not thread-safe: calls that feed or move it (inputs, measurements, ``advance_to*``,
    ``step``, ``reset``, ``reload``, ``set_config``) must come from one thread at a time
    (hold a lock of your own around them). Reading from another thread does not disturb
    the one that steps it: each step binds a new state array that is never written again
    (a reference to :attr:`x` stays the state of its step), and :meth:`output` without
    ``out`` returns a new array computed from the state alone. For a state, input and
    time that belong together, read them under the same lock.
    """

    def __init__(self, model: Any, config: PredictorConfig | None = None) -> None:
        self.config = PredictorConfig() if config is None else config
        path = None
        if isinstance(model, (str, os.PathLike)):
            path = model
            model = load_model(model)
        self._dyn = Dynamics(model, self.config, path)
        self._env = Envelopes(model, self.config)
        self.thresholds = Thresholds(model, self.config)
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.emit_outputs = False
        self._emitted: list[tuple[int, Array]] = []
        self.restarts = 0
        self._init_buffers()
        self._restart()

    # -- construction / reload -----------------------------------------------------------
    def _init_buffers(self) -> None:
        d = self._dyn
        self.x = d.initial_state()
        self.u = np.zeros(d.m)
        self._Bu = np.zeros(d.n)
        self._y = np.zeros(d.p)
        self._dy = np.zeros(d.p)
        self._dev = np.zeros(d.p)
        self.channels = ChannelStats(list(self.model.input_names))
        slack = self._env.y_bound - float(np.linalg.norm(self._dyn.y_ref))
        self._fast2 = slack * slack if slack > 0 else -1.0
        self._hist = np.zeros((_HISTORY, d.p))
        self._hist_k = np.full(_HISTORY, _NONE, dtype=np.int64)
        self._monitor = ErrorMonitor(self.config.error_window,
                                     int(self.config.error_window_s * 1e9))
        self._alarms: dict[str, tuple[int, str]] = {}
        self._diverged_latched = False
        self.totals = [0.0, 0.0, 0.0]     # sums of |y - y_hat|^2, |y|^2, |y - y_ref|^2

    @property
    def model(self) -> Any:
        """The running model."""
        return self._dyn.model

    @property
    def h(self) -> float:
        """Step in seconds."""
        return self._dyn.h

    @property
    def info(self) -> dict[str, Any]:
        """Model description (``~/model_info``) with the envelopes and the correction in force."""
        info = dict(self._dyn.info)
        info['envelope'] = self._env.summary()
        info['monitor'] = self.thresholds.summary()
        info['kalman'] = bool(self.config.kalman)
        return info

    @property
    def envelopes(self) -> Envelopes:
        """The input and output bounds in force."""
        return self._env

    @property
    def t_ns(self) -> int | None:
        """Model time in int nanoseconds (``None`` before the first update)."""
        return None if self._k is None else self._time_of(self._k)

    def _time_of(self, k: int) -> int:
        d = self._dyn
        if d.h_ns_int:
            return self._origin + k * d.h_ns_int
        return self._origin + int(round(k * d.h_ns))

    @property
    def t(self) -> float | None:
        """Model time in float seconds (derived from :attr:`t_ns`)."""
        t = self.t_ns
        return None if t is None else t * 1e-9

    def reload(self, model: Any, config: PredictorConfig | None = None, *,
               validate: Callable[[Any], None] | None = None) -> None:
        """Swap in another model (and/or config) atomically.

        Everything (file, discretization, Kalman gain, envelopes) is built first; on any
        failure the running model, state and config stay and the error propagates. On
        success the state restarts at the model time; held inputs are kept if the new model
        has the same number of inputs. ``validate(model)`` may raise to refuse it first.
        """
        config = self.config if config is None else config
        path = None
        if isinstance(model, (str, os.PathLike)):
            path = model
            try:
                model = load_model(model)
            except (FileNotFoundError, ModelFileError):
                raise
            except (OSError, ValueError) as err:
                raise ModelFileError(f'{path}: cannot load model ({err}).') from err
        if validate is not None:
            validate(model)
        self._swap(Dynamics(model, config, path), Envelopes(model, config), config)

    def _swap(self, dyn: Dynamics, env: Envelopes, config: PredictorConfig) -> None:
        old_u, old_ch = self.u, self.channels
        t = self.t_ns
        self._dyn, self._env, self.config = dyn, env, config
        self.thresholds = Thresholds(dyn.model, config)
        self._init_buffers()
        if old_u.shape == self.u.shape:
            self.u[:] = old_u
            self.channels.take_over(old_ch)
        self._restart()
        if t is not None:
            self._anchor(t)
            self._done = self._released = True

    def set_config(self, config: PredictorConfig) -> None:
        """Change settings; atomic like :meth:`reload`.

        Monitor thresholds, metric, timeouts and lag apply at once (state kept); a new
        ``error_window`` / ``error_window_s`` clears the monitor; stepping, rate, Kalman
        design or envelopes rebuild the discretization (the running model, same file).
        """
        old = self.config
        if any(getattr(old, k) != getattr(config, k) for k in REBUILD_FIELDS):
            dyn = Dynamics(self.model, config, None)
            dyn.path, dyn.sha256 = self._dyn.path, self._dyn.sha256
            dyn.info = dict(self._dyn.info)
            self._swap(dyn, Envelopes(self.model, config), config)
            return
        self.config = config
        self.thresholds = Thresholds(self.model, config)
        if (config.error_window, config.error_window_s) != (old.error_window,
                                                            old.error_window_s):
            self._monitor = ErrorMonitor(config.error_window, int(config.error_window_s * 1e9))

    def reset(self) -> None:
        """Back to the initial state; clears the monitor, queue, stamp history and alarms.

        :meth:`health` starts afresh (the alarms before a reset no longer show). Held inputs
        are kept; the model time restarts at the next input (so a restarted clock, e.g. a
        bag played again, is accepted after a reset).
        """
        self._restart()
        self._alarms.clear()

    def _restart(self) -> None:
        """:meth:`reset` keeping the alarms (a reload, a restarted clock: they still hold)."""
        self.x = self._dyn.initial_state()
        self._k: int | None = None
        self._origin = 0
        self._done = False
        self._released = False
        self._queue: list[tuple[int, int, int, int, Any]] = []
        self._queued_measurements = 0
        self._seq = 0
        self.restarts += 1
        self._monitor.clear()
        self._diverged_latched = False
        self._alarms.pop('diverged', None)
        self._awaiting_init = self.config.initial_state == 'measured'
        self.channels.forget_stamps()
        self._newest = _NONE
        self._first = _NONE
        self._exact_cache: dict[int, Any] = {}
        self._update_Bu()

    def _update_Bu(self) -> None:
        if self._dyn.linear:
            np.dot(self._dyn.B, self.u, out=self._Bu)

    # -- time ----------------------------------------------------------------------------
    def _step_of(self, t_ns: int) -> int:
        d = self._dyn
        if d.h_ns_int:
            return (t_ns - self._origin + d.h_ns_int // 2) // d.h_ns_int
        return int(round((t_ns - self._origin) / d.h_ns))

    def _anchor(self, t_ns: int) -> None:
        """Model time starts at ``t_ns``: the step grid is ``t_ns + k h``."""
        self._origin, self._k = t_ns, 0

    def _alarm(self, key: str, t_ns: int | None, why: str) -> None:
        """Remember a WARN/ERROR event at ``t_ns`` (default the newest known time)."""
        when = self.stamp_now() if t_ns is None else t_ns
        self._alarms[key] = (_NONE if when is None else when), why

    def _bad_time(self, what: str, t_ns: Any = None) -> bool:
        self.counters['bad_time'] += 1
        self._alarm('dropped', None, f'{what}: {time_problem(t_ns)}')
        return False

    # -- inputs --------------------------------------------------------------------------
    def set_input(self, u: ArrayLike, stamp: float) -> bool:
        """:meth:`set_input_ns` with the stamp in float seconds."""
        t = to_ns(stamp)
        return self._bad_time('input') if t is None else self.set_input_ns(u, t)

    def set_channel(self, index: int, value: float, stamp: float) -> bool:
        """:meth:`set_channel_ns` with the stamp in float seconds."""
        t = to_ns(stamp)
        return self._bad_time('input') if t is None else self.set_channel_ns(index, value, t)

    def set_input_ns(self, u: ArrayLike, stamp_ns: int) -> bool:
        """Take a whole input vector stamped ``stamp_ns``; returns whether it was used."""
        if not _ok_ns(stamp_ns):
            return self._bad_time('input', stamp_ns)
        stamp_ns = int(stamp_ns)
        vec = np.asarray(u, dtype=np.float64)
        m = self._dyn.m
        if vec.shape != (m,):
            return self._drop('wrong_length', None, stamp_ns,
                              f'input of shape {vec.shape}, expected ({m},)', every=True)
        env = self._env
        if env.u_lo is None:
            if not _finite(vec):
                return self._drop('nonfinite', None, stamp_ns, 'input with NaN/Inf',
                                  every=True)
        elif not ((vec >= env.u_lo) & (vec <= env.u_hi)).all():    # NaN fails both too
            if not _finite(vec):
                return self._drop('nonfinite', None, stamp_ns, 'input with NaN/Inf',
                                  every=True)
            inside = self._envelope_vector(vec, stamp_ns)
            if inside is None:
                return False
            vec = inside
        return self._take(None, vec, stamp_ns)

    def set_channel_ns(self, index: int, value: float, stamp_ns: int) -> bool:
        """Take one input channel (per-chamber topics); returns whether it was used."""
        if not _ok_ns(stamp_ns):
            return self._bad_time(f'input {index}', stamp_ns)
        stamp_ns = int(stamp_ns)
        m = self._dyn.m
        if not (isinstance(index, (int, np.integer)) and 0 <= index < m):
            return self._drop('wrong_length', None, stamp_ns,
                              f'input channel {index} not in 0..{m - 1}')
        index = int(index)
        value = float(value)
        if not math.isfinite(value):
            return self._drop('nonfinite', index, stamp_ns, f'input {index} NaN/Inf')
        if not self._env.input_ok(index, value):
            if self.config.input_envelope_action == 'drop':
                self.channels.out_of_envelope[index] += 1
                return self._drop('input_out_of_envelope', index, stamp_ns,
                                  f'input {self.model.input_names[index]}={value:.4g} outside '
                                  'its envelope')
            self._clipped(index, value, stamp_ns)
            value = self._env.clip(index, value)
        return self._take(index, value, stamp_ns)

    def refuse_input(self, index: int | None, counter: str, why: str) -> bool:
        """Drop an input for a reason only the caller can see (counted ``counter``, WARN).

        ``index`` ``None``: a whole vector (every input counts it). Returns False.
        """
        return self._drop(counter, index, None, why, every=index is None)

    def _envelope_vector(self, u: Array, stamp_ns: int) -> Array | None:
        """A finite input with values outside the envelope: clipped, or ``None`` (dropped)."""
        lo, hi = self._env.u_lo, self._env.u_hi
        if lo is None or hi is None:                # no envelope: nothing to clip
            return u
        bad = np.flatnonzero((u < lo) | (u > hi))
        if self.config.input_envelope_action == 'drop':
            for i in bad.tolist():
                self.channels.out_of_envelope[i] += 1
            self._drop('input_out_of_envelope', None, stamp_ns,
                       f'input {self.model.input_names[int(bad[0])]}={u[bad[0]]:.4g} outside '
                       'its envelope')
            return None
        for i in bad.tolist():
            self._clipped(i, float(u[i]), stamp_ns)
        return np.clip(u, lo, hi)

    def _clipped(self, index: int, value: float, stamp_ns: int) -> None:
        self.counters['input_clipped'] += 1
        self.channels.clipped[index] += 1
        self._alarm('clipped', stamp_ns, f'input {self.model.input_names[index]}={value:.4g} '
                                         'clipped to its envelope')

    def _drop(self, counter: str, index: int | None, stamp_ns: int | None, why: str, *,
              every: bool = False) -> bool:
        """Count a dropped input: on channel ``index``, or on ``every`` one (a whole vector)."""
        self.counters[counter] += 1
        dropped = self.channels.dropped
        for i in (range(len(dropped)) if every else () if index is None else (index,)):
            dropped[i] += 1
        self._alarm('dropped', stamp_ns, f'dropped messages (last: {why})')
        return False

    def _take(self, index: int | None, value: Any, stamp_ns: int) -> bool:
        """A valid input: clock checks, then queue (event) or latch (fixed/input)."""
        ch = self.channels
        newest_ch = ch.newest_max() if index is None else ch.newest[index]
        if stamp_ns < newest_ch:
            limit = self.config.clock_reset_s
            if limit > 0 and stamp_ns < self._newest - limit * 1e9:
                self._clock_reset(stamp_ns)
            elif self.config.stepping != 'event' or self._k is None or \
                    self._step_of(stamp_ns) < self._k or (
                        self._step_of(stamp_ns) == self._k and self._done):
                return self._drop('backwards', index, stamp_ns,
                                  'input stamp went backwards')
        self.counters['inputs'] += 1
        ch.received_one(index, stamp_ns)
        self._newest = max(self._newest, stamp_ns)
        if self.config.stepping == 'event':
            self._take_event(index, value, stamp_ns)
        else:
            self._take_clocked(index, value, stamp_ns)
        return True

    def _clock_reset(self, t_ns: int) -> None:
        """The clock restarted at ``t_ns``: counted, reset; the alarms keep their age."""
        self.counters['clock_reset'] += 1
        before = self.stamp_now()
        self._restart()
        if before is not None:      # else a WARN from the old clock would last the jump's length
            shift = t_ns - before
            self._alarms = {key: (t if t == _NONE else t + shift, why)
                            for key, (t, why) in self._alarms.items()}

    def _latch(self, index: int | None, value: Any) -> None:
        if index is None:
            self.u[:] = value
        else:
            self.u[index] = value

    # -- health --------------------------------------------------------------------------
    def stamp_now(self) -> int | None:
        """Newest time known on the stamps' clock: model time, input and measurement stamps."""
        known = [t for t in (self.t_ns, self.channels.measured_newest) if t is not None]
        if self._newest != _NONE:
            known.append(self._newest)
        return max(known) if known else None

    def health(self, now: float | int | None = None) -> Health:
        """Monitor state at ``now`` on the stamps' clock (int ns, or float seconds).

        Default :meth:`stamp_now`, which is right whatever clock the sensors stamp with;
        the runtime loop adds what only the reception clock can tell (nothing received).
        """
        if isinstance(now, (float, np.floating)):      # np.float32 too (was ignored)
            now = to_ns(float(now))
        elif now is not None and not _ok_ns(now):
            now = None
        return assess(self, self.stamp_now() if now is None else int(now), Level, SEVERITY)
