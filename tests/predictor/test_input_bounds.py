"""``input_min`` / ``input_max``: each bound on its own, one value for every input.

The rule lives in the ROS-free core (:class:`PredictorConfig`, :class:`Envelopes`,
:func:`predictor_config`); the node checks each ``ros2 param set`` against it with the other
bound as it is in force, so that the two can be set one at a time.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from soft_rom.envelope import training_envelope
from soft_rom.errors import ConfigError
from soft_rom.models import SecondOrderModel
from soft_rom.predictor import Predictor, PredictorConfig
from soft_rom.predictor.params import PARAMS, predictor_config

T0_NS = 1_000_000_000
H_NS = 1_000_000


def _model(trained: bool = True) -> SecondOrderModel:
    """A stable 3-input ROM at dt = 1 ms, with the training range [0, 10] per input."""
    rng = np.random.default_rng(4)
    r, m, p = 3, 3, 6
    M = rng.standard_normal((r, r))
    K = (M @ M.T / r + 4.0 * np.eye(r)) * 100.0
    model = SecondOrderModel(K, 0.5 * np.eye(r) + 0.01 * K, rng.standard_normal((r, m)),
                             0.01 * rng.standard_normal((p, r)), dt=1e-3,
                             y_ref=np.linspace(0.0, 1.0, p))
    if not trained:
        return model
    U = np.array([[0.0, 10.0], [0.0, 10.0], [0.0, 10.0]])
    meta = {'envelope': training_envelope([(U, model.simulate(U))], model.y_ref)}
    return SecondOrderModel(model.K, model.C, model.B, model.E, dt=model.dt,
                            y_ref=model.y_ref, metadata=meta)


@pytest.mark.parametrize('bounds', [
    {'input_min': (-1.0, -2.0, -3.0)},                  # one bound alone
    {'input_max': (5.0,)},                              # one value for every input
    {'input_min': (0.0,), 'input_max': (1.0, 2.0, 3.0)},
    {'input_min': (-1.0, -2.0, -3.0), 'input_max': (4.0,)},
    {'input_min': (1.0, 1.0), 'input_max': (1.0, 2.0)},  # equal bounds are fine
])
def test_config_takes_each_bound_alone_or_broadcast(bounds) -> None:
    cfg = PredictorConfig(**bounds)
    for name, value in bounds.items():
        assert getattr(cfg, name) == value


@pytest.mark.parametrize('bounds, words', [
    ({'input_min': (5.0,), 'input_max': (1.0,)}, 'input_min must not exceed input_max: 5 > 1'),
    ({'input_min': (0.0, 7.0), 'input_max': (1.0,)}, 'for input 2: 7 > 1'),
    ({'input_min': (0.0, 0.0), 'input_max': (1.0, 1.0, 1.0)}, 'same number of values'),
    ({'input_min': (float('nan'),)}, 'finite numbers'),
    ({'input_max': ('a',)}, 'list of numbers'),
])
def test_config_refuses_bounds_that_conflict(bounds, words) -> None:
    with pytest.raises(ConfigError, match=words):
        PredictorConfig(**bounds)


def test_envelope_takes_the_other_bound_from_the_training_range() -> None:
    model = _model()                    # training range [0, 10]: margin 1 -> [-10, 20]
    both = Predictor(model).envelopes
    np.testing.assert_array_equal(both.u_lo, [-10.0] * 3)
    np.testing.assert_array_equal(both.u_hi, [20.0] * 3)
    low = Predictor(model, PredictorConfig(input_min=(-1.0,))).envelopes
    np.testing.assert_array_equal(low.u_lo, [-1.0] * 3)          # one value, every input
    np.testing.assert_array_equal(low.u_hi, [20.0] * 3)          # the training side stays
    assert low.input_source.startswith('input_min configured; input_max: training range')
    high = Predictor(model, PredictorConfig(input_max=(1.0, 2.0, 3.0))).envelopes
    np.testing.assert_array_equal(high.u_lo, [-10.0] * 3)
    np.testing.assert_array_equal(high.u_hi, [1.0, 2.0, 3.0])
    assert high.summary()['input_max'] == [1.0, 2.0, 3.0]
    # a bound beyond the other side of the training envelope: refused, saying which input
    with pytest.raises(ConfigError, match=r'input_min must not exceed input_max: input u1 '
                                          r'would get 25 > 20'):
        Predictor(model, PredictorConfig(input_min=(25.0,)))
    with pytest.raises(ConfigError, match='lists 2 values; the model has 3 inputs'):
        Predictor(model, PredictorConfig(input_max=(1.0, 2.0)))


def test_one_bound_without_a_training_range_bounds_one_side() -> None:
    pred = Predictor(_model(trained=False), PredictorConfig(input_min=(-1.0,)))
    env = pred.envelopes
    assert np.all(env.u_hi == np.inf)
    assert env.summary()['input_min'] == [-1.0] * 3 and env.summary()['input_max'] is None
    pred.set_input_ns(np.array([-5.0, 1e6, 0.0]), T0_NS)
    assert pred.counters['input_clipped'] == 1
    np.testing.assert_array_equal(pred.u, [-1.0, 1e6, 0.0])


def test_set_config_one_bound_at_a_time_takes_effect_and_refuses_a_conflict() -> None:
    pred = Predictor(_model())
    cfg = pred.config.replace(input_min=(-1.0, -1.0, -1.0))
    pred.set_config(cfg)
    cfg = cfg.replace(input_max=(1.0,))
    pred.set_config(cfg)
    assert pred.info['envelope']['input_min'] == [-1.0] * 3
    assert pred.info['envelope']['input_max'] == [1.0] * 3
    assert pred.info['envelope']['input_source'] == 'configured'
    pred.set_input_ns(np.array([5.0, 0.5, -3.0]), T0_NS)
    np.testing.assert_array_equal(pred.u, [1.0, 0.5, -1.0])
    assert pred.counters['input_clipped'] == 2
    with pytest.raises(ConfigError, match='must not exceed'):
        pred.set_config(cfg.replace(input_min=(2.0,)))
    assert pred.config == cfg                                     # the running one stays
    np.testing.assert_array_equal(pred.envelopes.u_hi, [1.0] * 3)


def test_model_info_says_whether_the_kalman_correction_is_on() -> None:
    """~/model_info is republished when its content changes: the correction is part of it."""
    pred = Predictor(_model())
    assert pred.info['kalman'] is False
    pred.set_config(pred.config.replace(kalman=True))
    assert pred.info['kalman'] is True


def test_node_default_means_from_the_model_file_per_bound() -> None:
    values = {p.name: p.default for p in PARAMS}
    assert values['input_min'] == [0.0] and values['input_max'] == [0.0]
    cfg = predictor_config(values)
    assert cfg.input_min == () and cfg.input_max == ()
    cfg = predictor_config(dict(values, input_min=[-100.0] * 6))     # input_max unset
    assert cfg.input_min == (-100.0,) * 6 and cfg.input_max == ()
    cfg = predictor_config(dict(values, input_min=[-1.0], input_max=[0.0]))
    assert cfg.input_min == (-1.0,) and cfg.input_max == ()
    cfg = predictor_config(dict(values, input_min=[0.0], input_max=[100.0] * 6))
    assert cfg.input_min == () and cfg.input_max == (100.0,) * 6
    cfg = predictor_config(dict(values, input_min=[0.0, 0.0], input_max=[1.0]))
    assert cfg.input_min == (0.0, 0.0)            # a zero bound written out per input
    with pytest.raises(ConfigError, match='must not exceed'):
        predictor_config(dict(values, input_min=[5.0], input_max=[1.0]))


@pytest.mark.parametrize('lo, hi, ratio', [(-0.001, 0.005, '0.0006'), (-1e5, 1e5, '2e+04')])
def test_an_envelope_in_other_units_than_the_training_range_is_refused(lo, hi, ratio) -> None:
    """Bounds 1000 x off the training range (kPa for Pa) are refused, as the MPC does.

    They clipped every input to a thousandth of its range (a WARN 'clipped' at run time,
    predictions near zero).
    """
    model = _model()                    # training range [0, 10]
    words = (rf'span {re.escape(ratio)} x the training range \[0, 10\]: '
             r"give them in the model's input units \(unnamed")
    with pytest.raises(ConfigError, match=words):
        Predictor(model, PredictorConfig(input_min=(lo,), input_max=(hi,)))
    # a hundredth or a hundred times the range is a choice, and so is one bound alone
    Predictor(model, PredictorConfig(input_min=(0.0,), input_max=(0.1,)))
    Predictor(model, PredictorConfig(input_min=(-500.0,), input_max=(500.0,)))
    Predictor(model, PredictorConfig(input_max=(0.001,)))
    Predictor(_model(trained=False), PredictorConfig(input_min=(lo,), input_max=(hi,)))
