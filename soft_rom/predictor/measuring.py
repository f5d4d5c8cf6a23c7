"""Measurements against the prediction: the :class:`Measuring` part of the predictor.

A measured output is checked (time, size, finite values, output envelope, horizon), then
compared with the prediction of its own step: at once when the model is there, from the
history when the model is past it, or queued (``'event'`` stepping) until the model reaches
it. The error feeds the windowed monitor before any correction; then the state is
initialised from the measurement or corrected by the Kalman gain. The module notes of
:mod:`soft_rom.predictor.core` describe the behaviour; :class:`Measuring` is mixed into
:class:`~soft_rom.predictor.core.Predictor`, which sets the attributes it uses.
"""

from __future__ import annotations

import heapq
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.predictor.monitor import ErrorMonitor
from soft_rom.predictor.stepping import _HISTORY, _ok_ns, Stepping, time_problem, to_ns

__all__ = ['MAX_QUEUED_MEASUREMENTS', 'Measuring']

Array = NDArray[np.float64]

#: Most measurements queued for a step the model has not reached (``'event'`` stepping):
#: 4 s at 1 kHz, 34 s at 120 Hz -- beyond the default horizon ``clock_reset_s`` of 1 s,
#: a bound on memory whatever the settings (``clock_reset_s = 0`` has no horizon).
MAX_QUEUED_MEASUREMENTS = 4096


def _finite(v: Array) -> bool:
    """Every value finite, tested per value (a sum of 1e308s overflows, with a warning).

    Up to 32 values (the inputs) a Python loop over the floats is the cheapest (0.25 us for
    6, against 0.6 us for the sum it replaces); beyond, one ``isfinite`` pass (0.85 us).
    """
    if v.size <= 32:
        return all(map(math.isfinite, v.tolist()))
    return bool(np.isfinite(v).all())


class Measuring(Stepping):
    """Measurements compared with the prediction, windowed errors (mixed into ``Predictor``)."""

    # attributes set by Predictor
    _monitor: ErrorMonitor
    _dy: Array
    _awaiting_init: bool
    totals: list[float]

    def measure(self, y: ArrayLike, stamp: float) -> float | None:
        """:meth:`measure_ns` with the stamp in float seconds."""
        t = to_ns(stamp)
        if t is None:
            self.counters['measured_dropped'] += 1
            self._alarm('measured', None, 'measurement dropped: time not finite or out of '
                                          'range')
            return None
        return self.measure_ns(y, t)

    def measure_ns(self, y: ArrayLike, stamp_ns: int) -> float | None:
        """Compare a measured absolute output with the prediction at ``stamp_ns``.

        ``'event'``: compared with the prediction of its step once the model is there
        (queued until then; from the history if the model is past it). Clocked stepping:
        the model first advances to ``stamp_ns``. A stamp more than ``clock_reset_s``
        ahead of the model time is dropped (it would wait, or jump the model, that long),
        and so is one more while :data:`MAX_QUEUED_MEASUREMENTS` wait. The error is taken
        before any correction; then the state is initialised from it
        (``initial_state='measured'``) or corrected by the Kalman filter (current step only).

        Returns
        -------
        float or None
            The windowed error so far (``None``: dropped, counted ``measured_dropped``, or
            queued for a step not reached yet).
        """
        y = np.array(y, dtype=np.float64)
        d = self._dyn
        if not _ok_ns(stamp_ns):
            self.counters['measured_dropped'] += 1
            self._alarm('measured', None, f'measurement dropped: {time_problem(stamp_ns)}')
            return None
        stamp_ns = int(stamp_ns)
        if y.shape != (d.p,):
            self.counters['measured_dropped'] += 1
            self._alarm('measured', stamp_ns, f'measurement of shape {y.shape} dropped; '
                                              f'the model has {d.p} outputs')
            return None
        if not _finite(y):
            self.counters['measured_dropped'] += 1
            bad = int(np.count_nonzero(~np.isfinite(y)))
            self._alarm('measured', stamp_ns, f'measurement with {bad} NaN/Inf value(s) of '
                                              f'{d.p} dropped')
            return None
        dev = float(np.max(np.abs(y - d.y_ref))) if d.p else 0.0
        if not self._env.output_ok(dev):
            self.counters['measured_dropped'] += 1
            self._alarm('measured', stamp_ns, f'measurement outside the output envelope '
                                              f'(max |y - y_ref| = {dev:.3g})')
            return None
        if self._k is not None and self._ahead(stamp_ns, self._k):
            return None
        if self.config.stepping != 'event':
            self._advance_ns(stamp_ns)
            if self._k is None:
                return None
            return self._measure_now(y, stamp_ns, self._k)
        if self._k is None:
            self.counters['measured_dropped'] += 1
            return None
        s = self._step_of(stamp_ns)
        if s > self._k or (s == self._k and not self._done):
            if self._queued_measurements >= MAX_QUEUED_MEASUREMENTS:
                self.counters['measured_dropped'] += 1
                self._alarm('measured', None, f'{MAX_QUEUED_MEASUREMENTS} measurements '
                                              'already wait for the model: dropped')
                return None
            self._seq += 1
            self._queued_measurements += 1
            heapq.heappush(self._queue, (s, 1, self._seq, -1, (y, stamp_ns)))
            return None
        return self._measure_now(y, stamp_ns, s)

    def _ahead(self, stamp_ns: int, k: int) -> bool:
        """Drop (counted, said) a measurement beyond the horizon ``clock_reset_s``."""
        limit = self.config.clock_reset_s
        ahead = stamp_ns - self._time_of(k)
        if limit <= 0 or ahead <= limit * 1e9:
            return False
        self.counters['measured_dropped'] += 1
        # said at the newest known time, not at the stamp (that clock is not ours)
        self._alarm('measured', None, f'measurement stamped {ahead * 1e-9:.3g} s ahead of the '
                                      f'model time (more than clock_reset_s = {limit:g} s): '
                                      'dropped')
        return True

    def _measure_now(self, y: Array, stamp_ns: int, k: int) -> float | None:
        d = self._dyn
        current = k == self._k
        if current and self._awaiting_init:
            self.x = np.array(self.model.state_from_output(y, self.u), dtype=np.float64)
            self._awaiting_init = False
        if current:
            yhat = self._output_into(self._y)
        elif self._hist_k[k % _HISTORY] == k:
            yhat = self._hist[k % _HISTORY]
        else:
            self.counters['measured_dropped'] += 1
            return None
        np.subtract(y, yhat, out=self._dy)
        np.subtract(y, d.y_ref, out=self._dev)
        e2 = float(self._dy @ self._dy)
        if not self._monitor.push(stamp_ns, e2, float(y @ y), float(self._dev @ self._dev)):
            self.counters['measured_dropped'] += 1
            return None
        self.totals[0] += e2
        self.totals[1] += float(y @ y)
        self.totals[2] += float(self._dev @ self._dev)
        if d.L is not None and current:
            self.x = self.x + d.L @ self._dy      # a new array (see step)
        self.counters['measurements'] += 1
        self.channels.measured_one(stamp_ns)
        return self.windowed_error()

    def windowed_errors(self, now_ns: int | None = None) -> tuple[float, float]:
        """``(absolute, deviation)`` windowed relative errors (``nan`` without data)."""
        self._monitor.expire(now_ns)
        return self._monitor.errors()

    def windowed_error(self, now_ns: int | None = None) -> float:
        """The windowed relative error chosen by ``error_metric``."""
        a, dv = self.windowed_errors(now_ns)
        return dv if self.config.error_metric == 'deviation' else a

