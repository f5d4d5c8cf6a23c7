"""The runtime loop: one ROS-free object that decides what the predictor publishes, and when.

The predictor node, ``soft-rom replay`` and ``soft-rom replay --stream`` all run a
:class:`RuntimeLoop` around a :class:`~soft_rom.predictor.Predictor`; each feeds it
messages (value, stamp in int ns, reception time in int ns) and publishes the
:class:`Publish` it returns:

* ``outputs`` -- ``~/output`` messages, each paired with its model time (int ns): every
  completed step (``output_rate_hz = 0``) or decimated to that rate on the model clock;
* ``centerline`` -- the newest prediction as points, for ``~/centerline`` and the markers,
  at ``centerline_rate_hz`` (default 30 Hz, what RViz can take), model-time decimated;
  ``measured_points`` (the last accepted measurement) and ``error`` go with it;
* ``diagnostics_due`` -- time for :meth:`RuntimeLoop.diagnostics` (reception clock).

When the predictor restarts (:attr:`Predictor.restarts <soft_rom.predictor.Predictor>`:
a restarted clock -- a bag played again, ``/clock`` jumping back -- a reset or a reload) the
whole schedule re-anchors at the next output and report, so model time starting over
earlier than before never silences a publisher; a reception clock that went back by more
than a diagnostics period before the last report also re-anchors the diagnostics.

Stepping is the predictor's: with ``'event'`` stepping the inputs drive the model, so no
fast timer is needed -- :meth:`RuntimeLoop.tick` only has to run at the diagnostics rate;
with ``'fixed'`` stepping a timer calls it at :meth:`RuntimeLoop.timer_period_ns`.
A zero stamp (un-stamped sources: ``Float64MultiArray``) is replaced by the sender's
sequence on the reception clock (:class:`SequenceClock`; counted ``stamp_fallback``),
which starts over when the reception clock goes back by more than ``clock_reset_s``;
a measurement without a stamp takes its reception time.

A per-chamber input stamped more than :data:`CLOCK_APART_S` ahead of its reception time
*and* of another input's clock (a sensor on another clock than the others) is dropped before
the predictor sees it (counted ``input_ahead`` and in that input's ``dropped`` and ``ahead``;
WARN): event stepping advances to the newest stamp every input has reached, so one input
from the future would otherwise carry the model there, time out the others and make every
later input of theirs late. Until another input has been heard, the node's clock is the
other clock. Inputs that are all on one clock, ahead or behind the node's (a robot's clock
not synchronized with this machine's; a bag played without its clock), and an array (one
sender, one clock) are kept: the model runs on their clock, and the diagnostics WARN that
it is not the node's. A reception time of 0 (a node in sim time before its first
``/clock``) checks nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.errors import ConfigError
from soft_rom.predictor.config import Health, PredictorConfig
from soft_rom.predictor.conversions import check_components, outputs_to_points, points_to_outputs
from soft_rom.predictor.core import Predictor
from soft_rom.predictor.seqclock import SequenceClock

__all__ = ['CLOCK_APART_S', 'Diagnostics', 'LoopSettings', 'MARKER_STYLES', 'Publish',
           'RuntimeLoop', 'SequenceClock']

Array = NDArray[np.float64]

#: An input stamped further than this (s) from its reception time is on another clock: WARN on
#: its topic, and dropped when it is ahead (it would carry the model's event time with it).
CLOCK_APART_S = 10.0
_AHEAD_NS = int(CLOCK_APART_S * 1e9)

#: ``kind -> (namespace, id, rgba, line width)`` of the centerline markers.
MARKER_STYLES: dict[str, tuple[str, int, tuple[float, float, float, float], float]] = {
    'predicted': ('predicted', 0, (0.1, 0.4, 1.0, 1.0), 0.004),
    'measured': ('measured', 1, (1.0, 0.3, 0.1, 1.0), 0.003),
}


@dataclass(frozen=True)
class LoopSettings:
    """What the loop publishes and how it converts (the node's non-core parameters).

    Parameters
    ----------
    output_rate_hz : float
        ``~/output`` rate on the model clock; ``0`` = every step.
    centerline_rate_hz : float
        ``~/centerline`` and markers; ``0`` = with every output.
    diagnostics_rate_hz : float
        Diagnostics on the reception clock (``> 0``).
    components : str
        Output layout, component-major (``'xz'``: ``y = [x_1..x_N, z_1..z_N]``).
    fill_value : float
        Coordinate value of the components the model does not predict.
    input_scale, input_offset : float
        ``u = input_scale * value + input_offset``.
    """

    output_rate_hz: float = 0.0
    centerline_rate_hz: float = 30.0
    diagnostics_rate_hz: float = 1.0
    components: str = 'xz'
    fill_value: float = 0.0
    input_scale: float = 1.0
    input_offset: float = 0.0

    def __post_init__(self) -> None:
        for name in ('output_rate_hz', 'centerline_rate_hz', 'diagnostics_rate_hz',
                     'fill_value', 'input_scale', 'input_offset'):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool)
                    and math.isfinite(value)):
                raise ConfigError(f'{name} must be a finite number; got {value!r}.')
        for name in ('output_rate_hz', 'centerline_rate_hz'):
            if getattr(self, name) < 0:
                raise ConfigError(f'{name} must be >= 0; got {getattr(self, name)!r}.')
        if self.diagnostics_rate_hz <= 0:
            raise ConfigError(f'diagnostics_rate_hz must be > 0; got '
                              f'{self.diagnostics_rate_hz!r}.')


class Publish:
    """What to publish after one call (all fields empty when nothing is due)."""

    __slots__ = ('centerline', 'diagnostics_due', 'error', 'measured_points', 'outputs')

    def __init__(self) -> None:
        self.outputs: list[tuple[int, Array]] = []
        self.centerline: tuple[int, Array] | None = None
        self.measured_points: Array | None = None
        self.error: float | None = None
        self.diagnostics_due = False

    def __bool__(self) -> bool:
        return bool(self.outputs) or self.centerline is not None or self.diagnostics_due


@dataclass(frozen=True)
class Diagnostics:
    """One diagnostics report: level (``DiagnosticStatus`` byte), message, key-values."""

    level: int
    message: str
    values: list[tuple[str, str]]
    health: Health


def _period_ns(rate_hz: float, h: float) -> int:
    """A publish period, a whole number of steps ``h`` (0 = every step)."""
    if rate_hz <= 0:
        return 0
    return int(round(max(1, round(1.0 / (rate_hz * h))) * h * 1e9))


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return 'nan' if math.isnan(value) else f'{value:.6g}'
    return str(value)


class RuntimeLoop:
    """Stepping, publish schedule, rate figures and diagnostics around one predictor.

    Parameters
    ----------
    predictor : Predictor
    settings : LoopSettings, optional

    Attributes
    ----------
    counts : dict of str to int
        ``outputs``, ``centerlines``, ``diagnostics``, ``stamp_fallback`` published/used.
    """

    def __init__(self, predictor: Predictor, settings: LoopSettings | None = None) -> None:
        self.predictor = predictor
        self.settings = LoopSettings() if settings is None else settings
        self.counts = {'outputs': 0, 'centerlines': 0, 'diagnostics': 0, 'stamp_fallback': 0}
        predictor.emit_outputs = True
        self._install()

    # -- configuration -------------------------------------------------------------------
    def _install(self, keep_figures: bool = False) -> None:
        """(Re)build the schedule; ``keep_figures`` keeps the reception figures and rates."""
        pred = self.predictor
        check_components(self.settings.components, pred.model.n_outputs)
        self._n_points = pred.model.n_outputs // len(self.settings.components)
        self._out_period = _period_ns(self.settings.output_rate_hz, pred.h)
        self._cl_period = _period_ns(self.settings.centerline_rate_hz, pred.h)
        self._diag_period = int(round(1e9 / self.settings.diagnostics_rate_hz))
        self._next_out: int | None = None
        self._next_cl: int | None = None
        self._next_diag: int | None = None
        self._last_t: int | None = None
        self._restarts = pred.restarts
        pred.take_emitted()
        self._clocks: dict[int, SequenceClock] = {}
        self._last_clock: SequenceClock | None = None
        if keep_figures and len(self._recv) == pred.model.n_inputs:
            return
        self._measured: Array | None = None
        self._rate_mark: tuple[int, list[int], int, int, int] | None = None
        self._recv: list[int | None] = [None] * pred.model.n_inputs
        self._moved: list[int | None] = [None] * pred.model.n_inputs    # stamp last advanced
        self._seen = list(pred.channels.newest)
        self._recv_measured: int | None = None
        self._ahead = [0] * pred.model.n_inputs     # dropped: stamped ahead (count)
        self._ahead_last: list[tuple[int, float] | None] = [None] * pred.model.n_inputs
        self._offset: list[int | None] = [None] * pred.model.n_inputs   # stamp - reception

    def set_settings(self, settings: LoopSettings) -> None:
        """New publish rates / conversion (checked against the model first)."""
        check_components(settings.components, self.predictor.model.n_outputs)
        self.settings = settings
        self._install(keep_figures=True)

    def replace_settings(self, **changes: Any) -> None:
        """:meth:`set_settings` with some fields changed."""
        self.set_settings(replace(self.settings, **changes))

    def timer_period_ns(self) -> int:
        """Period of the timer that must call :meth:`tick`.

        ``'fixed'`` stepping: the output period (or one step); otherwise the diagnostics
        period (the inputs drive the stepping).
        """
        if self.predictor.config.stepping == 'fixed':
            return self._out_period or int(round(self.predictor.h * 1e9))
        return self._diag_period

    def reset(self) -> None:
        """Reset the predictor and the publish schedule."""
        self.predictor.reset()
        self._install()

    def reload(self, model: Any, config: PredictorConfig | None = None, *,
               validate: Any = None) -> None:
        """Atomic model reload (see :meth:`Predictor.reload`); the components are checked."""
        comps = self.settings.components

        def check(candidate: Any) -> None:
            check_components(comps, candidate.n_outputs)
            if validate is not None:
                validate(candidate)

        self.predictor.reload(model, config, validate=check)
        self.predictor.emit_outputs = True
        self._install()

    def set_config(self, config: PredictorConfig) -> None:
        """Change core settings (see :meth:`Predictor.set_config`)."""
        self.predictor.set_config(config)
        self.predictor.emit_outputs = True
        self._install(keep_figures=True)

    # -- feeding -------------------------------------------------------------------------
    def _stamp(self, stamp_ns: int, now_ns: int, clock: SequenceClock | None = None) -> int:
        if stamp_ns == 0:
            self.counts['stamp_fallback'] += 1
            self._last_clock = clock
            return now_ns if clock is None else clock.stamp(now_ns)
        return stamp_ns

    def _clock(self, index: int | None) -> SequenceClock:
        key = -1 if index is None else index
        clock = self._clocks.get(key)
        if clock is None:
            pred = self.predictor
            cfg = pred.config
            clock = SequenceClock(int(round(pred.h * 1e9)), int(cfg.max_lag_s * 1e9),
                                  int(cfg.clock_reset_s * 1e9))
            self._clocks[key] = clock
        return clock

    def taken(self, now_ns: int) -> None:
        """The node finished taking (and publishing for) the last input at ``now_ns``.

        Un-stamped input only: its sequence clock then knows which messages waited in the
        queue (taken within a step after this at start-up, within a quarter step and a step
        after the previous arrival later: :class:`SequenceClock`).
        """
        if self._last_clock is not None:
            self._last_clock.taken(now_ns)
            self._last_clock = None

    def on_channel(self, index: int, value: float, stamp_ns: int, now_ns: int) -> Publish:
        """One per-chamber value (raw units; scale and offset applied here)."""
        if now_ns and 0 <= index < len(self._offset):
            self._offset[index] = offset = stamp_ns - now_ns
            if offset > _AHEAD_NS and self._ahead_of_the_others(index, offset):
                return self._refuse_ahead(index, offset, now_ns)
        s = self.settings
        if self.predictor.set_channel_ns(index, s.input_scale * value + s.input_offset,
                                         self._stamp(stamp_ns, now_ns,
                                                     self._clock(index))):
            self._received(index, now_ns)
        return self._collect(now_ns)

    def on_array(self, values: ArrayLike, stamp_ns: int, now_ns: int) -> Publish:
        """All inputs at once (``Float64MultiArray``: pass ``stamp_ns=0`` for ``now_ns``)."""
        s = self.settings
        u = np.asarray(values, dtype=np.float64).reshape(-1)
        if s.input_scale != 1.0 or s.input_offset != 0.0:
            u = s.input_scale * u + s.input_offset
        if self.predictor.set_input_ns(u, self._stamp(stamp_ns, now_ns, self._clock(None))):
            for i in range(len(self._recv)):
                self._received(i, now_ns)
        return self._collect(now_ns)

    def _ahead_of_the_others(self, index: int, offset: int) -> bool:
        """Whether input ``index``, ``offset`` ahead of its reception, is on a clock of its own.

        It is when another input's last stamp was more than :data:`CLOCK_APART_S` less
        ahead of its own reception, or when no other input has been heard yet (the node's
        clock is then the only other one). A single input has no other to disagree with.
        """
        others = [o for j, o in enumerate(self._offset) if j != index and o is not None]
        return len(self._offset) > 1 and (not others or min(others) < offset - _AHEAD_NS)

    def _refuse_ahead(self, index: int, ahead_ns: int, now_ns: int) -> Publish:
        """Drop input ``index``, stamped ``ahead_ns`` ahead of its reception (another clock)."""
        pred = self.predictor
        self._ahead[index] += 1
        self._ahead_last[index] = (now_ns, ahead_ns * 1e-9)     # received then, so far ahead
        pred.refuse_input(index, 'input_ahead',
                          f'{pred.model.input_names[index]} stamped {ahead_ns * 1e-9:.3g} s '
                          'ahead of the reception clock and of the other inputs (another '
                          'clock?)')
        return self._collect(now_ns)

    def _received(self, i: int, now_ns: int) -> None:
        self._recv[i] = now_ns
        newest = self.predictor.channels.newest[i]
        if newest != self._seen[i] or self._moved[i] is None:
            self._seen[i] = newest
            self._moved[i] = now_ns

    def on_measured(self, measured: ArrayLike, stamp_ns: int, now_ns: int) -> Publish:
        """A measured output: points ``(N, 3)`` (centerline) or the vector ``(p,)``."""
        arr = np.asarray(measured, dtype=np.float64)
        pred = self.predictor
        if arr.ndim == 2:
            if arr.shape[1] != 3 or arr.shape[0] != self._n_points:
                pred.measure_ns(arr, self._stamp(stamp_ns, now_ns))   # dropped, said
                return self._collect(now_ns)
            arr = points_to_outputs(arr, self.settings.components)
        before = pred.counters['measured_dropped']
        pred.measure_ns(arr, self._stamp(stamp_ns, now_ns))
        if pred.counters['measured_dropped'] == before:     # compared, or queued
            self._measured = arr
            self._recv_measured = now_ns
        return self._collect(now_ns)

    def measured_points(self) -> Array | None:
        """The last accepted measurement as points ``(N, 3)`` (``None`` before one)."""
        if self._measured is None:
            return None
        s = self.settings
        return outputs_to_points(self._measured, s.components, s.fill_value)

    def tick(self, now_ns: int) -> Publish:
        """Timer: ``'fixed'`` stepping advances to ``now_ns``; then what is due."""
        if self.predictor.config.stepping == 'fixed':
            self.predictor.advance_to_ns(now_ns)
        return self._collect(now_ns)

    # -- schedule --------------------------------------------------------------------
    def _collect(self, now_ns: int) -> Publish:
        pred = self.predictor
        if pred.restarts != self._restarts:       # model time started over: re-anchor all
            self._restarts = pred.restarts
            self._next_out = self._next_cl = self._next_diag = self._last_t = None
        pub = Publish()
        emitted = pred.take_emitted()
        t = pred.t_ns
        if not emitted and pred.config.stepping != 'event' and t is not None and \
                t != self._last_t:
            emitted = [(t, pred.output())]
        if emitted:
            self._last_t = emitted[-1][0]
            if self._out_period:
                for t_e, y in emitted:
                    if self._next_out is None or t_e >= self._next_out:
                        pub.outputs.append((t_e, y))
                        self._next_out = t_e + self._out_period
            else:
                pub.outputs = emitted
            t_last, y_last = pub.outputs[-1] if not self._cl_period and pub.outputs \
                else emitted[-1]
            if (pub.outputs if not self._cl_period else
                    self._next_cl is None or t_last >= self._next_cl):
                s = self.settings
                pub.centerline = (t_last, outputs_to_points(y_last, s.components,
                                                            s.fill_value))
                if self._measured is not None:
                    pub.measured_points = outputs_to_points(self._measured, s.components,
                                                            s.fill_value)
                err = pred.windowed_error(pred.stamp_now())
                pub.error = err if math.isfinite(err) else None
                self._next_cl = t_last + self._cl_period
                self.counts['centerlines'] += 1
            self.counts['outputs'] += len(pub.outputs)
        nd, period = self._next_diag, self._diag_period
        # due, or the reception clock went back by more than a period before the last report
        if nd is None or not nd - 2 * period <= now_ns < nd:
            pub.diagnostics_due = True
            # on schedule; after a jump either way, from now (no burst, no long silence)
            self._next_diag = nd + period if nd is not None and nd <= now_ns < nd + period \
                else now_ns + period
        return pub

    # -- diagnostics -----------------------------------------------------------------
    def diagnostics(self, now_ns: int, extra: list[tuple[str, str]] | None = None
                    ) -> Diagnostics:
        """Health with global and per-input figures (rates since the last call).

        The predictor's health is judged on the stamps' clock; ``now_ns`` is the reception
        clock, on which the loop adds: inputs from which nothing was received for longer
        than ``input_timeout_s``, measurements stopped for longer than ``error_window_s``.
        Per input: ``rate_hz``, ``age_s`` (since the last message received), ``stamp_lag_s``
        (behind the newest input stamp), ``received``, ``late``, ``dropped``, ``clipped``,
        ``ahead`` (dropped: stamped more than :data:`CLOCK_APART_S` ahead of the reception
        clock), ``ahead_s`` (how far, when the newest arrival was dropped so; else nan),
        ``timed_out``.
        """
        from soft_rom.predictor.config import Level, SEVERITY

        pred = self.predictor
        cfg = pred.config
        health = pred.health()
        reasons = [(health.level, health.message)] if health.level != Level.OK else []
        values = [(str(k), _fmt(v)) for k, v in health.values.items()]
        ch = pred.channels
        mark = self._rate_mark
        dt = (now_ns - mark[0]) * 1e-9 if mark is not None else 0.0
        newest = ch.newest_max()
        silent = []
        for i, name in enumerate(ch.names):
            recv = self._recv[i]
            last = self._ahead_last[i]      # how far ahead, if the newest arrival was so
            ahead_s = last[1] if last is not None and (recv is None or last[0] > recv) \
                else math.nan
            age = math.inf if recv is None else (now_ns - recv) * 1e-9
            if recv is not None and age > cfg.input_timeout_s:
                silent.append(f'{name} {age:.2f} s')
            lag = math.inf if ch.newest[i] == -(2 ** 63) else (newest - ch.newest[i]) * 1e-9
            rate = (ch.received[i] - mark[1][i]) / dt if mark and dt > 0 else math.nan
            values += [(f'input.{name}.rate_hz', _fmt(float(rate))),
                       (f'input.{name}.age_s', _fmt(float(age))),
                       (f'input.{name}.stamp_lag_s', _fmt(float(lag))),
                       (f'input.{name}.received', str(ch.received[i])),
                       (f'input.{name}.late', str(ch.late[i])),
                       (f'input.{name}.dropped', str(ch.dropped[i])),
                       (f'input.{name}.clipped', str(ch.clipped[i])),
                       (f'input.{name}.ahead', str(self._ahead[i])),
                       (f'input.{name}.ahead_s', _fmt(ahead_s)),
                       (f'input.{name}.timed_out', str(ch.timed_out[i]).lower())]
        if silent:
            reasons.append((Level.STALE, f'nothing received from input(s) {", ".join(silent)} '
                                         f'(timeout {cfg.input_timeout_s:g} s)'))
        stalled = [f'{name} {(now_ns - moved) * 1e-9:.2f} s' for name, recv, moved in zip(
            ch.names, self._recv, self._moved) if recv is not None and moved is not None
            and recv > moved and now_ns - moved > cfg.input_timeout_s * 1e9]
        if stalled:
            reasons.append((Level.WARN, f'stamps not advancing (clock stalled?) on input(s) '
                                        f'{", ".join(stalled)} while messages arrive'))
        if self._recv_measured is not None:
            m_age = (now_ns - self._recv_measured) * 1e-9
            values.append(('measured.age_s', _fmt(float(m_age))))
            if m_age > cfg.error_window_s:
                reasons.append((Level.STALE, f'no measurement received for {m_age:.2f} s'))
        m_rate = (ch.measured - mark[2]) / dt if mark and dt > 0 else math.nan
        o_rate = (self.counts['outputs'] - mark[3]) / dt if mark and dt > 0 else math.nan
        values += [('measured.rate_hz', _fmt(float(m_rate))),
                   ('output.rate_hz', _fmt(float(o_rate))),
                   ('input_rate_hz', _fmt((pred.counters['inputs'] - mark[4]) / dt)
                    if mark and dt > 0 else 'nan'),
                   ('outputs_published', str(self.counts['outputs'])),
                   ('stamp_fallback', str(self.counts['stamp_fallback'])),
                   ('stamp_resync', str(sum(c.resyncs for c in self._clocks.values())))]
        values += list(extra or [])
        self._rate_mark = (int(now_ns), list(ch.received), ch.measured, self.counts['outputs'],
                           pred.counters['inputs'])
        self.counts['diagnostics'] += 1
        level = max((lv for lv, _ in reasons), key=SEVERITY.__getitem__, default=Level.OK)
        message = '; '.join(msg for _, msg in reasons) or 'ok'
        return Diagnostics(int(level), message, values, health)
