"""Event-time stepping, int64-ns time, envelopes and the runtime loop (ROS-free)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from soft_rom.data import Episode
from soft_rom.errors import ModelFileError
from soft_rom.models import DiscreteModel, SecondOrderModel
from soft_rom.predictor import Level, Predictor, PredictorConfig, training_envelope
from soft_rom.predictor.loop import LoopSettings, RuntimeLoop

DT = 1e-3
H_NS = 1_000_000
T0_NS = 1_700_000_000 * 1_000_000_000          # an epoch stamp: 1.7e9 s


def _model(r: int = 4, m: int = 6, p: int = 10, seed: int = 0) -> SecondOrderModel:
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((r, r))
    K = (M @ M.T / r + 4.0 * np.eye(r)) * 100.0
    y_ref = np.concatenate([np.linspace(0.0, 0.4, p // 2), np.zeros(p - p // 2)])
    return SecondOrderModel(K, 0.5 * np.eye(r) + 0.01 * K, rng.standard_normal((r, m)),
                            0.01 * rng.standard_normal((p, r)), dt=DT, y_ref=y_ref,
                            input_names=[f'chamber_{i + 1}' for i in range(m)])


def _discrete(m: int = 6, seed: int = 1) -> DiscreteModel:
    rng = np.random.default_rng(seed)
    r, p = 5, 4
    Q, _ = np.linalg.qr(rng.standard_normal((r, r)))
    A = Q @ np.diag(np.linspace(0.5, 0.95, r)) @ Q.T
    return DiscreteModel(A, rng.standard_normal((r, m)), rng.standard_normal((p, r)),
                         rng.standard_normal((p, m)), dt=DT, method='dmdc',
                         y_ref=rng.standard_normal(p))


def _inputs(m: int, k: int, seed: int = 2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.repeat(rng.standard_normal((m, k // 7 + 1)), 7, axis=1)[:, :k]


def _arrivals(k: int, m: int, seed: int, jitter: float = 0.2, delay_ms: float = 3.0):
    """Per-chamber messages ``(arrival_ns, channel, step, stamp_ns)`` in arrival order.

    Each chamber stamps with jitter up to ``jitter`` steps (±200 µs at 1 kHz; below h/4,
    so no stamp is nearer another step of the grid started by the first) and its messages
    reach the node in its own order (a ROS topic is FIFO) after a random transport delay of
    up to ``delay_ms``; across chambers the order is arbitrary (chamber 1 of step j+2 may come
    before chamber 6 of step j).
    """
    rng = np.random.default_rng(seed)
    msgs = []
    for i in range(m):
        stamps = T0_NS + np.arange(k) * H_NS + np.round(
            rng.uniform(-jitter, jitter, k) * H_NS).astype(np.int64)
        arrive = np.maximum.accumulate(stamps + np.round(
            rng.uniform(0, delay_ms, k) * 1e6).astype(np.int64))
        msgs += [(int(a), i, j, int(s)) for j, (a, s) in enumerate(zip(arrive, stamps))]
    msgs.sort()
    return msgs


@pytest.mark.parametrize(('make', 'delay_ms'), [(_model, 3.0), (_discrete, 3.0),
                                               (_model, 60.0)])
def test_six_chambers_in_any_order_equal_simulate(make, delay_ms: float) -> None:
    model = make()
    k = 1500
    U = _inputs(6, k)
    Y = model.simulate(U)
    msgs = _arrivals(k, 6, seed=3, delay_ms=delay_ms)      # delays within max_lag_s (0.1 s)
    first = [j for _, _, j, _ in msgs[:40]]
    assert sorted(first) != first                      # really out of order across chambers
    loop = RuntimeLoop(Predictor(model), LoopSettings(components='xz'
                                                      if model.n_outputs % 2 == 0 else 'x'))
    got: list[tuple[int, np.ndarray]] = []
    for arrive, i, j, stamp in msgs:
        got += loop.on_channel(i, U[i, j], stamp, arrive).outputs
    pred = loop.predictor
    assert pred.counters['late'] == 0 and pred.counters['lag_forced'] == 0
    assert pred.counters['timeouts'] == 0 and pred.counters['backwards'] == 0
    assert len(got) == k                                # ~/output every step, in order
    start = got[0][0]                                   # the grid of the first stamp
    assert abs(start - T0_NS) <= 0.2 * H_NS
    assert [t for t, _ in got] == [start + j * H_NS for j in range(k)]   # exact int ns
    Yhat = np.array([y for _, y in got]).T
    assert np.abs(Yhat - Y).max() <= 1e-12 * np.abs(Y).max()


@pytest.mark.slow
def test_ten_minutes_at_an_epoch_one_step_per_input() -> None:
    model = _model(r=2, m=3, p=4)
    k = 600_000                                         # 10 min at 1 kHz
    U = _inputs(3, k, seed=4)
    Y = model.simulate(U)
    pred = Predictor(model)
    out = np.empty((k, 4))
    y = np.empty(4)
    Ut = np.ascontiguousarray(U.T)
    steps = []
    for j in range(k):
        pred.set_input_ns(Ut[j], T0_NS + j * H_NS)
        out[j] = pred.output(y)
        if j % 1000 == 0:
            steps.append(pred.counters['steps'])
    assert pred.counters['steps'] == k - 1
    assert np.all(np.diff(steps) == 1000)               # one step per input throughout
    assert pred.t_ns == T0_NS + (k - 1) * H_NS
    assert np.abs(out.T - Y).max() <= 1e-12 * np.abs(Y).max()
    # float seconds at the epoch (0.24 us resolution) with a clock: still one step each
    fixed = Predictor(model, PredictorConfig(stepping='fixed'))
    taken = set()
    for j in range(20_000):
        t = 1.7e9 + j * DT
        taken.add(fixed.advance_to(t))
        fixed.set_input(Ut[j], t)
        out[j] = fixed.output(y)
    assert taken == {0, 1} and fixed.counters['steps'] == 20_000 - 1
    assert np.abs(out[:20_000].T - Y[:, :20_000]).max() <= 1e-12 * np.abs(Y).max()


def test_watermark_timeout_and_lag() -> None:
    model = _model(m=3)
    cfg = PredictorConfig(input_timeout_s=0.05, max_lag_s=0.02)
    pred = Predictor(model, cfg)
    for j in range(10):                                  # all three chambers: steps 0..9
        for i in range(3):
            pred.set_channel_ns(i, 1.0, T0_NS + j * H_NS)
    assert pred.t_ns == T0_NS + 9 * H_NS
    # chamber 3 falls behind by 5 steps: the model waits for it (never past the watermark)
    for j in range(10, 15):
        pred.set_channel_ns(0, 1.0, T0_NS + j * H_NS)
        pred.set_channel_ns(1, 1.0, T0_NS + j * H_NS)
    assert pred.t_ns == T0_NS + 9 * H_NS
    pred.set_channel_ns(2, 2.0, T0_NS + 12 * H_NS)       # it catches up to 12: model too
    assert pred.t_ns == T0_NS + 12 * H_NS and pred.counters['late'] == 0
    # it stays silent: beyond the lag (20 ms) the model advances with its value held
    for j in range(15, 40):
        pred.set_channel_ns(0, 1.0, T0_NS + j * H_NS)
        pred.set_channel_ns(1, 1.0, T0_NS + j * H_NS)
        assert T0_NS + j * H_NS - pred.t_ns <= 20 * H_NS
    assert pred.counters['lag_forced'] > 0 and pred.u[2] == 2.0
    # beyond the timeout it no longer holds back at all: STALE, counted, named
    for j in range(40, 80):
        pred.set_channel_ns(0, 1.0, T0_NS + j * H_NS)
        pred.set_channel_ns(1, 1.0, T0_NS + j * H_NS)
    assert pred.t_ns == T0_NS + 79 * H_NS
    assert pred.counters['timeouts'] == 1 and pred.channels.timed_out == [False, False, True]
    h = pred.health(T0_NS + 79 * H_NS)
    assert h.level == Level.STALE and 'chamber_3' in h.message
    # back: it holds the model again, late values counted once
    assert pred.set_channel_ns(2, 3.0, T0_NS + 80 * H_NS)
    assert pred.channels.timed_out[2] is False and pred.u[2] == 2.0      # step 80 not taken
    pred.set_channel_ns(0, 1.0, T0_NS + 80 * H_NS)
    pred.set_channel_ns(1, 1.0, T0_NS + 80 * H_NS)
    assert pred.t_ns == T0_NS + 80 * H_NS and pred.u[2] == 3.0


# -- bad values ----------------------------------------------------------------------------
def _trained(model: SecondOrderModel, U: np.ndarray) -> SecondOrderModel:
    """The model with the training envelope of ``U`` recorded, as a fit does."""
    meta = {'envelope': training_envelope([(U, model.simulate(U))], model.y_ref)}
    return SecondOrderModel(model.K, model.C, model.B, model.E, dt=model.dt, y_ref=model.y_ref,
                            input_names=model.input_names, metadata=meta)


@pytest.mark.parametrize('action', ['clip', 'drop'])
def test_absurd_pressure_is_clipped_or_dropped(action: str) -> None:
    model = _model(m=3)
    U = 1e4 * _inputs(3, 2000, seed=5)                   # pressures of ~10 kPa
    model = _trained(model, U)
    env = model.metadata['envelope']
    assert len(env['u_min']) == 3 and env['y_dev_max'] > 0
    pred = Predictor(model, PredictorConfig(input_envelope_action=action))
    for j in range(100):
        u = U[:, j].copy()
        if 40 <= j < 50:
            u[1] = 1e308                                 # 10 ms of 1e308 Pa
        pred.set_input_ns(u, T0_NS + j * H_NS)
        dev = np.abs(pred.output() - model.y_ref).max()
        assert dev <= pred.envelopes.y_bound
    key = 'input_clipped' if action == 'clip' else 'input_out_of_envelope'
    assert pred.counters[key] == 10 and pred.counters['diverged'] == 0
    h = pred.health(T0_NS + 99 * H_NS)
    assert h.level == Level.WARN and 'envelope' in h.message
    lo, hi = pred.envelopes.u_lo, pred.envelopes.u_hi
    width = np.array(env['u_max']) - np.array(env['u_min'])
    np.testing.assert_allclose(hi, np.array(env['u_max']) + width)     # margin 1 x width
    np.testing.assert_allclose(lo, np.array(env['u_min']) - width)


@pytest.mark.filterwarnings('ignore:overflow:RuntimeWarning')
def test_absurd_pressure_on_an_old_model_file_is_caught_as_divergence() -> None:
    model = _model(m=3)                                  # no envelope recorded (old file)
    pred = Predictor(model)
    assert pred.envelopes.u_lo is None
    bound = pred.envelopes.y_bound
    assert bound == pytest.approx(100 * 0.4)             # 100 x max |y_ref|
    worst = 0.0
    for j in range(200):
        u = np.zeros(3)
        if 40 <= j < 50:
            u[1] = 1e308
        pred.set_input_ns(u, T0_NS + j * H_NS)
        worst = max(worst, float(np.abs(pred.output() - model.y_ref).max()))
    assert math.isfinite(worst) and worst <= bound      # never 4e299 m
    assert pred.counters['diverged'] >= 1
    assert pred.health(T0_NS + 60 * H_NS).level == Level.ERROR
    assert 'diverged' in pred.health(T0_NS + 60 * H_NS).message
    assert pred.health(T0_NS + 199 * H_NS + 3 * 10 ** 9).level != Level.ERROR   # recovered


def test_unstable_model_without_measurements_is_an_error_long_before_overflow() -> None:
    A = 1.05 * np.eye(2)
    model = DiscreteModel(A, np.ones((2, 1)), np.eye(2), dt=DT, y_ref=np.array([0.3, 0.1]))
    pred = Predictor(model, PredictorConfig(auto_reset=False))
    assert pred.health(0).level >= Level.WARN
    worst = 0.0
    for j in range(2000):
        pred.set_input_ns([1.0], T0_NS + j * H_NS)
        worst = max(worst, float(np.abs(pred.output()).max()))
    assert pred.counters['diverged'] == 1               # counted once while it stays out
    h = pred.health(T0_NS + 1999 * H_NS)
    assert h.level == Level.ERROR and 'diverged' in h.message and 'unstable' in h.message
    # with auto-reset the prediction never leaves the envelope by more than one step
    pred = Predictor(model)
    for j in range(2000):
        pred.set_input_ns([1.0], T0_NS + j * H_NS)
        worst = float(np.abs(pred.output() - model.y_ref).max())
        assert worst <= 1.05 * pred.envelopes.y_bound + 1.0
    assert pred.counters['diverged'] > 1


def test_absurd_measurement_is_dropped_and_the_error_never_nan() -> None:
    model = _model(m=3)
    pred = Predictor(model, PredictorConfig(error_window=50))
    pred.set_input_ns(np.zeros(3), T0_NS)
    y = pred.output()
    bad = y.copy()
    bad[3] = 1e200
    assert pred.measure_ns(bad, T0_NS) is None
    assert pred.counters['measured_dropped'] == 1
    assert pred.health(T0_NS).level == Level.WARN       # said, not silently OK
    off = y + 0.05                                       # then 50 measurements 5 cm off
    for j in range(1, 51):
        pred.set_input_ns(np.zeros(3), T0_NS + j * H_NS)
        err = pred.measure_ns(off, T0_NS + j * H_NS)
    assert err is not None and math.isfinite(err) and err > 0.3
    assert pred.health(T0_NS + 50 * H_NS).level == Level.ERROR


def test_error_expires_with_time_and_goes_stale() -> None:
    model = _model(m=3)
    pred = Predictor(model, PredictorConfig(error_window_s=0.5))
    for j in range(100):
        pred.set_input_ns(np.zeros(3), T0_NS + j * H_NS)
        pred.measure_ns(pred.output() + 0.05, T0_NS + j * H_NS)
    assert pred.health(T0_NS + 100 * H_NS).level == Level.ERROR
    # measurements stop, inputs go on: after 0.5 s the window is empty -> STALE, not ERROR
    for j in range(100, 800):
        pred.set_input_ns(np.zeros(3), T0_NS + j * H_NS)
    h = pred.health(T0_NS + 799 * H_NS)
    assert h.level == Level.STALE and 'no measurement' in h.message
    assert math.isnan(pred.windowed_error(T0_NS + 799 * H_NS))


@pytest.mark.parametrize('stepping', ['fixed', 'event', 'input'])
def test_clock_stall_of_60_s_is_reported(stepping: str) -> None:
    pred = Predictor(_model(m=3), PredictorConfig(stepping=stepping, max_catchup_steps=10000))
    pred.set_input_ns(np.zeros(3), T0_NS)
    pred.advance_to_ns(T0_NS + 10 * H_NS)
    assert pred.health(T0_NS + 10 * H_NS).level == Level.OK
    later = T0_NS + 60 * 10 ** 9                         # the clock resumes 60 s later
    pred.set_input_ns(np.zeros(3), later)
    assert pred.counters['clock_jump'] == 1
    assert pred.counters['catchup_skipped'] == 60_000 - 10 - 10_000
    assert pred.t_ns == later
    h = pred.health(later)
    assert h.level == Level.WARN and 'clock stalled or jumped' in h.message


@pytest.mark.parametrize('stepping', ['event', 'fixed', 'input'])
def test_non_finite_times_are_refused_without_freezing_or_raising(stepping: str) -> None:
    pred = Predictor(_model(m=3), PredictorConfig(stepping=stepping))
    assert pred.advance_to(math.nan) == 0 and pred.t is None        # before the first input
    assert pred.advance_to(math.inf) == 0 and pred.advance_to(-math.inf) == 0
    assert pred.advance_to_ns(2 ** 63) == 0
    assert not pred.set_input(np.ones(3), math.nan)
    assert not pred.set_channel(0, 1.0, math.inf)
    assert pred.measure(pred.output(), math.nan) is None
    assert pred.counters['bad_time'] == 6
    assert 'time not finite or out of range' in pred.health().message     # said, counted
    assert pred.set_input(np.ones(3), 1.0) and pred.t == 1.0          # not frozen
    assert pred.advance_to(math.inf) == 0 and pred.t == 1.0
    assert pred.set_input(np.ones(3), 1.001) and pred.t == pytest.approx(1.001, abs=1e-12)
    assert pred.health(math.nan).level in tuple(Level)


# -- the runtime loop ----------------------------------------------------------------------
def test_loop_schedules_outputs_centerline_and_diagnostics() -> None:
    model = _model(m=3)
    k = 1000
    U = _inputs(3, k, seed=6)
    Y = model.simulate(U)
    loop = RuntimeLoop(Predictor(model), LoopSettings(centerline_rate_hz=30.0,
                                                      diagnostics_rate_hz=4.0))
    outputs, centerlines, diags = [], [], []
    for j in range(k):
        t = T0_NS + j * H_NS
        pub = loop.on_array(U[:, j], t, t + 200_000)       # received 0.2 ms later
        pub2 = loop.on_measured(Y[:, j], t, t + 300_000)
        outputs += pub.outputs
        if pub.centerline is not None:
            centerlines.append(pub.centerline[0])
            assert pub.centerline[1].shape == (5, 3)
        for p in (pub, pub2):
            if p.diagnostics_due:
                diags.append(loop.diagnostics(t + 300_000))
    assert len(outputs) == k
    assert np.abs(np.array([y for _, y in outputs]).T - Y).max() <= 1e-12
    gaps = np.diff(centerlines)
    assert len(centerlines) == 31 and np.all(gaps == 33 * H_NS)       # <= 30 Hz
    assert len(diags) == 4
    kv = dict(diags[-1].values)
    assert float(kv['input.chamber_1.rate_hz']) == pytest.approx(1000.0, rel=0.01)
    assert float(kv['measured.rate_hz']) == pytest.approx(1000.0, rel=0.01)
    assert kv['input.chamber_2.late'] == '0' and kv['input.chamber_3.timed_out'] == 'false'
    assert float(kv['input.chamber_1.age_s']) == pytest.approx(1e-4, abs=1e-7)   # received
    assert float(kv['input.chamber_1.stamp_lag_s']) == 0.0
    assert diags[-1].level == int(Level.OK)
    assert loop.timer_period_ns() == 250_000_000         # event stepping: diagnostics only


def test_sensor_clock_far_from_the_node_clock_is_fine_until_messages_stop() -> None:
    model = _model(m=3)
    loop = RuntimeLoop(Predictor(model, PredictorConfig(input_timeout_s=0.1)))
    offset = 3 * 3600 * 10 ** 9                         # the sensors stamp 3 h behind the node
    U = _inputs(3, 500, seed=8)
    for j in range(500):
        t = T0_NS + j * H_NS
        loop.on_array(U[:, j], t - offset, t)
        loop.on_measured(loop.predictor.output(), t - offset, t)
    d = loop.diagnostics(T0_NS + 500 * H_NS)
    assert d.level == int(Level.OK), d.message
    d = loop.diagnostics(T0_NS + 800 * H_NS)             # 0.3 s without a message
    assert d.level == int(Level.STALE) and 'nothing received' in d.message
    d = loop.diagnostics(T0_NS + 3000 * H_NS)            # and no measurement for 2.5 s
    assert 'no measurement received' in d.message


def test_stalled_sensor_clock_is_reported() -> None:
    loop = RuntimeLoop(Predictor(_model(m=3), PredictorConfig(input_timeout_s=0.1)))
    for j in range(400):                                 # stamps stop at step 100
        stamp = T0_NS + min(j, 100) * H_NS
        loop.on_array(np.zeros(3), stamp, T0_NS + j * H_NS)
    d = loop.diagnostics(T0_NS + 400 * H_NS)
    assert d.level == int(Level.WARN) and 'stamps not advancing' in d.message
    assert loop.predictor.counters['late'] == 299       # each repeat applied from now on


def test_loop_reload_and_settings_at_run_time(tmp_path) -> None:
    from soft_rom.errors import ModelFileError

    model = _model(m=3)
    loop = RuntimeLoop(Predictor(model))
    for j in range(50):
        loop.on_array(np.ones(3), T0_NS + j * H_NS, T0_NS + j * H_NS)
    x = loop.predictor.x.copy()
    bad = tmp_path / 'bad.npz'
    bad.write_bytes(b'not a zip')
    with pytest.raises(ModelFileError):
        loop.reload(bad)
    odd = _model(m=3, p=9)                                # 9 outputs do not split into xz
    with pytest.raises(ValueError, match='components'):
        loop.reload(odd)
    assert loop.predictor.model is model and np.array_equal(loop.predictor.x, x)
    loop.replace_settings(output_rate_hz=100.0)
    outs = []
    for j in range(50, 100):
        outs += loop.on_array(np.ones(3), T0_NS + j * H_NS, T0_NS + j * H_NS).outputs
    assert [t for t, _ in outs] == [T0_NS + j * H_NS for j in range(50, 100, 10)]
    assert loop.diagnostics(T0_NS + 100 * H_NS).level == int(Level.OK)
    loop.set_config(loop.predictor.config.replace(warn_threshold=0.05))
    assert np.array_equal(loop.predictor.u, np.ones(3))
    path = _model(m=3, seed=4).save(tmp_path / 'new.npz')
    loop.reload(path)
    assert loop.predictor.info['sha256'] and loop.predictor.t_ns == T0_NS + 99 * H_NS
    outs = loop.on_array(np.ones(3), T0_NS + 100 * H_NS, T0_NS + 100 * H_NS).outputs
    assert [t for t, _ in outs] == [T0_NS + 100 * H_NS]


def test_unstamped_arrays_follow_the_senders_sequence_not_the_reception_jitter() -> None:
    model = _model(m=3)
    k = 3000
    U = _inputs(3, k, seed=10)
    Y = model.simulate(U)
    rng = np.random.default_rng(11)
    sent = T0_NS + np.arange(k) * H_NS
    recv = sent + rng.integers(50_000, 900_000, k)       # 0.05 .. 0.9 ms transport jitter
    for a in (500, 1500, 2500):                          # executor stalls of 30 ms: bunches
        recv[a:a + 30] = recv[a + 30]
    recv = np.maximum.accumulate(recv)
    loop = RuntimeLoop(Predictor(model))
    got = []
    for j in range(k):
        got += loop.on_array(U[:, j], 0, int(recv[j])).outputs
    pred = loop.predictor
    assert loop.counts['stamp_fallback'] == k
    assert pred.counters['late'] == 0
    times = np.array([t for t, _ in got])
    assert len(got) == k and np.all(np.diff(times) == H_NS)     # one step per message
    Yhat = np.array([y for _, y in got]).T
    assert np.abs(Yhat - Y).max() <= 1e-12 * np.abs(Y).max()
    kv = dict(loop.diagnostics(int(recv[-1])).values)
    assert kv['stamp_resync'] == '0'
    # the sender pauses for 1 s, then sends at its rate again: no burst catches the sequence
    # up, so after 16 messages it is re-synchronised to the reception clock, counted once
    after = int(recv[-1]) + 10 ** 9
    for j in range(50):
        loop.on_array(U[:, 0], 0, after + j * H_NS)
    assert dict(loop.diagnostics(after + 50 * H_NS).values)['stamp_resync'] == '1'
    assert abs(loop.predictor.t_ns - (after + 49 * H_NS)) <= H_NS // 2      # on its grid


def test_unstamped_slower_sender_gets_its_own_period() -> None:
    loop = RuntimeLoop(Predictor(_model(m=3)))
    rng = np.random.default_rng(12)
    recv = T0_NS + np.arange(300) * 10 * H_NS + rng.integers(0, 2 * H_NS, 300)   # 100 Hz
    times = []
    for a in recv.tolist():
        loop.on_array(np.zeros(3), 0, a)
        times.append(loop.predictor.t_ns)
    steps = np.diff(times[50:])
    assert np.all(steps == 10 * H_NS)                    # one sender period per message
    assert abs(times[-1] - int(recv[-1])) <= 100 * H_NS  # never far from the reception clock


def test_unstamped_sender_faster_than_the_model_never_runs_ahead_or_back() -> None:
    from soft_rom.predictor.loop import SequenceClock

    clock = SequenceClock(H_NS, 100 * H_NS)
    stamps = [clock.stamp(T0_NS + j * H_NS // 2) for j in range(2000)]     # 2 kHz sender
    assert all(b >= a for a, b in zip(stamps, stamps[1:]))                  # never backwards
    lead = max(s - (T0_NS + j * H_NS // 2) for j, s in enumerate(stamps))
    assert lead <= 101 * H_NS and clock.resyncs > 0


def test_loop_zero_stamp_falls_back_to_reception_time_and_scales_inputs() -> None:
    model = _model(m=3)
    loop = RuntimeLoop(Predictor(model), LoopSettings(input_scale=1e-3, input_offset=1.0))
    loop.on_array(np.array([1000.0, 2000.0, 3000.0]), 0, T0_NS)
    assert loop.predictor.t_ns == T0_NS and loop.counts['stamp_fallback'] == 1
    np.testing.assert_allclose(loop.predictor.u, [2.0, 3.0, 4.0])
    loop.on_channel(0, 0.0, T0_NS + H_NS, T0_NS)
    np.testing.assert_allclose(loop.predictor.u[0], 2.0)             # step 1 not complete


def test_a_late_input_stamped_after_its_grid_time_has_a_positive_lag() -> None:
    # a held-up chamber stamping 0.1 ms after the grid catches up with a model that
    # max_lag_s pushed on: its input for the step already put out is late, and its lag was
    # its stamp against that step's grid time: '-0.1 ms behind the model'
    import re

    model = _model(m=3)
    loop = RuntimeLoop(Predictor(model, PredictorConfig(max_lag_s=0.1)))
    for j in range(200):
        for i in (0, 1) if j >= 50 else (0, 1, 2):
            loop.on_channel(i, 1.0, T0_NS + j * H_NS + (100_000 if i == 2 else 0), T0_NS)
    lags = []
    for j in range(50, 200):                        # the held-up chamber's backlog
        loop.on_channel(2, 1.0, T0_NS + j * H_NS + 100_000, T0_NS)
        got = re.search(r'\(the last: input chamber_3, ([-0-9.e]+) ms behind the model\)',
                        loop.predictor.health().message)
        if got:
            lags.append(float(got.group(1)))
    late = loop.predictor.counters['late']
    assert late == 50 and lags, lags                # steps 50..99: the model was at 99
    assert min(lags) == 1.0 and max(lags) == 50.0, (min(lags), max(lags))   # 99 + 1 - 50


def test_loop_drops_inputs_stamped_ahead_of_their_reception_and_keeps_the_others() -> None:
    # one chamber on another clock, 100 s ahead: before, the model's event time followed it
    # (clock_jump, 100 s skipped), the other chambers timed out and every value of theirs
    # was applied late
    model = _model(m=3)
    loop = RuntimeLoop(Predictor(model), LoopSettings())
    pred = loop.predictor
    k = 800                                         # beyond input_timeout_s (0.5 s)
    for j in range(k):
        now = T0_NS + j * H_NS + 200_000            # received 0.2 ms after its stamp
        for i in range(3):
            loop.on_channel(i, float(i + 1), T0_NS + j * H_NS + (100 * 10**9 if i == 2 else 0),
                            now)
    assert pred.t_ns is not None and T0_NS + (k - 2) * H_NS <= pred.t_ns <= T0_NS + k * H_NS
    assert pred.counters['input_ahead'] == k and pred.counters['clock_jump'] == 0
    assert pred.counters['late'] == 0 and pred.channels.late == [0, 0, 0]
    assert pred.channels.dropped == [0, 0, k] and pred.channels.received[2] == 0
    np.testing.assert_allclose(pred.u, [1.0, 2.0, 0.0])     # never used
    values = dict(loop.diagnostics(T0_NS + k * H_NS).values)
    assert values['input.chamber_3.ahead'] == str(k)
    assert float(values['input.chamber_3.ahead_s']) == pytest.approx(100.0 - 2e-4)
    assert values['input.chamber_1.ahead'] == '0' and values['input.chamber_1.ahead_s'] == 'nan'
    assert 'chamber_3 stamped 100 s ahead of the reception clock' in pred.health().message
    # the sensor back on the node's clock: taken, and no longer said to be ahead
    loop.on_channel(2, 3.0, T0_NS + k * H_NS, T0_NS + k * H_NS + 200_000)
    assert pred.channels.received[2] == 1
    assert dict(loop.diagnostics(T0_NS + (k + 1) * H_NS).values)['input.chamber_3.ahead_s'] \
        == 'nan'
    # stamped far behind the reception clock (a bag played without its clock): kept, as a
    # zero reception time (sim time before the first /clock) checks nothing
    for now in (T0_NS + 3600 * 10**9, 0):
        other = RuntimeLoop(Predictor(model), LoopSettings())
        for i in range(3):
            other.on_channel(i, 1.0, T0_NS, now)
        assert other.predictor.channels.received == [1, 1, 1]
        assert other.predictor.counters['input_ahead'] == 0
    # an array stamped ahead (one sender, one clock): kept, the model runs on its clock
    other = RuntimeLoop(Predictor(model), LoopSettings())
    other.on_array(np.ones(3), T0_NS + 11 * 10**9, T0_NS)
    assert other.predictor.channels.received == [1, 1, 1]
    assert other.predictor.counters['input_ahead'] == 0


def test_loop_keeps_inputs_that_are_all_ahead_on_one_clock() -> None:
    # a robot whose clock runs 3 h ahead of this machine's: every chamber alike, so nothing
    # drags the event time; only the first value, heard before any other chamber, is dropped
    model = _model(m=3)
    ahead = 3 * 3600 * 10**9
    loop = RuntimeLoop(Predictor(model), LoopSettings())
    pred = loop.predictor
    for j in range(300):
        now = T0_NS + j * H_NS + 200_000
        for i in range(3):
            loop.on_channel(i, float(i + 1), T0_NS + ahead + j * H_NS, now)
    assert pred.counters['input_ahead'] == 1 and pred.channels.dropped == [1, 0, 0]
    assert pred.counters['late'] == 0 and pred.counters['timeouts'] == 0
    assert pred.t_ns is not None and pred.t_ns >= T0_NS + ahead + 298 * H_NS
    np.testing.assert_allclose(pred.u, [1.0, 2.0, 3.0])
    # two chambers ahead together, one on the node's clock: the two are on a clock of their
    # own against it, and dropped
    loop = RuntimeLoop(Predictor(model), LoopSettings())
    for j in range(300):
        now = T0_NS + j * H_NS + 200_000
        for i in range(3):
            loop.on_channel(i, 1.0, T0_NS + j * H_NS + (ahead if i else 0), now)
    assert loop.predictor.channels.dropped == [0, 300, 300]
    assert loop.predictor.t_ns is not None and loop.predictor.t_ns < T0_NS + 10**9
    # a single input has no other clock to disagree with
    single = RuntimeLoop(Predictor(_model(m=1)), LoopSettings())
    single.on_channel(0, 1.0, T0_NS + ahead, T0_NS)
    assert single.predictor.channels.received == [1]


class _Cubic:
    """A non-linear model of the predictor protocol (not a LinearROM)."""

    method, r, n_states, n_inputs, n_outputs, dt = 'cubic', 2, 2, 1, 2, DT
    input_names, output_names = ['u1'], ['y1', 'y2']
    input_units, output_units = [''], ['', '']

    def __init__(self) -> None:
        self.y_ref = np.array([0.2, -0.1])
        self.metadata: dict = {}
        self.A = np.array([[0.99, 0.01], [-0.02, 0.98]])

    def initial_state(self) -> np.ndarray:
        return np.zeros(2)

    def stepper(self, h: float):
        A = self.A

        def step(x, u):
            return A @ x - 0.1 * x ** 3 + np.array([u[0], 0.5 * u[0]]) * h * 10
        return step

    def output(self, x, u):
        return x + self.y_ref

    def linearize(self, x, u, h):
        return self.A - 0.3 * np.diag(x ** 2), np.array([[h * 10], [h * 5]]), np.eye(2), \
            np.zeros((2, 1))

    def simulate(self, U):
        step = self.stepper(self.dt)
        x = self.initial_state()
        Y = []
        for u in np.asarray(U).T:
            Y.append(self.output(x, u))
            x = step(x, u)
        return np.array(Y).T

    def state_from_output(self, y, u):
        return np.asarray(y) - self.y_ref


def test_nonlinear_model_protocol_runs_in_the_predictor() -> None:
    model = _Cubic()
    U = 3.0 * _inputs(1, 500, seed=7)
    Y = model.simulate(U)
    res_y = []
    pred = Predictor(model, PredictorConfig(kalman=True))
    for j in range(500):
        pred.set_input_ns(U[:, j], T0_NS + j * H_NS)
        res_y.append(pred.output())
    assert np.abs(np.array(res_y).T - Y).max() <= 1e-12
    assert pred.info['class'] == '_Cubic' and pred.info['stability_margin'] is None


class _SteppedSecondOrder(SecondOrderModel):
    """A LinearROM subclass that says it is non-linear and offers step/step_jacobian only."""

    is_nonlinear = True

    def step(self, x, u, dt=None):
        s = self.discretize(self.dt if dt is None else dt)
        return s.A @ x + s.B @ u + 0.0 * np.tanh(x)          # through the generic path

    def step_jacobian(self, x, u, dt=None):
        s = self.discretize(self.dt if dt is None else dt)
        return self.step(x, u, dt), s.A, s.B


def test_nonlinear_flagged_linear_rom_subclass_takes_the_generic_path() -> None:
    base = _model(m=3)
    model = _SteppedSecondOrder(base.K, base.C, base.B, base.E, dt=DT, y_ref=base.y_ref)
    pred = Predictor(model, PredictorConfig(kalman=True))
    assert not pred._dyn.linear and pred._dyn.L is not None
    U = _inputs(3, 300, seed=9)
    Y = base.simulate(U)
    got = []
    for j in range(300):
        pred.set_input_ns(U[:, j], T0_NS + j * H_NS)
        got.append(pred.output())
    assert np.abs(np.array(got).T - Y).max() <= 1e-12 * np.abs(Y).max()


def test_training_envelope_from_episodes() -> None:
    U = np.array([[0.0, 1.0, -2.0], [5.0, 5.0, 6.0]])
    Y = np.array([[1.0, 1.5, 0.0]])
    env = training_envelope([Episode(t=np.arange(3) * DT, U=U, Y=Y)], y_ref=[1.0])
    assert env == {'u_min': [-2.0, 5.0], 'u_max': [1.0, 6.0], 'y_dev_max': 1.0, 'samples': 3}


def test_untrusted_model_is_reported_and_refused_when_strict(tmp_path) -> None:
    good = _discrete()
    bad = DiscreteModel(1.05 * np.eye(2), np.ones((2, 6)), np.eye(2), dt=good.dt,
                        y_ref=np.array([0.3, 0.1]))
    assert bad.trust_issues() and not good.trust_issues()
    pred = Predictor(bad)
    assert pred.info['trust'] == bad.trust_issues()
    h = pred.health(0)
    assert h.level >= Level.WARN and 'not trusted' in h.message
    path = tmp_path / 'unstable.npz'
    bad.save(path)
    strict = PredictorConfig(strict_model=True)
    with pytest.raises(ModelFileError, match='not trusted'):
        Predictor(path, strict)
    running = Predictor(good, strict)
    assert running.info['trust'] == []
    with pytest.raises(ModelFileError, match='not trusted'):
        running.reload(path)
    assert running.model is good                       # the running model stays


def test_unstamped_sender_that_speeds_up_gets_a_new_step_per_message() -> None:
    # the period estimate from a slow start (10 ms) runs the sequence ahead of a sender that
    # then sends every 3 ms: past the bound each message still gets a step of its own (never
    # joins a step whose output is already out), and never runs far ahead of reception
    loop = RuntimeLoop(Predictor(_model(m=3)))
    recv = np.concatenate([T0_NS + np.arange(40) * 10 * H_NS,
                           T0_NS + 400 * H_NS + np.arange(1, 400) * 3 * H_NS])
    times, outs = [], 0
    for a in recv.tolist():
        outs += len(loop.on_array(np.ones(3), 0, a).outputs)
        times.append(loop.predictor.t_ns)
    assert all(b > a for a, b in zip(times, times[1:]))         # a new step every message
    assert loop.predictor.counters['late'] == 0
    lead = max(t - a for t, a in zip(times, recv.tolist()))
    assert lead <= loop.predictor.config.max_lag_s * 1e9 + H_NS


@pytest.mark.parametrize('stall_ms', [0, 47, 50, 80, 120, 150, 300])
def test_a_stall_of_the_node_keeps_one_step_per_array(stall_ms) -> None:
    # the audit's case: 1,000 un-stamped arrays sent at 1 kHz, received at j ms, but the
    # node stalls at array 100 and then takes the backlog in a burst
    from soft_rom.predictor.loop import SequenceClock
    clock = SequenceClock(1_000_000, 100_000_000, 1_000_000_000)
    recv = [j * H_NS if j < 100 else max(j, 100 + stall_ms) * H_NS for j in range(1000)]
    stamps = np.array([clock.stamp(t) for t in recv])
    assert np.all(np.diff(stamps) == H_NS) and clock.resyncs == 0
    model = _model(m=3)
    U = _inputs(3, 1000, seed=5)
    loop = RuntimeLoop(Predictor(model))
    got = []
    for j, t in enumerate(recv):
        got += loop.on_array(U[:, j], 0, T0_NS + t).outputs
    assert len(got) == 1000 and loop.predictor.counters['steps'] == 999
    Yhat = np.array([y for _, y in got]).T
    np.testing.assert_allclose(Yhat, model.simulate(U), rtol=0, atol=1e-9)


def test_a_rate_change_is_followed_but_a_stall_is_not() -> None:
    from soft_rom.predictor.loop import SequenceClock
    clock = SequenceClock(1_000_000, 100_000_000, 1_000_000_000)
    recv = [j * H_NS for j in range(2000)] + [2000 * H_NS + j * 2 * H_NS for j in range(2000)]
    stamps = np.array([clock.stamp(t) for t in recv])
    assert clock.period == 2 * H_NS                 # the sender now sends at 500 Hz
    assert abs(stamps[-1] - recv[-1]) <= 100 * H_NS   # and the sequence follows it
    assert np.all(np.diff(stamps[-500:]) == 2 * H_NS)


def test_fixed_stepping_publishes_every_step_it_integrates() -> None:
    model = _model(m=3)
    loop = RuntimeLoop(Predictor(model, PredictorConfig(stepping='fixed')))
    times = [t for t, _ in loop.on_array(np.ones(3), T0_NS, T0_NS).outputs]
    for t in (T0_NS, T0_NS + H_NS, T0_NS + 4 * H_NS, T0_NS + 4 * H_NS, T0_NS + 9 * H_NS):
        times += [t for t, _ in loop.tick(t).outputs]
    assert times == [T0_NS + j * H_NS for j in range(10)]
    assert loop.predictor.counters['steps'] == 9
    U = np.ones((3, 10))
    # each published output is the model's at its step (inputs held from t0)
    ref = model.simulate(U)
    loop2 = RuntimeLoop(Predictor(model, PredictorConfig(stepping='fixed')))
    outs = loop2.on_array(np.ones(3), T0_NS, T0_NS).outputs
    outs += loop2.tick(T0_NS).outputs + loop2.tick(T0_NS + 9 * H_NS).outputs
    np.testing.assert_allclose(np.array([y for _, y in outs]).T, ref, rtol=0, atol=1e-12)


def test_late_inputs_are_counted_and_warned_with_the_lag() -> None:
    model = _model(m=3)
    loop = RuntimeLoop(Predictor(model, PredictorConfig(max_lag_s=0.1)))
    for j in range(50):                                # all three in step
        for i in range(3):
            loop.on_channel(i, 0.0, T0_NS + j * H_NS, T0_NS + j * H_NS)
    assert loop.diagnostics(T0_NS + 50 * H_NS).level == int(Level.OK)
    # a pause: chamber 0's backlog of 150 ms is taken first; max_lag_s pushes the model on
    for j in range(50, 200):
        loop.on_channel(0, 1.0, T0_NS + j * H_NS, T0_NS + 200 * H_NS)
    for j in range(50, 200):                           # the others' backlog: many are late
        for i in (1, 2):
            loop.on_channel(i, 1.0, T0_NS + j * H_NS, T0_NS + 200 * H_NS)
    pred = loop.predictor
    late = pred.counters['late']
    assert late > 0 and late == sum(pred.channels.late)
    assert pred.counters['lag_forced'] > 0
    d = loop.diagnostics(T0_NS + 201 * H_NS)
    kv = dict(d.values)
    assert d.level == int(Level.WARN), d.message
    assert f'{late} input(s) arrived after their step was taken' in d.message
    assert 'ms behind the model' in d.message and 'departs from the offline' in d.message
    assert int(kv['input.chamber_2.late']) + int(kv['input.chamber_3.late']) == late
