"""Settings and health levels of the predictor: PredictorConfig, Level, Health."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
import enum
import math
from typing import Any

import numpy as np

from soft_rom.errors import ConfigError

__all__ = ['Health', 'Level', 'PredictorConfig', 'REBUILD_FIELDS', 'SEVERITY']


class Level(enum.IntEnum):
    """Health level; values equal ``diagnostic_msgs/msg/DiagnosticStatus`` levels."""

    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3


#: Order of severity (``STALE`` is worse than ``WARN``, better than ``ERROR``).
SEVERITY = {Level.OK: 0, Level.WARN: 1, Level.STALE: 2, Level.ERROR: 3}

#: Settings whose change rebuilds the discretization (the others apply at once).
REBUILD_FIELDS = ('stepping', 'rate_hz', 'kalman', 'process_noise', 'measurement_noise',
                  'input_min', 'input_max', 'input_envelope_margin', 'output_envelope_factor')


@dataclass(frozen=True)
class PredictorConfig:
    """Run-time settings of a :class:`~soft_rom.predictor.Predictor` (node parameters, minus ROS).

    Parameters
    ----------
    stepping : {'event', 'fixed', 'input'}
        ``'event'``: the inputs drive the model on the step grid ``h``, up to the
        watermark (newest time at which every input is known); ``'fixed'``: a clock drives
        it (:meth:`~soft_rom.predictor.Predictor.advance_to_ns`), inputs latched on
        arrival; ``'input'``: an exact step to each input stamp, latched on arrival.
    rate_hz : float
        Step rate; ``0`` means the model's native ``1/dt``. A discrete-time model (DMDc,
        ERA) accepts only integer divisors of its rate. With ``'event'`` stepping an input
        faster than this rate has its extra samples within a step counted ``late``
        (applied from the next step); keep the step rate at least the input rate.
    input_timeout_s : float
        An input whose newest stamp trails the newest stamp of all inputs by more than
        this stops holding the model back (value held, ``STALE``, counted ``timeouts``).
    max_lag_s : float
        Most the model may trail the newest input stamp (``'event'``); beyond it the model
        advances with the missing inputs held (counted ``lag_forced``).
    error_window : int
        Most measurements in the windowed relative error.
    error_window_s : float
        Measurements older than this (stamp time) leave the window; an empty window after
        measurements were seen is ``STALE``.
    error_metric : {'deviation', 'absolute'}
        Which windowed error is compared with the thresholds.
    warn_threshold, error_threshold : float
        Windowed relative error above which the health is ``WARN`` / ``ERROR``; ``0``
        (default): a multiple of the model's held-out error recorded in its file (2 x and
        4 x; files without one: 0.1 and 0.3), see
        :class:`~soft_rom.predictor.thresholds.Thresholds`. Where both are set,
        ``warn_threshold`` must not exceed ``error_threshold``.
    initial_state : {'reference', 'measured'}
        Start (and restart after a reset) at the reference, or at the least-squares state
        of the first measured output.
    kalman : bool
        Correct the state with a steady-state Kalman filter at each measurement.
    process_noise, measurement_noise : float
        Kalman design covariances ``Q = process_noise * I``, ``R = measurement_noise * I``.
    max_catchup_steps : int
        Most steps in one update; beyond that the model time jumps with the state held
        (counted ``catchup_skipped``, reported as a clock jump/stall).
    clock_reset_s : float
        An input stamp older than the newest by more than this (with fixed stepping: the
        node clock going back that far) is a restarted clock: the predictor resets (counted
        ``clock_reset``) and every schedule starts again from the new time. A measurement
        stamped more than this ahead of the model time is dropped (``measured_dropped``).
        ``0`` disables both.
    alarm_hold_s : float
        How long a dropped message, clipped input, clock jump or divergence keeps the
        health at ``WARN`` / ``ERROR`` after it happened.
    input_min, input_max : tuple of float
        Input envelope (absolute input units), each bound on its own: one value per input,
        or one value for every input. Empty: that bound from the training range recorded in
        the model file, widened by ``input_envelope_margin`` times its width on each side
        (no recorded range: no bound on that side). Where both are given they must list
        the same number of values (or one of them a single value) and ``input_min`` must
        not exceed ``input_max``; a bound against the training range is checked when the
        model is known (:class:`~soft_rom.predictor.envelope.Envelopes`).
    input_envelope_margin : float
        Widening of the recorded training range (default ``1.0``: the envelope is three
        times as wide as the training range, centred on it).
    input_envelope_action : {'clip', 'drop'}
        What happens to a value outside the envelope (counted ``input_clipped`` /
        ``input_out_of_envelope``, ``WARN``).
    output_envelope_factor : float
        Divergence bound: ``max |y_hat - y_ref| > factor * S`` with ``S`` the largest
        training deviation ``max |Y - y_ref|`` recorded in the model file (files without
        it: ``max |y_ref|``, or ``1`` if that is 0). Measurements beyond it are dropped
        by the error monitor.
    auto_reset : bool
        On divergence reset the state to the reference (else it is kept; ``ERROR`` either
        way, counted ``diverged``).
    strict_model : bool
        Refuse a model that loads but cannot be trusted (``model.trust_issues()``: unstable,
        indefinite K or C, absurd offsets) at start and on reload; ``False`` (default) runs
        it and reports ``WARN`` with the reasons.
    """

    stepping: str = 'event'
    rate_hz: float = 0.0
    input_timeout_s: float = 0.5
    max_lag_s: float = 0.1
    error_window: int = 100
    error_window_s: float = 2.0
    error_metric: str = 'deviation'
    warn_threshold: float = 0.0
    error_threshold: float = 0.0
    initial_state: str = 'reference'
    kalman: bool = False
    process_noise: float = 1e-6
    measurement_noise: float = 1e-4
    max_catchup_steps: int = 10000
    clock_reset_s: float = 1.0
    alarm_hold_s: float = 2.0
    input_min: tuple[float, ...] = ()
    input_max: tuple[float, ...] = ()
    input_envelope_margin: float = 1.0
    input_envelope_action: str = 'clip'
    output_envelope_factor: float = 100.0
    auto_reset: bool = True
    strict_model: bool = False

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:      # numpy scalars as the Python ones
            value = getattr(self, name)
            if isinstance(value, np.generic) and not isinstance(value, (np.str_, np.bytes_)):
                object.__setattr__(self, name, value.item())

        def bad(name: str, expected: str) -> ConfigError:
            return ConfigError(f'predictor {name} must be {expected}; got '
                               f'{getattr(self, name)!r}.')

        choices = {'stepping': ('event', 'fixed', 'input'),
                   'error_metric': ('deviation', 'absolute'),
                   'initial_state': ('reference', 'measured'),
                   'input_envelope_action': ('clip', 'drop')}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise bad(name, ' or '.join(repr(a) for a in allowed))
        for name in ('rate_hz', 'input_timeout_s', 'max_lag_s', 'error_window_s',
                     'warn_threshold', 'error_threshold', 'clock_reset_s', 'alarm_hold_s',
                     'input_envelope_margin'):
            value = getattr(self, name)
            if not (_number(value) and math.isfinite(value) and value >= 0):
                raise bad(name, 'a finite number >= 0')
        for name in ('process_noise', 'measurement_noise', 'output_envelope_factor'):
            value = getattr(self, name)
            if not (_number(value) and math.isfinite(value) and value > 0):
                raise bad(name, 'a finite number > 0')
        if 0 < self.error_threshold < self.warn_threshold:
            raise ConfigError(f'warn_threshold ({self.warn_threshold}) must not exceed '
                              f'error_threshold ({self.error_threshold}).')
        for name in ('error_window', 'max_catchup_steps'):
            value = getattr(self, name)
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise bad(name, 'an integer >= 1')
        for name in ('kalman', 'auto_reset', 'strict_model'):
            if not isinstance(getattr(self, name), bool):
                raise bad(name, 'true or false')
        lo, hi = self._bounds('input_min'), self._bounds('input_max')
        if lo and hi:
            if len(lo) != len(hi) and 1 not in (len(lo), len(hi)):
                raise ConfigError(f'input_min and input_max must list the same number of '
                                  f'values (or one of them a single value for every '
                                  f'input); got {len(lo)} and {len(hi)}.')
            n = max(len(lo), len(hi))
            for i in range(n):
                a, b = lo[i % len(lo)], hi[i % len(hi)]
                if a > b:
                    which = f' for input {i + 1}' if n > 1 else ''
                    raise ConfigError(f'input_min must not exceed input_max{which}: '
                                      f'{a:g} > {b:g} (input_min {list(lo)}, input_max '
                                      f'{list(hi)}).')

    def _bounds(self, name: str) -> tuple[float, ...]:
        raw = getattr(self, name)
        try:
            values = tuple(float(v) for v in raw)
        except (TypeError, ValueError):
            raise ConfigError(f'predictor {name} must be a list of numbers; got '
                              f'{raw!r}.') from None
        if not all(math.isfinite(v) for v in values):
            raise ConfigError(f'predictor {name} must hold finite numbers; got {raw!r}.')
        object.__setattr__(self, name, values)
        return values

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


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


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
