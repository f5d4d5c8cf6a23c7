"""predict / evaluate: sample-time handling, initial states, metrics per episode and split."""

from __future__ import annotations

import numpy as np
import pytest

from soft_rom.data import Episode
from soft_rom.errors import ConfigError, DimensionError
from soft_rom.evaluation import evaluate, predict
from soft_rom.metrics import output_errors
from soft_rom.models import DiscreteModel, SecondOrderModel


def _discrete(dt=1e-3, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((4, 4))
    A *= 0.9 / np.max(np.abs(np.linalg.eigvals(A)))
    return DiscreteModel(A, rng.standard_normal((4, 2)), rng.standard_normal((3, 4)),
                         rng.standard_normal((3, 2)), dt=dt, method='era',
                         y_ref=[1.0, 2.0, 3.0]), rng


def _second_order(dt=1e-3):
    K = np.array([[40.0, -5.0], [-5.0, 30.0]])
    C = np.array([[0.5, 0.0], [0.0, 0.4]])
    return SecondOrderModel(K, C, np.array([[1.0], [0.5]]), np.array([[1.0, 0.0],
                                                                      [0.3, 1.0]]),
                            dt=dt, y_ref=[0.5, -0.5])


def test_same_rate_equals_simulate():
    model, rng = _discrete()
    U = rng.standard_normal((2, 100))
    ep = Episode(t=np.arange(100) * 1e-3, U=U, Y=np.zeros((3, 100)))
    np.testing.assert_allclose(predict(model, ep), model.simulate(U), rtol=1e-13, atol=1e-13)


def test_coarser_data_steps_whole_multiples():
    model, rng = _discrete(dt=1e-3)
    U = rng.standard_normal((2, 50))
    ep = Episode(t=np.arange(50) * 3e-3, U=U, Y=np.zeros((3, 50)))
    fine = model.simulate(np.repeat(U, 3, axis=1))
    np.testing.assert_allclose(predict(model, ep), fine[:, ::3] - model.D @ np.repeat(
        U, 3, axis=1)[:, ::3] + model.D @ U, rtol=1e-12, atol=1e-12)


def test_continuous_model_discretized_at_data_rate_and_initial_output():
    model = _second_order(dt=1e-3)
    U = np.sin(np.linspace(0, 6, 400))[None, :]
    ep = Episode(t=np.arange(400) * 2e-3, U=U, Y=np.zeros((2, 400)))
    A, B, Cm, Dm, _ = model.discretize(2e-3)
    x, Y = np.zeros(4), np.empty((2, 400))
    for j in range(400):
        Y[:, j] = Cm @ x + model.y_ref
        x = A @ x + B @ U[:, j]
    np.testing.assert_allclose(predict(model, ep), Y, rtol=1e-12, atol=1e-12)
    # initial='output': the state reproduces the first measured output.
    q0 = np.array([0.01, -0.02])
    y0 = model.E @ q0 + model.y_ref
    ep2 = Episode(t=ep.t, U=U, Y=np.repeat(y0[:, None], 400, axis=1))
    Y_hat = predict(model, ep2, initial='output')
    np.testing.assert_allclose(Y_hat[:, 0], y0, atol=1e-14)


def test_decimated_model_block_means_and_interpolation():
    model, rng = _discrete(dt=4e-3)
    k = 18                                           # 4 full blocks and one of 2 samples
    U = rng.standard_normal((2, k))
    ep = Episode(t=np.arange(k) * 1e-3, U=U, Y=np.zeros((3, k)))
    Y_hat = predict(model, ep)
    blocks = [U[:, a:a + 4].mean(axis=1) for a in range(0, k, 4)]
    _, X = model.simulate(np.column_stack(blocks), return_states=True)
    X = np.column_stack([X, model.A @ X[:, -1] + model.B @ blocks[-1]])
    for i in range(k):
        j, w = divmod(i, 4)
        x = X[:, j] * (1 - w / 4) + X[:, j + 1] * (w / 4)
        np.testing.assert_allclose(Y_hat[:, i], model.C @ x + model.D @ U[:, i] + model.y_ref,
                                   rtol=1e-12, atol=1e-12)


def test_evaluate_rows_match_metrics_and_split():
    model, rng = _discrete()
    eps = []
    for i in range(2):
        U = rng.standard_normal((2, 300))
        Y = model.simulate(U) + 0.01 * rng.standard_normal((3, 300))
        eps.append(Episode(t=10.0 + np.arange(300) * 1e-3, U=U, Y=Y, name=f'e{i}'))
    ev = evaluate(model, eps, t_split=0.2, return_predictions=True)
    assert len(ev.rows) == 3 * 3
    for ep in eps:
        Y_hat = ev.predictions[ep.name]
        want = output_errors(ep.Y, Y_hat, model.y_ref)
        row = ev.get(ep.name, 'all')
        assert row['relative_error'] == pytest.approx(want['relative_error'], rel=1e-12)
        assert row['relative_deviation_error'] == pytest.approx(
            want['relative_deviation_error'], rel=1e-12)
        # t_split counts from the episode's first sample (t starts at 10 s here).
        tr = output_errors(ep.Y[:, :200], Y_hat[:, :200], model.y_ref)
        te = output_errors(ep.Y[:, 200:], Y_hat[:, 200:], model.y_ref)
        assert ev.get(ep.name, 'train')['n_samples'] == 200
        assert ev.get(ep.name, 'train')['relative_error'] == pytest.approx(
            tr['relative_error'], rel=1e-12)
        assert ev.get(ep.name, 'test')['relative_deviation_error'] == pytest.approx(
            te['relative_deviation_error'], rel=1e-12)
    Yall = np.hstack([ep.Y for ep in eps])
    Yh = np.hstack([ev.predictions[ep.name] for ep in eps])
    pooled = output_errors(Yall, Yh, model.y_ref)
    assert ev.get('*', 'all')['relative_error'] == pytest.approx(pooled['relative_error'],
                                                                  rel=1e-12)
    assert ev.to_dict()['model']['method'] == 'era'


def test_errors():
    model, rng = _discrete(dt=1e-3)
    ep = Episode(t=np.arange(10) * 1e-3, U=np.zeros((3, 10)), Y=np.zeros((3, 10)))
    with pytest.raises(DimensionError, match='expects 2 inputs'):
        predict(model, ep)
    ep = Episode(t=np.arange(10) * 1.5e-3, U=np.zeros((2, 10)), Y=np.zeros((3, 10)))
    with pytest.raises(DimensionError, match='whole multiple'):
        predict(model, ep)
    with pytest.raises(ConfigError, match='initial'):
        predict(model, ep, initial='zero')
    with pytest.raises(DimensionError):
        evaluate(model, [])


def _episodes(model, n, k=300, seed=5):
    rng = np.random.default_rng(seed)
    eps = []
    for i in range(n):
        U = np.repeat(rng.standard_normal((model.n_inputs, k // 30 + 1)), 30, axis=1)[:, :k]
        eps.append(Episode(t=np.arange(k) * model.dt, U=U, Y=model.simulate(U),
                           name=f'ep{i + 1}'))
    return eps


def test_held_out_errors_leave_each_episode_out_in_turn():
    from soft_rom.evaluation import held_out_errors

    truth = _second_order()
    eps = _episodes(truth, 3)
    seen = []

    def fit(episodes):
        seen.append([e.name for e in episodes])
        return truth
    exact = held_out_errors(fit, eps, truth.y_ref)
    assert seen == [['ep2', 'ep3'], ['ep1', 'ep3'], ['ep1', 'ep2']]
    assert exact['deviation_error'] == 0.0 and exact['samples'] == 900
    assert 'each of ep1, ep2, ep3 left out' in exact['data']
    # a model off by 10 % in its output map: that error, pooled over the left-out episodes
    wrong = SecondOrderModel(truth.K, truth.C, truth.B, 1.1 * truth.E, dt=truth.dt,
                             y_ref=truth.y_ref)
    res = held_out_errors(lambda _eps: wrong, eps, truth.y_ref)
    assert res['deviation_error'] == pytest.approx(0.1, rel=1e-9)
    Y = np.concatenate([e.Y for e in eps], axis=1)
    Yh = np.concatenate([wrong.simulate(e.U) for e in eps], axis=1)
    assert res['absolute_error'] == pytest.approx(np.linalg.norm(Y - Yh) / np.linalg.norm(Y))


def test_held_out_errors_of_one_episode_score_its_tail():
    from soft_rom.evaluation import held_out_errors

    truth = _second_order()
    (ep,) = _episodes(truth, 1, k=1000)
    lengths = []

    def fit(episodes):
        lengths.append(episodes[0].n_samples)
        return SecondOrderModel(truth.K, truth.C, truth.B, 1.1 * truth.E, dt=truth.dt,
                                y_ref=truth.y_ref)
    res = held_out_errors(fit, [ep], truth.y_ref, tail=0.25)
    assert lengths == [750] and res['samples'] == 250
    assert res['deviation_error'] == pytest.approx(0.1, rel=1e-9)
    assert 'the last 25% of ep1' in res['data']
    with pytest.raises(ConfigError, match='at least one'):
        held_out_errors(fit, [], truth.y_ref)


def test_a_nan_in_the_data_is_refused_not_averaged_into_nan_errors():
    """Found by an audit: a NaN in a stored episode printed rows of nan with exit 0."""
    m, _ = _discrete()
    U = np.zeros((m.n_inputs, 20))
    Y = np.zeros((m.n_outputs, 20))
    Y[1, 7] = np.nan
    with pytest.raises(DimensionError, match=r"Y of episode 'ep1' contains NaN or Inf "
                                             r'\(first at index \(1, 7\)\).*evaluating'):
        evaluate(m, [Episode(t=np.arange(20) * m.dt, U=U, Y=Y, name='ep1')])


def test_times_in_other_units_are_refused_not_predicted():
    """Times in ms are refused; within a factor of 100 either way is still predicted.

    A step 1000 times the model's gave a LOpInf prediction at 1 s steps (deviation error
    1.77 on the demo's ep3, no word said) and DMDc/ERA 1000 steps per sample (overflow, NaN).
    """
    for model in (_second_order(dt=1e-3), _discrete(dt=1e-3)[0]):
        m, p = model.n_inputs, model.n_outputs
        U = np.ones((m, 50))
        for t in (np.arange(50) * 1.0, np.arange(50) * 1e-6):     # ms, or ns, taken for s
            ep = Episode(t=t, U=U, Y=np.zeros((p, 50)), name='ms')
            with pytest.raises(DimensionError, match=r"episode 'ms' is sampled every .* "
                                                     r'\(a factor of .*\): are the episode '
                                                     'times in seconds'):
                predict(model, ep)
        ok = Episode(t=np.arange(50) * 0.1, U=U, Y=np.zeros((p, 50)))
        assert np.isfinite(predict(model, ok)).all()


def test_predict_refuses_non_finite_inputs():
    """NaN inputs: ``evaluate`` refused them, ``predict`` (under it) returned NaN outputs."""
    model = _second_order()
    U = np.ones((1, 30))
    U[0, 12] = np.inf
    ep = Episode(t=np.arange(30) * 1e-3, U=U, Y=np.zeros((2, 30)), name='e')
    with pytest.raises(DimensionError, match=r"U of episode 'e' contains NaN or Inf \(first "
                                             r'at index \(0, 12\)\)'):
        predict(model, ep)


@pytest.mark.parametrize('t_split', [float('nan'), -0.5, 0.0, float('inf'), 'soon'])
def test_a_split_that_is_not_a_positive_time_is_refused(t_split):
    """A t_split that is not a positive number of seconds is refused, as the CLI does.

    NaN, negative or zero gave rows of 0 samples and NaN errors everywhere ('soon': a
    TypeError traceback); soft-rom evaluate --t-split refused them already.
    """
    model = _second_order()
    ep = Episode(t=np.arange(200) * 1e-3, U=np.ones((1, 200)), Y=np.ones((2, 200)))
    with pytest.raises(ConfigError, match=r't_split must be a positive number of seconds '
                                          r"from each episode's first sample; got"):
        evaluate(model, ep, t_split=t_split)
    res = evaluate(model, ep, t_split=0.199)        # the last sample alone is a test part
    assert res.get(segment='test')['n_samples'] == 1
    assert res.get(segment='train')['n_samples'] == 199


def test_an_episode_refuses_non_finite_times_and_names_float32_times():
    """A NaN time is refused; float32 times are named as the cause of a non-uniform step.

    A NaN time was accepted (dt NaN), then called "not uniformly sampled"; float32 times
    (uniform, but to 7 digits) were told to "resample" with no hint.
    """
    with pytest.raises(DimensionError, match=r"episode 'x': time stamps must be finite; "
                                             r't\[3\] = nan'):
        Episode(t=[0.0, 1.0, 2.0, np.nan], U=np.ones((1, 4)), Y=np.ones((1, 4)), name='x')
    t32 = (np.arange(2000) * 1e-3).astype(np.float32)
    ep = Episode(t=t32, U=np.ones((1, 2000)), Y=np.ones((2, 2000)), name='f32')
    with pytest.raises(DimensionError, match=r"episode 'f32' is not uniformly sampled: its "
                                             r'steps range from .*float32.*float64'):
        predict(_second_order(), ep)
    jitter = np.arange(20) * 1e-3 + np.r_[0, 4e-4, np.zeros(18)]
    ep = Episode(t=jitter, U=np.ones((1, 20)), Y=np.ones((2, 20)), name='j')
    with pytest.raises(DimensionError, match='resample it first'):
        predict(_second_order(), ep)


def test_an_episode_of_transposed_arrays_says_transpose():
    """U, Y or Q as (samples, channels) were refused without the hint simulate gives."""
    t = np.arange(50) * 1e-3
    for U, Y, Q, what in ((np.ones((50, 2)), np.ones((3, 50)), None, 'U'),
                          (np.ones((2, 50)), np.ones((50, 3)), None, 'Y'),
                          (np.ones((2, 50)), np.ones((3, 50)), np.ones((50, 7)), 'Q')):
        with pytest.raises(DimensionError, match=f'{what} must have .*transpose'):
            Episode(t=t, U=U, Y=Y, Q=Q)


def test_epoch_float_times_are_named_as_the_cause():
    """Float seconds since the epoch have 0.2 us steps: a 1 ms grid varies by 2e-4."""
    t = 1.7e9 + np.arange(200) * 1e-3
    ep = Episode(t=t, U=np.ones((1, 200)), Y=np.ones((2, 200)), name='epoch')
    with pytest.raises(DimensionError, match=r'float seconds since the epoch .* give float64 '
                                             r"times from the episode's start"):
        predict(_second_order(), ep)
