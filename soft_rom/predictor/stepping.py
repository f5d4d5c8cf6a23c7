"""Stepping of the predictor: clocked (``'fixed'``, ``'input'``) and event-time (``'event'``).

The :class:`Stepping` mixin holds the part of :class:`~soft_rom.predictor.core.Predictor`
that moves the model in time, computes its output and checks it against the output
envelope; the module notes of :mod:`soft_rom.predictor.core` describe the behaviour.
"""

from __future__ import annotations

import heapq
import math
from typing import Any, cast, TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

__all__ = ['Stepping', 'to_ns']

Array = NDArray[np.float64]
_T_LIMIT = 2 ** 62
_HISTORY = 512
_NONE = -(2 ** 63)


def to_ns(t: float) -> int | None:
    """Float seconds to int ns; ``None`` for non-finite or out-of-range times."""
    try:
        if not math.isfinite(t) or abs(t) > _T_LIMIT * 1e-9:
            return None
        return int(round(t * 1e9))
    except TypeError:
        return None


def _ok_ns(t: Any) -> bool:
    return bool(isinstance(t, (int, np.integer)) and not isinstance(t, bool)
                and -_T_LIMIT <= t <= _T_LIMIT)


def time_problem(t_ns: Any = None) -> str:
    """Why a time was refused, in words (``t_ns``: what an ``*_ns`` method was given)."""
    if isinstance(t_ns, (float, np.floating)) and math.isfinite(t_ns):
        return (f'time {float(t_ns)!r} is a float; the *_ns methods take an int of '
                'nanoseconds (the others float seconds)')
    return 'time not finite or out of range'


class Stepping:
    """Time stepping, outputs and divergence checks (mixed into ``Predictor``)."""

    # attributes set by Predictor
    _dyn: Any
    _env: Any
    config: Any
    counters: dict[str, int]
    channels: Any
    x: Array
    u: Array
    emit_outputs: bool
    _emitted: list[tuple[int, Array]]
    _k: int | None
    _origin: int
    _done: bool
    _released: bool
    _queue: list[tuple[int, int, int, int, Any]]
    _queued_measurements: int
    _seq: int
    _newest: int
    _Bu: Array
    _y: Array
    _dev: Array
    _fast2: float
    _hist: Array
    _hist_k: NDArray[np.int64]

    if TYPE_CHECKING:  # methods of Predictor used here (declared for the type checker)
        @property
        def model(self) -> Any: ...

        @property
        def t_ns(self) -> int | None: ...

        def _time_of(self, k: int) -> int: ...

        def _update_Bu(self) -> None: ...

        def _step_of(self, t_ns: int) -> int: ...

        def _anchor(self, t_ns: int) -> None: ...

        def _alarm(self, key: str, t_ns: int | None, why: str) -> None: ...

        def _bad_time(self, what: str, t_ns: Any = None) -> bool: ...

        def _latch(self, index: int | None, value: Any) -> None: ...

        def _measure_now(self, y: Array, stamp_ns: int, k: int) -> float | None: ...

        def _clock_reset(self, t_ns: int) -> None: ...

    # -- clocked stepping ('fixed', 'input') ----------------------------------------------
    def _take_clocked(self, index: int | None, value: Any, stamp_ns: int) -> None:
        if self._k is None:
            self._anchor(stamp_ns)
        elif stamp_ns < self._time_of(self._k):
            self._late(index, stamp_ns)
        else:
            self._advance_ns(stamp_ns)
        self._latch(index, value)
        self._update_Bu()

    def advance_to(self, t: float) -> int:
        """:meth:`advance_to_ns` with the time in float seconds."""
        t_ns = to_ns(t)
        return self._bad_time('advance') if t_ns is None else self.advance_to_ns(t_ns)

    def advance_to_ns(self, t_ns: int) -> int:
        """Advance the model to ``t_ns`` with the held inputs; returns steps taken.

        ``'fixed'``: every whole step due; ``'input'``: exactly to ``t_ns`` (discrete-time
        models: whole native steps, remainder carried); ``'event'``: every step up to the
        one ``t_ns`` belongs to, as if every input were known until then. Past times do
        nothing, except with ``'fixed'`` stepping (the caller's clock drives the model) a
        time more than ``clock_reset_s`` before the model time: a restarted clock (``/clock``
        of a bag played again), counted ``clock_reset``; the predictor resets and model time
        starts over at ``t_ns``. Refused times (non-finite, out of range) are counted
        ``bad_time``.
        """
        if not _ok_ns(t_ns):
            return int(self._bad_time('advance', t_ns))
        t_ns = int(t_ns)
        limit = self.config.clock_reset_s
        if self.config.stepping == 'fixed' and self._k is not None and limit > 0 and \
                t_ns < self._time_of(self._k) - limit * 1e9:
            self._clock_reset(t_ns)
        return self._advance_ns(t_ns)

    def _advance_ns(self, t_ns: int) -> int:
        """:meth:`advance_to_ns` of a checked time, never a clock reset (measurements)."""
        if self._k is None:
            self._anchor(t_ns)
            if self.config.stepping == 'event':
                self._first = t_ns
                self._release(cast(int, self._k))    # set by _anchor
            return 0
        if self.config.stepping == 'event':
            before = self.counters['steps']
            self._release(self._step_of(t_ns))
            return self.counters['steps'] - before
        d = self._dyn
        now = self._time_of(self._k)
        elapsed = t_ns - now
        if elapsed <= 0:
            return 0
        if self.config.stepping == 'fixed' or d.discrete or not d.linear:
            n = int((elapsed + d.h_ns * 1e-3) // d.h_ns)
            n = self._limit_catchup(n)
            self._steps(n)
            if n:
                self._check_output(self.t_ns)
            return n
        limit_ns = int(self.config.max_catchup_steps * d.h_ns)
        if elapsed > limit_ns:          # exact stepping: the state is held over the gap too
            self.counters['catchup_skipped'] += int((elapsed - limit_ns) // d.h_ns)
            self.counters['clock_jump'] += 1
            self._alarm('clock', t_ns, f'clock stalled or jumped: {elapsed * 1e-9:.3g} s '
                                       'in one step, state held')
            elapsed = limit_ns
        A, B = d.matrices_for(elapsed)
        self.x = A @ self.x + B @ self.u
        self._origin, self._k = t_ns, 0
        self.counters['steps'] += 1
        if self._check_output(t_ns) and self.emit_outputs:
            self._emitted.append((t_ns, self._output_into(np.empty(d.p))))
        return 1

    def _limit_catchup(self, n: int) -> int:
        limit = self.config.max_catchup_steps
        if n <= limit:
            return n
        skipped = n - limit
        self.counters['catchup_skipped'] += skipped
        self.counters['clock_jump'] += 1
        self._k += skipped
        self._alarm('clock', self._time_of(self._k + limit),
                    f'clock stalled or jumped: {skipped} steps ({skipped * self._dyn.h:.3g} s) '
                    'skipped, state held')
        return limit

    def step(self) -> None:
        """One step ``h`` with the held inputs (the hot path; no checks)."""
        d = self._dyn
        if d.linear:
            # a new array each step, never written again: a reference to ``x`` kept by the
            # caller (a history, another thread) stays the state of its step
            xn = d.A @ self.x
            xn += self._Bu
            self.x = xn
        else:
            self.x = d.stepper(self.x, self.u)
        self.counters['steps'] += 1
        if self._k is not None:
            self._k += 1

    def _steps(self, n: int) -> None:
        """``n`` steps; with clocked stepping each one's output is emitted (every step)."""
        if not self.emit_outputs or self.config.stepping == 'event':
            for _ in range(n):
                self.step()
            return
        for _ in range(n):
            self.step()
            t_ns = self.t_ns
            assert t_ns is not None                 # steps are taken only once anchored
            self._emitted.append((t_ns, self._output_into(np.empty(self._dyn.p))))

    def _late(self, index: int | None, stamp_ns: int) -> None:
        """An input for a step already taken: counted, and a WARN while it is recent.

        It is applied from the current step on, so the prediction departs from the offline
        simulation of the same inputs (a pause of the node longer than ``max_lag_s``, an
        input faster than the step rate). The lag said is from the input's own step (event
        stepping) or stamp to the first output it reaches: at least one step, never negative.
        """
        self.counters['late'] += 1
        self.channels.late_one(index)
        k = self._k
        assert k is not None                        # late only once anchored
        if self.config.stepping == 'event':
            # from its step to the first output it reaches: this step's, or the next one's
            # if this one is out (a stamp up to h/2 after the grid belongs to the step: its
            # own time against the step's gave a negative lag, '-0.1 ms behind the model')
            lag = (self._time_of(k + (1 if self._done else 0))
                   - self._time_of(self._step_of(stamp_ns))) * 1e-9
        else:
            lag = (self._time_of(k) - stamp_ns) * 1e-9     # before the model time: > 0
        names = self.model.input_names
        name = 'all inputs' if index is None else f'input {names[index]}'
        self._alarm('late', None, f'{self.counters["late"]} input(s) arrived after their step '
                                  f'was taken (the last: {name}, {lag * 1e3:.3g} ms behind '
                                  'the model); they are applied late and the prediction '
                                  'departs from the offline simulation')

    # -- event stepping ------------------------------------------------------------------
    def _take_event(self, index: int | None, value: Any, stamp_ns: int) -> None:
        if self._k is None:
            self._anchor(stamp_ns)
            self._first = stamp_ns
        assert self._k is not None                  # anchored above
        s = self._step_of(stamp_ns)
        if index is None and s == self._k + 1 and self._done and not self._queue:
            # the 1 kHz array path: every input known up to s, nothing queued, one step
            if any(self.channels.timed_out):
                self.channels.timed_out = [False] * len(self.channels.timed_out)
            self.step()
            self.u[:] = value
            self._update_Bu()
            self._complete(s)
            return
        if not self._released and s < self._k:      # nothing taken yet: move the start back
            self._k = s
            self._first = min(self._first, stamp_ns)
        if s > self._k:
            self._seq += 1
            heapq.heappush(self._queue, (s, 0, self._seq, -1 if index is None else index,
                                         value))
        else:
            if s < self._k or self._done:
                self._late(index, stamp_ns)
            self._latch(index, value)
            self._update_Bu()
        self._release(self._target())

    def _target(self) -> int:
        """Step the model may advance to: watermark, timeouts, lag."""
        ch = self.channels
        timeout = self.config.input_timeout_s * 1e9
        newest = self._newest
        before_first = self._first - self._dyn.h_ns       # unseen inputs: known until here
        wm = None
        for i, s in enumerate(ch.newest):
            s_eff = before_first if s == _NONE else s
            silent = newest - s_eff > timeout
            if silent != ch.timed_out[i]:
                ch.timed_out[i] = silent
                if silent:
                    self.counters['timeouts'] += 1
            if not silent and (wm is None or s_eff < wm):
                wm = s_eff
        k_wm = self._step_of(newest if wm is None else int(wm))
        k_lag = self._step_of(newest - int(self.config.max_lag_s * 1e9))
        assert self._k is not None                  # inputs are queued only once anchored
        if k_lag > k_wm and k_lag > self._k:
            self.counters['lag_forced'] += k_lag - max(k_wm, self._k)
            return k_lag
        return k_wm

    def _release(self, target: int) -> None:
        """Complete every step up to ``target`` (event stepping)."""
        if self._k is None or target < self._k:
            return
        if target - self._k > self.config.max_catchup_steps:
            self._limit_catchup(target - self._k)
            self._done = False
        q = self._queue
        while True:
            if not self._done:
                k = self._k
                changed = False
                while q and q[0][0] <= k and (q[0][1] == 0 or q[0][0] < k):
                    s, kind, _, i, v = heapq.heappop(q)
                    if kind == 0:
                        self._latch(None if i < 0 else i, v)
                        changed = True
                    else:
                        self._queued_measurements -= 1
                        self._measure_now(v[0], v[1], s)
                if changed:
                    self._update_Bu()
                self._complete(k)
                while q and q[0][0] <= k:
                    s, _, _, _, v = heapq.heappop(q)
                    self._queued_measurements -= 1
                    self._measure_now(v[0], v[1], s)
                self._done = True
                self._released = True
            if self._k >= target:
                return
            self.step()
            self._done = False

    def _complete(self, k: int) -> None:
        """Output of step ``k`` into the history; envelope check; emission."""
        row = self._hist[k % _HISTORY]
        self._output_into(row)
        self._hist_k[k % _HISTORY] = k
        t_ns = self.t_ns
        assert t_ns is not None                     # a step completes only once anchored
        if not self._check_output(t_ns, row):
            self._output_into(row)
        if self.emit_outputs:
            self._emitted.append((t_ns, row.copy()))

    def take_emitted(self) -> list[tuple[int, Array]]:
        """``(t_ns, y)`` of every step completed since the last call (``emit_outputs``)."""
        out, self._emitted = self._emitted, []
        return out

    # -- outputs and divergence -------------------------------------------------------
    def _output_into(self, y: Array) -> Array:
        d = self._dyn
        if d.linear:
            np.dot(d.C, self.x, out=y)
            if d.has_D:
                y += d.D @ self.u
            y += d.y_ref
        else:
            y[:] = self.model.output(self.x, self.u)
        return y

    def output(self, out: Array | None = None) -> Array:
        """Predicted absolute output at the model time, shape (p,).

        Without ``out`` a new array; reads the state only (no scratch buffer of the
        predictor is written, so a reader does not disturb the thread that steps it).
        """
        if out is None:
            out = np.empty(self._dyn.p)
        return self._output_into(out)

    def _check_output(self, t_ns: int | None, y: Array | None = None) -> bool:
        """Divergence check; returns False if the state was found outside the envelope."""
        y = self._output_into(self._y) if y is None else y
        # fast path: |y - y_ref|_inf <= |y|_2 + |y_ref|_2 <= bound (one dot; NaN fails every
        # comparison). A non-finite state always reaches y through C x (0 * inf is NaN).
        if float(y @ y) <= self._fast2:
            self._diverged_latched = False
            return True
        np.subtract(y, self._dyn.y_ref, out=self._dev)
        dev = float(np.max(np.abs(self._dev))) if self._dev.size else 0.0
        if self._env.output_ok(dev) and math.isfinite(float(self.x.sum())):
            self._diverged_latched = False
            return True
        if not self._diverged_latched or self.config.auto_reset:
            self.counters['diverged'] += 1
        self._diverged_latched = True
        what = 'non-finite' if not math.isfinite(dev) else f'max |y - y_ref| = {dev:.3g}'
        action = 'state reset to the reference' if self.config.auto_reset else 'state kept'
        self._alarm('diverged', t_ns, f'prediction diverged ({what} > bound '
                                      f'{self._env.y_bound:.3g}); {action}')
        if self.config.auto_reset or not math.isfinite(float(self.x.sum())):
            self.x = self._dyn.initial_state()
        return False
