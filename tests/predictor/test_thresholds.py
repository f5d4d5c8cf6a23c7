"""Monitor thresholds from the model's held-out error, the old defaults for older files."""

from __future__ import annotations

import numpy as np
import pytest

from soft_rom.data import Episode
from soft_rom.errors import ConfigError
from soft_rom.models import load_model, SecondOrderModel
from soft_rom.predictor import Level, Predictor, PredictorConfig, replay_episode
from soft_rom.predictor.thresholds import (
    DEFAULT_ERROR,
    DEFAULT_WARN,
    ERROR_FACTOR,
    held_out_error,
    Thresholds,
    WARN_FACTOR,
)

DT = 1e-3


def _model(held_out: dict | None = None, *, stiff: float = 1.0) -> SecondOrderModel:
    rng = np.random.default_rng(3)
    r, m, p = 4, 2, 6
    M = rng.standard_normal((r, r))
    K = stiff * (M @ M.T / r + 4.0 * np.eye(r)) * 100.0
    meta = {} if held_out is None else {'held_out': held_out}
    return SecondOrderModel(K, 0.5 * np.eye(r) + 0.01 * K, rng.standard_normal((r, m)),
                            rng.standard_normal((p, r)), dt=DT, y_ref=np.linspace(0, 1, p),
                            metadata=meta)


def _episode(truth: SecondOrderModel, k: int = 3000, seed: int = 5) -> Episode:
    rng = np.random.default_rng(seed)
    U = np.repeat(rng.standard_normal((truth.n_inputs, k // 100 + 1)), 100, axis=1)[:, :k]
    return Episode(t=np.arange(k) * DT, U=U, Y=truth.simulate(U), name='ep')


HELD = {'deviation_error': 0.05, 'absolute_error': 0.002, 'data': 'tails'}


def test_defaults_are_multiples_of_the_held_out_error() -> None:
    thr = Thresholds(_model(HELD), PredictorConfig())
    assert thr.warn == pytest.approx(WARN_FACTOR * 0.05)
    assert thr.error == pytest.approx(ERROR_FACTOR * 0.05)
    assert thr.held_out == 0.05 and 'held-out deviation error 0.05' in thr.source
    absolute = Thresholds(_model(HELD), PredictorConfig(error_metric='absolute'))
    assert absolute.warn == pytest.approx(WARN_FACTOR * 0.002)


def test_files_without_a_held_out_error_keep_the_former_defaults(tmp_path) -> None:
    model = _model()
    path = tmp_path / 'old.npz'
    model.save(path)
    loaded = load_model(path)
    assert held_out_error(loaded) is None
    thr = Thresholds(loaded, PredictorConfig())
    assert (thr.warn, thr.error) == (DEFAULT_WARN, DEFAULT_ERROR) == (0.1, 0.3)
    assert 'no held-out error' in thr.source


@pytest.mark.parametrize('held', [
    {'deviation_error': float('nan')}, {'deviation_error': -1.0}, {'deviation_error': 0.0},
    {'deviation_error': 'big'}, {'deviation_error': True}, {'absolute_error': 0.1}, [0.1],
])
def test_unusable_held_out_errors_fall_back_to_the_defaults(held) -> None:
    model = _model()
    model.metadata['held_out'] = held
    thr = Thresholds(model, PredictorConfig())
    assert (thr.warn, thr.error) == (DEFAULT_WARN, DEFAULT_ERROR)


def test_a_threshold_set_by_hand_wins_and_the_other_keeps_the_order() -> None:
    model = _model(HELD)                                   # auto: 0.1 / 0.2
    both = Thresholds(model, PredictorConfig(warn_threshold=0.3, error_threshold=0.5))
    assert (both.warn, both.error, both.source) == (0.3, 0.5, 'set')
    warn = Thresholds(model, PredictorConfig(warn_threshold=0.3))
    assert (warn.warn, warn.error) == (0.3, 0.3)            # error raised to the warn level
    error = Thresholds(model, PredictorConfig(error_threshold=0.08))
    assert (error.warn, error.error) == (0.08, 0.08)        # warn lowered to the error level
    with pytest.raises(ConfigError, match='must not exceed'):
        PredictorConfig(warn_threshold=0.5, error_threshold=0.1)


def test_health_says_ok_for_the_model_and_warns_for_a_mismatched_one() -> None:
    truth = _model()
    ep = _episode(truth)
    # A good model: the truth itself with its (small) held-out error recorded.
    good = _model({'deviation_error': 0.02})
    pred = Predictor(good, PredictorConfig())
    res = replay_episode(pred, ep, track_health=True)
    assert res.summary['relative_deviation_error'] < 1e-9
    assert pred.health().level == Level.OK
    # The same file at another stiffness: predicts markedly worse than it was shown to.
    wrong = _model({'deviation_error': 0.02}, stiff=1.5)
    pred = Predictor(wrong, PredictorConfig())
    res = replay_episode(pred, ep, track_health=True)
    assert res.summary['relative_deviation_error'] > 5 * 0.02
    health = pred.health()
    assert health.level in (Level.WARN, Level.ERROR)
    assert 'x the held-out error 0.02' in health.message
    assert health.values['warn_threshold'] == pytest.approx(0.04)
    assert pred.info['monitor']['held_out_error'] == 0.02      # in ~/model_info too


def test_thresholds_follow_a_reload_and_a_metric_change(tmp_path) -> None:
    pred = Predictor(_model(HELD), PredictorConfig())
    assert pred.thresholds.warn == pytest.approx(0.1)
    pred.set_config(pred.config.replace(error_metric='absolute'))
    assert pred.thresholds.warn == pytest.approx(WARN_FACTOR * 0.002)
    path = tmp_path / 'other.npz'
    _model({'deviation_error': 0.2, 'absolute_error': 0.01}).save(path)
    pred.reload(path)
    assert pred.thresholds.warn == pytest.approx(WARN_FACTOR * 0.01)
    assert pred.info['monitor']['warn_threshold'] == pytest.approx(WARN_FACTOR * 0.01)
