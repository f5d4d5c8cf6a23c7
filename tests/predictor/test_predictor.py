"""Predictor core: exact replay, stepping modes, bad inputs, monitor, Kalman, atomic reload."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from soft_rom.data import Episode
from soft_rom.errors import ConfigError, ModelFileError, SoftRomWarning
from soft_rom.models import DiscreteModel, SecondOrderModel
from soft_rom.predictor import (
    kalman_gain,
    kalman_vs_open_loop,
    Level,
    Predictor,
    PredictorConfig,
    replay_episode,
)

DT = 1e-3


def _second_order(r: int = 6, m: int = 3, p: int = 8, seed: int = 0,
                  stiff: float = 1.0) -> SecondOrderModel:
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((r, r))
    K = stiff * (M @ M.T / r + 4.0 * np.eye(r)) * 100.0
    C = 0.5 * np.eye(r) + 0.01 * K
    B = rng.standard_normal((r, m))
    E = rng.standard_normal((p, r))
    return SecondOrderModel(K, C, B, E, dt=DT, y_ref=rng.standard_normal(p),
                            input_names=[f'chamber_{i + 1}' for i in range(m)])


def _discrete(r: int = 5, m: int = 2, p: int = 4, seed: int = 1) -> DiscreteModel:
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((r, r)))
    A = Q @ np.diag(np.linspace(0.5, 0.95, r)) @ Q.T
    return DiscreteModel(A, rng.standard_normal((r, m)), rng.standard_normal((p, r)),
                         rng.standard_normal((p, m)), dt=0.01, method='dmdc',
                         y_ref=rng.standard_normal(p))


def _episode(model, k: int = 400, seed: int = 2, t0: float = 3.0) -> Episode:
    rng = np.random.default_rng(seed)
    U = np.repeat(rng.standard_normal((model.n_inputs, k // 20 + 1)), 20, axis=1)[:, :k]
    t = t0 + np.arange(k) * model.dt
    return Episode(t=t, U=U, Y=model.simulate(U), name='ep')


@pytest.mark.parametrize('stepping', ['fixed', 'input'])
@pytest.mark.parametrize('make', [_second_order, _discrete])
def test_replay_equals_simulate(make, stepping: str) -> None:
    model = make()
    ep = _episode(model)
    res = replay_episode(Predictor(model, PredictorConfig(stepping=stepping)), ep)
    scale = np.abs(ep.Y).max()
    assert np.abs(res.Y - ep.Y).max() <= 1e-12 * scale
    assert res.summary['relative_error'] <= 1e-12
    assert Predictor(model).counters['steps'] == 0


def test_replay_of_times_in_ms_warns_and_slow_sampling_does_not() -> None:
    """Times in ms replayed on a 1 ms model were a deviation error of ~1.4 without a word."""
    model = _second_order()
    ep = _episode(model, t0=0.0)
    ms = Episode(t=ep.t * 1e3, U=ep.U, Y=ep.Y, name='ms')
    with pytest.warns(SoftRomWarning, match=r"'ms' is sampled every 1 s .* factor of 1e\+03\): "
                      r'are the episode times in seconds\?'):
        res = replay_episode(Predictor(model), ms)
    assert res.summary['relative_deviation_error'] > 0.1       # replayed as given
    slow = Episode(t=ep.t[::100], U=ep.U[:, ::100], Y=ep.Y[:, ::100], name='10 Hz')
    with warnings.catch_warnings():
        warnings.simplefilter('error')       # a 10 Hz recording on a 1 ms model is legitimate
        replay_episode(Predictor(model), slow)


def test_replay_of_an_empty_or_all_zero_episode_is_not_perfect() -> None:
    """An empty episode was relative errors of 0.0, as if predicted perfectly."""
    model = _second_order()
    empty = Episode(t=np.zeros(0), U=np.zeros((3, 0)), Y=np.zeros((8, 0)), name='empty')
    res = replay_episode(Predictor(model), empty)
    assert math.isnan(res.summary['relative_error'])
    assert math.isnan(res.summary['relative_deviation_error'])
    ep = _episode(model)        # outputs at the reference throughout, predictions moving
    still = Episode(t=ep.t, U=ep.U, Y=np.repeat(model.y_ref[:, None], ep.t.size, 1), name='z')
    assert math.isnan(replay_episode(Predictor(model), still).summary[
        'relative_deviation_error'])
    rest = Episode(t=ep.t, U=np.zeros_like(ep.U), Y=still.Y, name='rest')
    assert replay_episode(Predictor(model), rest).summary['relative_deviation_error'] == 0.0


def test_input_stepping_is_exact_for_irregular_stamps() -> None:
    model = _second_order()
    pred = Predictor(model, PredictorConfig(stepping='input'))
    u0, u1 = np.array([1.0, -2.0, 0.5]), np.array([0.0, 3.0, 1.0])
    pred.set_input(u0, 10.0)
    pred.set_input(u1, 10.0037)     # 3.7 native steps with u0 held
    pred.advance_to(10.0112)        # 7.5 more with u1
    A1, B1, *_ = model.discretize(0.0037)
    A2, B2, *_ = model.discretize(0.0075)
    x = A2 @ (B1 @ u0) + B2 @ u1
    np.testing.assert_allclose(pred.x, x, rtol=1e-12, atol=1e-15)
    assert pred.t == pytest.approx(10.0112, abs=1e-12)


def test_discrete_model_carries_the_remainder() -> None:
    model = _discrete()
    pred = Predictor(model, PredictorConfig(stepping='input'))
    u = np.array([1.0, 2.0])
    pred.set_input(u, 0.0)
    assert pred.advance_to(0.025) == 2          # 2.5 native steps: 2 taken
    assert pred.t == pytest.approx(0.02)
    assert pred.advance_to(0.031) == 1          # remainder 0.005 + 0.006 -> one more
    A, B = model.A, model.B
    x = np.zeros(model.r)
    for _ in range(3):
        x = A @ x + B @ u
    np.testing.assert_allclose(pred.x, x, rtol=1e-13)


def test_fixed_rate_decimated_and_bad_rates() -> None:
    model = _discrete()
    pred = Predictor(model, PredictorConfig(rate_hz=50.0))    # 2 native steps per step
    assert pred.h == pytest.approx(0.02)
    with pytest.raises(ConfigError, match='whole'):
        Predictor(model, PredictorConfig(rate_hz=30.0))
    cont = Predictor(_second_order(), PredictorConfig(rate_hz=400.0))
    assert cont.h == pytest.approx(0.0025)
    with pytest.raises(ConfigError):
        PredictorConfig(stepping='sometimes')
    with pytest.raises(ConfigError):
        PredictorConfig(warn_threshold=0.5, error_threshold=0.1)
    with pytest.raises(ConfigError, match='unknown'):
        PredictorConfig.from_mapping({'rate': 1})


def test_bad_inputs_have_defined_behaviour() -> None:
    model = _second_order()
    pred = Predictor(model, PredictorConfig(stepping='fixed', input_timeout_s=0.5,
                                           alarm_hold_s=0.5))
    h = pred.health(0.0)
    assert h.level == Level.STALE and 'no value yet' in h.message
    good = np.array([1.0, 2.0, 3.0])
    assert pred.set_input(good, 1.0)
    # wrong length: dropped, counted, value held
    assert not pred.set_input(np.ones(4), 1.1)
    assert pred.counters['wrong_length'] == 1
    np.testing.assert_array_equal(pred.u, good)
    assert not pred.set_channel(7, 1.0, 1.1)
    assert pred.counters['wrong_length'] == 2
    # NaN / Inf: dropped, counted, value held
    assert not pred.set_input(np.array([1.0, np.nan, 0.0]), 1.1)
    assert not pred.set_channel(0, math.inf, 1.1)
    assert pred.counters['nonfinite'] == 2
    np.testing.assert_array_equal(pred.u, good)
    # a drop within the timeout makes the health WARN
    pred.advance_to(1.2)
    h = pred.health(1.2)
    assert h.level == Level.WARN and 'dropped' in h.message
    # stamps going backwards: dropped, counted
    assert not pred.set_input(np.zeros(3), 0.9)
    assert not pred.set_channel(1, 0.0, 0.9)
    assert pred.counters['backwards'] == 2
    np.testing.assert_array_equal(pred.u, good)
    # per-channel: one channel updated, the others held
    assert pred.set_channel(1, -5.0, 1.3)
    np.testing.assert_array_equal(pred.u, [1.0, -5.0, 3.0])
    # silence: held, STALE naming the silent channels
    pred.advance_to(1.7)
    h = pred.health(1.7)
    assert h.level == Level.STALE
    assert 'chamber_1' in h.message and 'chamber_3' in h.message
    assert 'chamber_2' not in h.message
    np.testing.assert_array_equal(pred.u, [1.0, -5.0, 3.0])
    assert h.values['input_age.chamber_1'] == pytest.approx(0.7)
    # fresh inputs: OK again
    pred.set_input(good, 2.05)
    assert pred.health(2.1).level == Level.OK
    # measurement of wrong length / NaN: dropped
    assert pred.measure(np.ones(3), 2.1) is None
    assert pred.measure(np.full(model.n_outputs, np.nan), 2.1) is None
    assert pred.counters['measured_dropped'] == 2


def test_late_channel_is_applied_from_model_time() -> None:
    pred = Predictor(_second_order(), PredictorConfig(stepping='input'))
    pred.set_channel(0, 1.0, 5.0)
    pred.set_channel(1, 1.0, 5.01)
    assert pred.set_channel(2, 2.0, 5.005)     # newer for channel 2, older than the model
    assert pred.counters['late'] == 1
    assert pred.u[2] == 2.0 and pred.t == pytest.approx(5.01)


@pytest.mark.filterwarnings('ignore::RuntimeWarning')
def test_diverged_state_resets_and_reports_error() -> None:
    model = DiscreteModel(np.array([[1e200]]), np.ones((1, 1)), np.ones((1, 1)), dt=0.1)
    pred = Predictor(model)
    pred.set_input([1e200], 0.0)
    pred.advance_to(1.0)
    assert pred.counters['diverged'] >= 1
    assert np.all(np.isfinite(pred.x))
    assert pred.health(1.0).level == Level.ERROR
    pred.reset()
    assert pred.health(1.0).level != Level.ERROR


def test_monitor_thresholds_and_window() -> None:
    model = _second_order()
    cfg = PredictorConfig(stepping='fixed', error_window=10, warn_threshold=0.05,
                          error_threshold=0.2)
    pred = Predictor(model, cfg)
    pred.set_input(np.zeros(3), 0.0)
    y0 = model.y_ref
    d = np.ones(model.n_outputs)
    # measured = y_ref + d, predicted = y_ref: deviation error exactly 1
    for j in range(10):
        err = pred.measure(y0 + d, j * DT)
    assert err == pytest.approx(1.0)
    e_abs, e_dev = pred.windowed_errors()
    assert e_abs == pytest.approx(np.linalg.norm(d) / np.linalg.norm(y0 + d))
    assert pred.health(10 * DT).level == Level.ERROR
    # 10 perfect measurements flush the window
    for j in range(10, 20):
        err = pred.measure(pred.output(), j * DT)
    assert err == pytest.approx(0.0, abs=1e-12)
    assert pred.health(20 * DT).level == Level.OK
    pred.reset()
    assert math.isnan(pred.windowed_error())


def test_a_body_at_rest_against_a_moving_prediction_is_not_an_error_of_zero() -> None:
    # measured centerline exactly at y_ref (a noise-free simulated body at rest) while the
    # model moves: the deviation error's reference norm is 0; it read 0.0 and health OK
    model = _second_order()
    pred = Predictor(model, PredictorConfig(stepping='fixed', error_window=10))
    pred.set_input(np.full(3, 5.0), 0.0)
    for j in range(20):
        pred.measure(model.y_ref, j * DT)
    assert np.linalg.norm(pred.output() - model.y_ref) > 0
    assert math.isinf(pred.windowed_errors()[1])
    health = pred.health(20 * DT)
    assert health.level == Level.ERROR and 'exactly 0' in health.message
    # and exact at rest is still an error of 0
    rest = Predictor(model, PredictorConfig(stepping='fixed', error_window=10))
    rest.set_input(np.zeros(3), 0.0)
    for j in range(20):
        rest.measure(model.y_ref, j * DT)
    assert rest.windowed_errors()[1] == 0.0 and rest.health(20 * DT).level == Level.OK


def test_initial_state_from_measurement() -> None:
    model = _second_order(p=8, r=6)
    q = np.linspace(-1, 1, 6)
    y = model.E @ q + model.y_ref
    pred = Predictor(model, PredictorConfig(initial_state='measured'))
    pred.set_input(np.zeros(3), 0.0)
    pred.measure(y, 0.0)
    np.testing.assert_allclose(pred.x[:6], q, rtol=1e-10)
    np.testing.assert_allclose(pred.output(), y, rtol=1e-10)
    assert pred.windowed_error() == pytest.approx(0.0, abs=1e-10)
    pred.reset()
    assert np.all(pred.x == 0)


def test_kalman_gain_matches_riccati() -> None:
    model = _discrete()
    A, C = model.A, model.C
    Q, R = 1e-2 * np.eye(5), 1e-1 * np.eye(4)
    L = kalman_gain(A, C, Q, R)
    # fixed point of the Riccati recursion
    P = np.eye(5)
    for _ in range(2000):
        S = C @ P @ C.T + R
        P = A @ (P - P @ C.T @ np.linalg.solve(S, C @ P)) @ A.T + Q
    np.testing.assert_allclose(L, P @ C.T @ np.linalg.inv(C @ P @ C.T + R), rtol=1e-8)


def test_kalman_halves_error_of_mismatched_model() -> None:
    true = _second_order(r=6, m=3, p=8, seed=3)
    wrong = SecondOrderModel(true.K * 1.3, true.C * 0.7, true.B * 1.15, true.E, dt=DT,
                             y_ref=true.y_ref)
    ep = _episode(true, k=1500, seed=4)
    rng = np.random.default_rng(5)
    sigma = 0.02 * np.std(ep.Y - true.y_ref[:, None])
    noisy = Episode(ep.t, ep.U, ep.Y + sigma * rng.standard_normal(ep.Y.shape))
    cfg = PredictorConfig(process_noise=1e-6, measurement_noise=sigma ** 2)
    res = kalman_vs_open_loop(wrong, noisy, config=cfg, Y_true=ep.Y)
    assert res['open_loop'] > 0.05            # the mismatch is real
    assert res['kalman'] <= 0.5 * res['open_loop']
    assert res['ratio'] == pytest.approx(res['kalman'] / res['open_loop'])


def test_reload_is_atomic(tmp_path) -> None:
    a, b = _second_order(seed=0), _second_order(seed=9, r=4)
    path_b = b.save(tmp_path / 'b.npz')
    pred = Predictor(a)
    pred.set_input(np.ones(3), 0.0)
    pred.advance_to(0.05)
    x_before = pred.x.copy()
    bad = tmp_path / 'bad.npz'
    bad.write_bytes(b'not a zip')
    with pytest.raises(ModelFileError):
        pred.reload(bad)
    with pytest.raises(FileNotFoundError):
        pred.reload(tmp_path / 'missing.npz')
    with pytest.raises(ConfigError):
        pred.reload(_discrete(m=3), PredictorConfig(rate_hz=33.0))
    assert pred.model is a
    np.testing.assert_array_equal(pred.x, x_before)
    pred.reload(path_b)
    assert pred.model.r == 4 and pred.x.shape == (8,) and np.all(pred.x == 0)
    np.testing.assert_array_equal(pred.u, np.ones(3))       # same m: inputs held
    assert pred.info['sha256'] and pred.info['r'] == 4
    assert pred.t == pytest.approx(0.05)


def test_catchup_is_bounded() -> None:
    pred = Predictor(_second_order(), PredictorConfig(max_catchup_steps=100))
    pred.set_input(np.zeros(3), 0.0)
    assert pred.advance_to(10.0) == 100
    assert pred.counters['catchup_skipped'] == 10000 - 100
    assert pred.t == pytest.approx(10.0)


def test_set_config_keeps_state_unless_the_design_changes() -> None:
    model = _second_order()
    pred = Predictor(model)
    pred.set_input(np.ones(3), 0.0)
    pred.advance_to(0.02)
    x = pred.x.copy()
    pred.set_config(pred.config.replace(warn_threshold=0.01, error_threshold=0.02))
    np.testing.assert_array_equal(pred.x, x)
    assert pred.config.warn_threshold == 0.01
    pred.set_config(pred.config.replace(error_window=5))
    np.testing.assert_array_equal(pred.x, x)
    with pytest.raises(ConfigError):
        pred.set_config(pred.config.replace(stepping='input', rate_hz=-1.0))
    np.testing.assert_array_equal(pred.x, x)
    pred.set_config(pred.config.replace(kalman=True))
    assert pred.info['r'] == model.r and np.all(pred.x == 0)
    assert pred.t == pytest.approx(0.02)


def test_restarted_clock_resets_instead_of_dropping_forever() -> None:
    pred = Predictor(_second_order(), PredictorConfig(clock_reset_s=1.0))
    pred.set_input(np.ones(3), 50.0)
    pred.set_input(np.ones(3), 60.0)
    assert not pred.set_input(np.zeros(3), 59.5)        # small step back: dropped
    assert pred.counters['backwards'] == 1
    assert pred.set_input(np.full(3, 2.0), 0.0)         # bag played again from 0 s
    assert pred.counters['clock_reset'] == 1
    assert pred.t == 0.0 and np.all(pred.x == 0) and np.all(pred.u == 2.0)
    strict = Predictor(_second_order(), PredictorConfig(clock_reset_s=0.0))
    strict.set_input(np.ones(3), 50.0)
    assert not strict.set_input(np.ones(3), 0.0)
    assert strict.counters['backwards'] == 1
