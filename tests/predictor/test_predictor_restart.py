"""Clock restarts, measurements from a clock far ahead, and 1e308 values (ROS-free).

Fed the way the outside world does: epoch stamps (1.7e9 s), reception a little after the
stamp with jitter, a bag played again (stamps and ``/clock`` 20 s back), a measurement
clock 60 s ahead of the inputs.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from soft_rom.models import SecondOrderModel
from soft_rom.predictor import Level, Predictor, PredictorConfig, training_envelope
from soft_rom.predictor.core import MAX_QUEUED_MEASUREMENTS
from soft_rom.predictor.loop import LoopSettings, RuntimeLoop

DT = 1e-3
H_NS = 1_000_000
S_NS = 1_000_000_000
T0_NS = 1_700_000_000 * S_NS          # an epoch stamp: 1.7e9 s
M, P = 3, 10                          # 3 chambers, 5 points in x and z


def _model(seed: int = 0) -> SecondOrderModel:
    """A stable ROM with the training envelope of pressures of ~10 kPa recorded."""
    rng = np.random.default_rng(seed)
    r = 4
    A = rng.standard_normal((r, r))
    K = (A @ A.T / r + 4.0 * np.eye(r)) * 100.0
    y_ref = np.concatenate([np.linspace(0.0, 0.4, P // 2), np.zeros(P // 2)])
    model = SecondOrderModel(K, 0.5 * np.eye(r) + 0.01 * K, rng.standard_normal((r, M)),
                             0.01 * rng.standard_normal((P, r)), dt=DT, y_ref=y_ref,
                             input_names=[f'chamber_{i + 1}' for i in range(M)])
    U = 1e4 * rng.uniform(0.0, 1.0, (M, 2000))
    meta = {'envelope': training_envelope([(U, model.simulate(U))], y_ref)}
    return SecondOrderModel(model.K, model.C, model.B, model.E, dt=DT, y_ref=y_ref,
                            input_names=model.input_names, metadata=meta)


MODEL = _model()


class _Tally:
    """What the loop asked to publish over one run."""

    def __init__(self) -> None:
        self.outputs: list[int] = []
        self.centerlines: list[int] = []
        self.errors = 0
        self.measured_markers = 0
        self.diagnostics: list = []

    def add(self, loop: RuntimeLoop, pub, now_ns: int) -> None:
        self.outputs += [t for t, _ in pub.outputs]
        if pub.centerline is not None:
            self.centerlines.append(pub.centerline[0])
            self.errors += pub.error is not None
            self.measured_markers += pub.measured_points is not None
        if pub.diagnostics_due:
            self.diagnostics.append(loop.diagnostics(now_ns))


def _run(loop: RuntimeLoop, start_ns: int, seconds: float, source: str,
         rng: np.random.Generator, recv_offset_ns: int = 0) -> _Tally:
    """``seconds`` of 1 kHz inputs and a 100 Hz measured centerline from ``start_ns``.

    Received 0.1-0.6 ms after the stamp (plus ``recv_offset_ns``); ``'fixed'`` stepping
    also gets the timer at :meth:`RuntimeLoop.timer_period_ns` on the reception clock.
    """
    tally = _Tally()
    pred = loop.predictor
    fixed = pred.config.stepping == 'fixed'
    period = loop.timer_period_ns()
    next_tick = None
    for j in range(int(round(seconds * 1000))):
        t = start_ns + j * H_NS
        now = t + recv_offset_ns + int(rng.uniform(0.1, 0.6) * 1e6)
        u = 1e4 * (0.5 + 0.4 * np.sin(2e-3 * np.pi * j + np.arange(M)))
        if source == 'chambers':        # each chamber stamps with its own jitter
            for i in rng.permutation(M):
                stamp = t + int(rng.uniform(-0.2, 0.2) * 1e6)
                tally.add(loop, loop.on_channel(int(i), float(u[i]), stamp, now), now)
        else:
            tally.add(loop, loop.on_array(u, t if source == 'array' else 0, now), now)
        if j % 10 == 5:                # the measured centerline, as points
            pts = np.stack([pred.output()[:P // 2], np.zeros(P // 2),
                            pred.output()[P // 2:]], axis=1)
            tally.add(loop, loop.on_measured(pts, t - 5 * H_NS, now), now)
        if fixed and (next_tick is None or now >= next_tick or now < next_tick - period):
            next_tick = now + period
            tally.add(loop, loop.tick(now), now)
    return tally


@pytest.mark.parametrize('stepping', ['event', 'fixed'])
@pytest.mark.parametrize('source', ['array', 'chambers', 'unstamped'])
def test_every_publisher_continues_after_the_clock_restarts(stepping: str, source: str) -> None:
    """A bag played again (stamps and the node's /clock 20 s back): nothing goes quiet."""
    rng = np.random.default_rng(7)
    pred = Predictor(MODEL, PredictorConfig(stepping=stepping))
    loop = RuntimeLoop(pred, LoopSettings(output_rate_hz=100.0, centerline_rate_hz=30.0,
                                          diagnostics_rate_hz=4.0))
    first = _run(loop, T0_NS + 20 * S_NS, 1.0, source, rng)
    again = _run(loop, T0_NS, 1.0, source, rng)           # the clock restarted, 20 s back
    assert pred.counters['clock_reset'] == 1
    for tally in (first, again):
        assert 98 <= len(tally.outputs) <= 101             # ~/output decimated to 100 Hz
        assert 29 <= len(tally.centerlines) <= 31          # ~/centerline and markers, 30 Hz
        assert tally.measured_markers >= len(tally.centerlines) - 1
        assert tally.errors >= len(tally.centerlines) - 2  # ~/error with it
        assert 4 <= len(tally.diagnostics) <= 5            # /diagnostics at 4 Hz
    stamps = np.array(again.outputs + again.centerlines)
    assert np.all((stamps >= T0_NS - S_NS // 100) & (stamps <= T0_NS + S_NS))  # on the new
    assert np.all(np.diff(again.outputs) > 0)                                   # clock
    assert pred.t_ns is not None and abs(pred.t_ns - (T0_NS + S_NS)) <= 20 * H_NS
    last = again.diagnostics[-1]
    assert last.level in (int(Level.OK), int(Level.WARN)), last.message
    assert dict(last.values)['clock_reset'] == '1'


@pytest.mark.parametrize('stepping', ['event', 'fixed'])
def test_diagnostics_continue_when_only_the_reception_clock_goes_back(stepping: str) -> None:
    """The node's clock (use_sim_time) jumps 30 s back; the sensors' stamps go on."""
    rng = np.random.default_rng(8)
    pred = Predictor(MODEL, PredictorConfig(stepping=stepping))
    loop = RuntimeLoop(pred, LoopSettings(output_rate_hz=100.0, diagnostics_rate_hz=4.0))
    _run(loop, T0_NS, 1.0, 'array', rng, recv_offset_ns=30 * S_NS)
    later = _run(loop, T0_NS + S_NS, 1.0, 'array', rng)          # received 30 s "earlier"
    assert 4 <= len(later.diagnostics) <= 5
    if stepping == 'event':            # the stamps drive the model: nothing restarted
        assert pred.counters['clock_reset'] == 0
        assert 98 <= len(later.outputs) <= 101 and 29 <= len(later.centerlines) <= 31


def test_fixed_stepping_reanchors_when_its_clock_restarts() -> None:
    """``'fixed'``: the timer's clock alone goes 20 s back (no inputs): model time follows."""
    pred = Predictor(MODEL, PredictorConfig(stepping='fixed'))
    loop = RuntimeLoop(pred, LoopSettings(output_rate_hz=100.0, centerline_rate_hz=30.0))
    pred.set_input_ns(np.full(M, 5e3), T0_NS + 20 * S_NS)
    outputs = []
    for start in (T0_NS + 20 * S_NS, T0_NS):
        before = len(outputs)
        for j in range(1, 101):                            # 1 s of 10 ms timer ticks
            outputs += [t for t, _ in loop.tick(start + j * 10 * H_NS).outputs]
        assert len(outputs) - before == 100
    assert pred.counters['clock_reset'] == 1
    assert outputs[-1] == pred.t_ns == T0_NS + S_NS
    # a measurement stamped 2 s in the past never restarts the clock (only the driver does)
    pred.measure_ns(pred.output(), T0_NS - S_NS)
    assert pred.counters['clock_reset'] == 1 and pred.t_ns == T0_NS + S_NS


@pytest.mark.parametrize('stepping', ['event', 'fixed'])
def test_an_alarm_before_the_restart_keeps_its_age_on_the_new_clock(stepping: str) -> None:
    """A WARN raised on the old clock lasts ``alarm_hold_s``, not the jump back (20 s)."""
    pred = Predictor(MODEL, PredictorConfig(stepping=stepping, alarm_hold_s=2.0))
    start = T0_NS + 20 * S_NS
    for j in range(3000):                                  # clipped 1e308 at 2 s before the end
        pred.set_input_ns(np.full(M, 1e308 if j == 1000 else 5e3), start + j * H_NS)
    assert pred.health().level == Level.WARN and 'clipped' in pred.health().message
    for j in range(500):                                   # the clock restarts, 20 s back
        pred.set_input_ns(np.full(M, 5e3), T0_NS + j * H_NS)
        pred.advance_to_ns(T0_NS + j * H_NS)
    assert pred.counters['clock_reset'] == 1
    assert pred.health().level == Level.OK, pred.health().message     # 2.5 s old: expired


# -- measurements stamped ahead of the inputs ---------------------------------------------
def test_measurements_far_ahead_are_dropped_and_counted_not_queued() -> None:
    """1 kHz inputs, a 100 Hz measured centerline on a clock 60 s ahead, 20 s long."""
    rng = np.random.default_rng(9)
    loop = RuntimeLoop(Predictor(MODEL), LoopSettings(diagnostics_rate_hz=1.0))
    pred = loop.predictor
    for j in range(20_000):
        t = T0_NS + j * H_NS
        now = t + int(rng.uniform(0.1, 0.6) * 1e6)
        loop.on_array(np.full(M, 5e3), t, now)
        if j % 10 == 0:
            loop.on_measured(pred.output(), t + 60 * S_NS, now)
            assert pred.health().values['measured_queued'] == 0        # never grows
    assert pred.counters['measured_dropped'] == 2000
    assert pred.counters['measurements'] == 0
    d = loop.diagnostics(T0_NS + 20 * S_NS)
    assert d.level == int(Level.WARN)
    assert 'ahead of the model time' in d.message and 'clock_reset_s' in d.message
    assert dict(d.values)['measured_dropped'] == '2000'
    assert loop.measured_points() is None                  # none shown as accepted


@pytest.mark.parametrize('ahead_ms', [0, 50, 400])
def test_measurements_near_ahead_wait_and_are_compared(ahead_ms: int) -> None:
    """The camera's frames arrive before the pressures of their step: queued, compared."""
    pred = Predictor(MODEL, PredictorConfig(error_window=1000, error_window_s=10.0))
    U = 1e4 * np.abs(np.sin(np.arange(3000)[None, :] * 2e-3 + np.arange(M)[:, None]))
    Y = MODEL.simulate(U)
    ahead = ahead_ms
    for j in range(3000):
        pred.set_input_ns(U[:, j], T0_NS + j * H_NS)
        if j % 10 == 0 and j + ahead < 3000:              # sent `ahead` steps early
            pred.measure_ns(Y[:, j + ahead], T0_NS + (j + ahead) * H_NS)
    assert pred.counters['measured_dropped'] == 0
    assert pred.counters['measurements'] == len(range(0, 3000 - ahead, 10))
    assert pred.windowed_error() <= 1e-9
    assert pred.health().values['measured_queued'] == 0


def test_measurement_queue_is_bounded_without_a_horizon() -> None:
    """``clock_reset_s = 0`` (no horizon): at most MAX_QUEUED_MEASUREMENTS wait."""
    pred = Predictor(MODEL, PredictorConfig(clock_reset_s=0.0))
    pred.set_input_ns(np.full(M, 5e3), T0_NS)
    y = pred.output()
    n = MAX_QUEUED_MEASUREMENTS + 100
    for j in range(n):                                     # 1 kHz, 60 s ahead
        pred.measure_ns(y, T0_NS + 60 * S_NS + j * H_NS)
    assert pred.health().values['measured_queued'] == MAX_QUEUED_MEASUREMENTS
    assert pred.counters['measured_dropped'] == 100
    assert 'measurements already wait' in pred.health().message
    pred.reset()                                            # a reset empties the queue
    assert pred.health().values['measured_queued'] == 0


@pytest.mark.parametrize('stepping', ['fixed', 'input'])
def test_measurement_far_ahead_does_not_jump_a_clocked_model(stepping: str) -> None:
    pred = Predictor(MODEL, PredictorConfig(stepping=stepping))
    pred.set_input_ns(np.full(M, 5e3), T0_NS)
    assert pred.measure_ns(pred.output(), T0_NS + 60 * S_NS) is None
    assert pred.t_ns == T0_NS and pred.counters['clock_jump'] == 0
    assert pred.counters['measured_dropped'] == 1
    assert pred.measure_ns(pred.output(), T0_NS + 5 * H_NS) is not None   # near: compared
    assert pred.t_ns == T0_NS + 5 * H_NS


# -- 1e308 ---------------------------------------------------------------------------------
@pytest.mark.parametrize('action', ['clip', 'drop'])
def test_1e308_everywhere_follows_the_envelope_action_without_a_warning(action: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter('error')                     # any RuntimeWarning fails
        loop = RuntimeLoop(Predictor(MODEL, PredictorConfig(input_envelope_action=action)))
        pred = loop.predictor
        hi = pred.envelopes.u_hi
        assert hi is not None
        loop.on_array(np.full(M, 5e3), T0_NS, T0_NS)
        loop.on_array(np.full(M, 1e308), T0_NS + H_NS, T0_NS + H_NS)       # every value
        loop.on_array([1e308] + [5e3] * (M - 1), T0_NS + 2 * H_NS, T0_NS + 2 * H_NS)
        loop.on_array(np.full(M, -1e308), T0_NS + 3 * H_NS, T0_NS + 3 * H_NS)
        if action == 'clip':
            assert pred.counters['input_clipped'] == 2 * M + 1
            np.testing.assert_array_equal(pred.u, pred.envelopes.u_lo)
        else:
            assert pred.counters['input_out_of_envelope'] == 3
            np.testing.assert_array_equal(pred.u, np.full(M, 5e3))
        assert pred.counters['nonfinite'] == 0
        loop.on_array([np.inf] + [0.0] * (M - 1), T0_NS + 4 * H_NS, T0_NS + 4 * H_NS)
        loop.on_array([0.0, np.nan] + [0.0] * (M - 2), T0_NS + 5 * H_NS, T0_NS + 5 * H_NS)
        assert pred.counters['nonfinite'] == 2             # still NaN/Inf
        # the measured centerline of 1e308: outside the output envelope, dropped and said
        before = pred.counters['measured_dropped']
        loop.on_measured(np.full((P // 2, 3), 1e308), T0_NS + 5 * H_NS, T0_NS + 5 * H_NS)
        loop.on_measured(np.full(P, -1e308), T0_NS + 5 * H_NS, T0_NS + 5 * H_NS)
        assert pred.counters['measured_dropped'] == before + 2
        assert 'outside the output envelope' in pred.health().message
        loop.on_measured(np.full(P, np.inf), T0_NS + 5 * H_NS, T0_NS + 5 * H_NS)
        assert pred.counters['measured_dropped'] == before + 3
