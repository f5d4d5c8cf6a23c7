"""The predictor's health at a given time: level, reasons and the figures behind them.

Reasons, worst first:

* ``ERROR`` -- the prediction diverged (outside the output envelope or non-finite) within
  the last ``alarm_hold_s`` (or still is, without ``auto_reset``); the windowed error is
  above the error threshold (``error_threshold``, by default a multiple of the model's
  held-out error: :class:`~soft_rom.predictor.thresholds.Thresholds`);
* ``STALE`` -- an input has not sent a value yet, or is silent for longer than
  ``input_timeout_s``; measurements were seen but none is left in the window
  (``error_window_s``);
* ``WARN`` -- within the last ``alarm_hold_s``: a dropped message, an input that arrived after
  its step was taken (``late``: the prediction departs from the offline simulation), an input
  clipped to its envelope, a measurement outside the output envelope, stamped more than
  ``clock_reset_s`` ahead of the model time or beyond the queue bound, a clock stall or jump;
  the model is unstable or not trusted (``model.trust_issues()``); the windowed error is above
  the warn threshold.
"""

from __future__ import annotations

import math
from typing import Any

from soft_rom.predictor.channels import NO_STAMP
from soft_rom.predictor.config import Health

__all__ = ['assess']

_ALARM_LEVEL = {'dropped': 1, 'clipped': 1, 'measured': 1, 'clock': 1, 'late': 1,
                'diverged': 2}


def assess(pred: Any, now_ns: int | None, Level: Any, severity: dict[Any, int]) -> Health:
    """:class:`Health` of ``pred`` at ``now_ns`` (``None``: nothing has happened yet)."""
    cfg = pred.config
    ch = pred.channels
    reasons: list[tuple[Any, str]] = []
    never = [n for n, s in zip(ch.names, ch.newest) if s == NO_STAMP]
    if never:
        reasons.append((Level.STALE, f'no value yet on input(s) {", ".join(never)} '
                                     '(holding 0)'))
    ages = [math.inf if s == NO_STAMP or now_ns is None else (now_ns - s) * 1e-9
            for s in ch.newest]
    silent = [f'{n} {a:.2f} s' for n, s, a, out in zip(ch.names, ch.newest, ages, ch.timed_out)
              if s != NO_STAMP and (a > cfg.input_timeout_s or out)]
    if silent:
        reasons.append((Level.STALE, f'input(s) silent: {", ".join(silent)} (timeout '
                                     f'{cfg.input_timeout_s:g} s; holding last value)'))
    hold = cfg.alarm_hold_s * 1e9
    for key, (t_alarm, why) in sorted(pred._alarms.items()):
        latched = key == 'diverged' and pred._diverged_latched and not cfg.auto_reset
        early = t_alarm == NO_STAMP       # before any time was known: until one is
        # no time known yet (every input so far dropped): each alarm so far says why
        if latched or now_ns is None or (
                now_ns is not None and not early and now_ns - t_alarm <= hold):
            reasons.append((Level(_ALARM_LEVEL.get(key, 1)), why))
    if pred._dyn.trust_issues:
        reasons.append((Level.WARN, 'model not trusted: ' + '; '.join(pred._dyn.trust_issues)))
    elif pred._dyn.unstable:
        reasons.append((Level.WARN, f'model unstable (stability margin '
                                    f'{pred._dyn.info["stability_margin"]:.3g} < 0)'))
    e_abs, e_dev = pred.windowed_errors(now_ns)
    err = e_dev if cfg.error_metric == 'deviation' else e_abs
    thr = pred.thresholds
    what = f'{cfg.error_metric} error over the last {cfg.error_window_s:g} s'
    if not math.isnan(err):
        if math.isinf(err):
            reasons.append((Level.ERROR, f'{what} inf: the measured deviation from y_ref is '
                                         'exactly 0 and the prediction is not'))
        elif err > thr.error:
            reasons.append((Level.ERROR, f'{what} {err:.3g} > {thr.error:.3g}{thr.error_why}'))
        elif err > thr.warn:
            reasons.append((Level.WARN, f'{what} {err:.3g} > {thr.warn:.3g}{thr.warn_why}'))
    elif pred._monitor.seen and ch.measured_newest is not None and now_ns is not None:
        age = (now_ns - ch.measured_newest) * 1e-9
        reasons.append((Level.STALE, f'no measurement for {age:.2f} s (window '
                                     f'{cfg.error_window_s:g} s)'))
    level = max((lv for lv, _ in reasons), key=severity.__getitem__, default=Level.OK)
    t_ns = pred.t_ns
    values: dict[str, float | int | str] = {
        'error_absolute': e_abs,
        'error_deviation': e_dev,
        'window': len(pred._monitor),
        'model_time': math.nan if t_ns is None else t_ns * 1e-9,
        'model_time_ns': -1 if t_ns is None else t_ns,
        'method': pred.model.method,
        'r': pred.model.r,
        'kalman': int(pred._dyn.L is not None),
        'stepping': cfg.stepping,
        'output_bound': pred.envelopes.y_bound,
        'warn_threshold': thr.warn,
        'error_threshold': thr.error,
        'measured_queued': pred._queued_measurements,
    }
    values.update(pred.counters)
    for name, age in zip(ch.names, ages):
        values[f'input_age.{name}'] = float(age)
    text = '; '.join(msg for _, msg in reasons) or 'ok'
    return Health(level, text, tuple(msg for _, msg in reasons), values)
