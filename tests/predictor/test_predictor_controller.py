"""The predictor inside a controller's own loop (no ROS): references, threads, bad data."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from soft_rom.errors import ConfigError
from soft_rom.models import SecondOrderModel
from soft_rom.predictor import Level, Predictor, PredictorConfig

DT = 1e-3
T0_NS = 1_700_000_000_000_000_000


def _model(r: int = 4, m: int = 3, p: int = 8, seed: int = 0) -> SecondOrderModel:
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((r, r))
    K = (M @ M.T / r + 4.0 * np.eye(r)) * 100.0
    return SecondOrderModel(K, 0.5 * np.eye(r) + 0.01 * K, rng.standard_normal((r, m)),
                            rng.standard_normal((p, r)), dt=DT, y_ref=rng.standard_normal(p))


def _inputs(model: SecondOrderModel, k: int, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal((model.n_inputs, k))


def test_kept_state_references_stay_the_state_of_their_step() -> None:
    model = _model()
    U = _inputs(model, 200)
    _, X = model.simulate(U, return_states=True)
    pred = Predictor(model)
    kept = []
    for j in range(U.shape[1]):
        pred.set_input_ns(U[:, j], T0_NS + j * 1_000_000)
        kept.append(pred.x)                 # no copy, as a controller's history would
    np.testing.assert_allclose(np.array(kept).T, X, rtol=0, atol=1e-12 * np.abs(X).max())


def test_output_writes_nothing_the_stepping_uses() -> None:
    model = _model()
    pred = Predictor(model, PredictorConfig(kalman=True))
    pred.set_input_ns(np.ones(model.n_inputs), T0_NS)
    before = {k: v.copy() for k, v in vars(pred).items() if isinstance(v, np.ndarray)}
    y = pred.output()
    y[:] = np.nan                          # the caller owns what it got
    after = {k: v for k, v in vars(pred).items() if isinstance(v, np.ndarray)}
    assert before.keys() == after.keys()
    for key, value in before.items():
        np.testing.assert_array_equal(after[key], value, err_msg=key)
    assert np.isfinite(pred.output()).all()


def test_a_reader_thread_does_not_disturb_the_stepping_thread() -> None:
    model = _model()
    U = _inputs(model, 5000)
    Y = model.simulate(U)
    pred = Predictor(model)
    stop = threading.Event()

    def reader() -> None:
        while not stop.is_set():
            pred.output()

    th = threading.Thread(target=reader)
    th.start()
    try:
        out = np.empty_like(Y)
        for j in range(U.shape[1]):
            pred.set_input_ns(U[:, j], T0_NS + j * 1_000_000)
            out[:, j] = pred.output()
    finally:
        stop.set()
        th.join()
    assert np.abs(out - Y).max() <= 1e-12 * np.abs(Y).max()
    assert pred.counters['diverged'] == 0


def _running(kalman: bool = True) -> tuple[SecondOrderModel, Predictor, np.ndarray]:
    model = _model()
    U = _inputs(model, 50)
    pred = Predictor(model, PredictorConfig(kalman=kalman))
    for j in range(U.shape[1]):
        pred.set_input_ns(U[:, j], T0_NS + j * 1_000_000)
    return model, pred, model.simulate(U)[:, -1]


def test_an_occluded_marker_drops_the_measurement_and_says_so() -> None:
    model, pred, y = _running()
    x = pred.x
    y_occluded = y.copy()
    y_occluded[[1, 5]] = np.nan
    assert pred.measure_ns(y_occluded, T0_NS + 49_000_000) is None
    assert pred.counters['measured_dropped'] == 1 and pred.counters['measurements'] == 0
    assert pred.x is x                      # no correction from a partial measurement
    health = pred.health()
    assert health.level == Level.WARN
    assert 'measurement with 2 NaN/Inf value(s) of 8 dropped' in health.message
    assert pred.measure_ns(y, T0_NS + 49_000_000) is not None   # a whole one is used


def test_a_measurement_of_wrong_length_or_time_is_dropped_with_the_reason() -> None:
    model, pred, y = _running()
    assert pred.measure_ns(y[:-1], T0_NS + 49_000_000) is None
    assert 'measurement of shape (7,) dropped; the model has 8 outputs' in pred.health().message
    assert pred.health().level == Level.WARN
    _, pred, y = _running()
    assert pred.measure(y, float('nan')) is None
    assert pred.measure_ns(y, 1.7e18) is None                    # float where int ns is due
    assert pred.counters['measured_dropped'] == 2
    assert ('time 1.7e+18 is a float; the *_ns methods take an int of nanoseconds'
            in pred.health().message)


def test_a_caller_whose_every_input_is_dropped_is_told_why() -> None:
    """Every input dropped (shape (m, 1), NaN, float-ns stamps): health says why.

    It said only "no value yet on input(s) ... (holding 0)" (no accepted stamp: the alarm
    was never shown), and a shape (m, 1) was called "input of length m, expected m".
    """
    model = _model()
    m = model.n_inputs
    cases = [(lambda p, j: p.set_input(np.ones((m, 1)), j * 1e-3),
              f'input of shape ({m}, 1), expected ({m},)'),
             (lambda p, j: p.set_input(np.full(m, np.nan), j * 1e-3), 'input with NaN/Inf'),
             (lambda p, j: p.set_input_ns(np.ones(m), j * 1e6),
              'is a float; the *_ns methods take an int of nanoseconds')]
    for feed, why in cases:
        pred = Predictor(model)
        for j in range(20):
            assert not feed(pred, j)
        health = pred.health()
        assert health.level == Level.STALE
        assert why in health.message, health.message
        assert 'no value yet' in health.message


def test_reset_clears_the_alarms_before_it() -> None:
    """After a manual reset, the drops before it still showed in health.

    Until the next input (no time known), and within alarm_hold_s after it too.
    """
    model = _model()
    m = model.n_inputs
    for accepted_first in (True, False):
        pred = Predictor(model)
        if accepted_first:
            assert pred.set_input_ns(np.zeros(m), 1_000_000_000)
        assert not pred.set_input_ns(np.zeros(m + 1), 1_001_000_000)
        assert not pred.set_input_ns(np.full(m, np.nan), 1_002_000_000)
        assert 'dropped' in pred.health().message
        pred.reset()
        health = pred.health()
        assert 'dropped' not in health.message and 'NaN' not in health.message, health.message
        assert health.level == Level.STALE and 'no value yet' in health.message
        assert pred.set_input_ns(np.zeros(m), 1_003_000_000)
        assert pred.health().level == Level.OK, pred.health().message


def test_something_that_is_not_a_model_is_one_type_error() -> None:
    """``Predictor(42)`` was "AttributeError: 'int' object has no attribute 'dt'"."""
    for bad in (42, np.eye(3), None):
        with pytest.raises(TypeError, match=f'the predictor needs a model .*got '
                                            f'{type(bad).__name__}'):
            Predictor(bad)


def test_numpy_scalars_are_settings_and_times_like_python_numbers() -> None:
    """Numpy scalars work as settings and as ``health(now)`` times.

    ``rate_hz=np.int64(100)`` was refused as "must be a finite number >= 0", and
    ``health(np.float32(t))`` ignored ``t`` (not a Python float) and reported at the newest
    stamp instead (OK where the inputs were silent for 4 s: STALE).
    """
    cfg = PredictorConfig(rate_hz=np.int64(1000), error_window=np.int64(50),
                          kalman=np.bool_(False), warn_threshold=np.float32(0.25))
    assert (cfg.rate_hz, cfg.error_window, cfg.kalman) == (1000, 50, False)
    assert type(cfg.error_window) is int and type(cfg.warn_threshold) is float
    assert cfg == PredictorConfig(rate_hz=1000, error_window=50, kalman=False,
                                  warn_threshold=float(np.float32(0.25)))
    with pytest.raises(ConfigError, match='error_window must be an integer >= 1'):
        PredictorConfig(error_window=np.float64(2.5))
    model = _model()
    pred = Predictor(model)
    assert pred.set_input(np.zeros(model.n_inputs), 1.0)
    assert pred.health(5.0).level == Level.STALE
    for now in (np.float64(5.0), np.float32(5.0)):
        assert pred.health(now).level == Level.STALE, now
    assert pred.health(np.float32(1.0)).level != Level.STALE
