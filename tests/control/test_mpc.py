"""The MPC and the offset-free estimator against known truth (ROMs as the plant)."""

from __future__ import annotations

from _eel_rom import modal_rom
import numpy as np
import pytest

from soft_rom.control import (
    check_moves,
    EstimatorConfig,
    FOMPlant,
    MPC,
    MPCConfig,
    OffsetFreeEstimator,
    parse_reference,
    Reference,
    ROMPlant,
    run_closed_loop,
    Sensor,
    simulate_inputs,
)
from soft_rom.errors import ConfigError, DimensionError
from soft_rom.models import DiscreteModel, SecondOrderModel
from soft_rom.sim import random_pressures


def _feasible(model, k: int, seed: int, amplitude: float = 20e3) -> tuple[np.ndarray, Reference]:
    """A reference the model itself produces with 10 ms zero-order-hold inputs."""
    U = random_pressures(k, 1e-3, seed=seed, episode=1, amplitude=amplitude)
    U = np.repeat(U[:, ::10], 10, axis=1)[:, :k]
    return U, Reference(t=np.arange(k) * 1e-3, Y=model.simulate(U))


def test_perfect_model_tracks_a_feasible_reference_exactly() -> None:
    model = modal_rom(8)
    _U, ref = _feasible(model, 700, seed=5)
    big = MPCConfig(u_min=(-1e6,), u_max=(1e6,), rate_max=1e12, rate_weight=1e-9)
    res = run_closed_loop(model, ref, plant=ROMPlant(model), mpc=big, sensor=Sensor(noise=0.0),
                          duration=0.45)
    # before the horizon reaches the reference's end (held there), tracking is exact
    assert res.tracking_error() < 1e-5


def test_offset_free_on_a_model_with_the_wrong_gain() -> None:
    model = modal_rom(8)
    wrong = SecondOrderModel(model.K, model.C, 1.3 * model.B, model.E, dt=model.dt,
                             y_ref=model.y_ref, output_names=model.output_names,
                             metadata=model.metadata)
    u = np.array([10e3, -10e3, 5e3, -5e3, 0.0, 0.0])
    target = model.simulate(np.repeat(u[:, None], 4000, axis=1))[:, -1]   # the plant's steady
    t = np.array([0.0, 0.05, 0.0501, 3.0])
    Y = np.stack([model.y_ref, model.y_ref, target, target], axis=1)
    ref = Reference(t=t, Y=Y)
    # state noise 0: the filter is a pure output-disturbance observer (fast to settle here;
    # with state noise the eel's 0.27 Hz first mode settles over seconds)
    est = EstimatorConfig(process_noise=0.0)
    res = run_closed_loop(wrong, ref, plant=ROMPlant(model), sensor=Sensor(noise=0.0),
                          estimator=est, duration=1.5)
    dev = np.linalg.norm(target - model.y_ref)
    final = np.linalg.norm(res.Y[:, -1] - target)
    assert final < 1e-3 * dev
    # and without the disturbance estimate the same loop keeps an offset
    no_d = EstimatorConfig(disturbance_noise=1e-7, process_noise=0.0)   # d frozen
    res0 = run_closed_loop(wrong, ref, plant=ROMPlant(model), sensor=Sensor(noise=0.0),
                           estimator=no_d, duration=1.5)
    assert np.linalg.norm(res0.Y[:, -1] - target) > 0.05 * dev


def test_inputs_stay_in_bounds_and_rate_limits() -> None:
    model = modal_rom(8)
    _U, ref = _feasible(model, 600, seed=7, amplitude=80e3)        # beyond the bounds
    cfg = MPCConfig(u_min=(-20e3,), u_max=(30e3,), rate_max=400e3)
    res = run_closed_loop(model, ref, plant=ROMPlant(model), mpc=cfg, sensor=Sensor(noise=0.0))
    assert np.all(res.U >= -20e3 - 1e-6) and np.all(res.U <= 30e3 + 1e-6)
    steps = np.abs(np.diff(res.U[:, ::10], axis=1))
    assert steps.max() <= 400e3 * 0.01 * (1 + 1e-6)
    assert res.summary()['saturated_fraction'] > 0.05          # the bounds were reached


def test_dmdc_like_discrete_model_steps_by_multiples() -> None:
    model = modal_rom(4)
    s = model.discretize(1e-3)
    disc = DiscreteModel(s.A, s.B, s.C, s.D, dt=1e-3, method='dmdc', y_ref=model.y_ref,
                         output_names=model.output_names, metadata=model.metadata)
    a, b = MPC(model), MPC(disc)
    assert a.N == b.N == 20
    np.testing.assert_allclose(a.H, b.H, rtol=1e-7, atol=1e-12 * np.abs(a.H).max())
    with pytest.raises(ConfigError, match='whole multiple'):
        MPC(disc, MPCConfig(step=0.0105))


def test_cubic_model_is_refused() -> None:
    from soft_rom.models import CubicSecondOrderModel
    model = modal_rom(2)
    r = model.r
    cubic = CubicSecondOrderModel(model.K, model.C, np.zeros((r, r, r)), np.zeros((r,) * 4),
                                  model.B, model.E, dt=model.dt, y_ref=model.y_ref)
    with pytest.raises(ConfigError, match='nonlinear'):
        MPC(cubic)
    # nor taken as linear by the plant or the estimator (their discretize() linearizes)
    with pytest.raises(ConfigError, match='nonlinear'):
        ROMPlant(cubic)
    with pytest.raises(ConfigError, match='nonlinear'):
        OffsetFreeEstimator(cubic)


def test_a_long_gap_on_a_discrete_model_is_discretized_by_squaring() -> None:
    # A^j and (A^{j-1} + ... + I) B against the plain sums; a 1e9-step gap is immediate
    model = modal_rom(4)
    s = model.discretize(1e-3)
    disc = DiscreteModel(s.A, s.B, s.C, s.D, dt=1e-3, method='dmdc', y_ref=model.y_ref)
    for j in (2, 7, 33):
        Aj = np.linalg.matrix_power(s.A, j)
        Bj = sum(np.linalg.matrix_power(s.A, i) for i in range(j)) @ s.B
        got = disc.discretize(j * 1e-3)
        np.testing.assert_allclose(got.A, Aj, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(got.B, Bj, rtol=1e-10, atol=1e-14 * np.abs(Bj).max())
    far = disc.discretize(1e6)                     # 1e9 steps: 30 squarings
    assert np.all(np.isfinite(far.A))


@pytest.mark.parametrize('kw, words', [
    ({'u_min': (-20,), 'u_max': (20,)}, 'give them in the model'),          # kPa for Pa
    ({'u_min': (-5e8,), 'u_max': (5e8,)}, 'x the training range'),
])
def test_bounds_in_other_units_than_the_model_are_refused(kw, words) -> None:
    with pytest.raises(ConfigError, match=words):
        MPC(modal_rom(2), MPCConfig(**kw))


def test_bounds_message_names_the_units_or_says_they_are_unnamed() -> None:
    """A model without units printed 'give them in the model's input units ()'."""
    named = modal_rom(2)
    with pytest.raises(ConfigError, match=r"model's input units \(Pa\)\.$"):
        MPC(named, MPCConfig(u_min=(-20,), u_max=(20,)))
    bare = SecondOrderModel(named.K, named.C, named.B, named.E, dt=named.dt,
                            y_ref=named.y_ref, metadata=named.metadata)
    assert bare.input_units == [''] * 6
    with pytest.raises(ConfigError, match=r'input units \(unnamed in the model file\)\.$'):
        MPC(bare, MPCConfig(u_min=(-20,), u_max=(20,)))


def test_plants_and_simulate_inputs_check_their_inputs() -> None:
    model = modal_rom(2)
    U = np.zeros((6, 30))
    with pytest.raises(DimensionError, match='transpose'):
        simulate_inputs(model, U.T)
    with pytest.raises(DimensionError, match='NaN'):
        simulate_inputs(model, np.full((6, 3), np.nan))
    with pytest.raises(DimensionError, match=r'shape \(6,\) \(one channel\)'):
        simulate_inputs(model, np.zeros(6))
    for plant in (ROMPlant(model), FOMPlant(model)):
        with pytest.raises(DimensionError, match='6 finite values'):
            plant.step(np.full(50, 2e4))
        plant.step([2e4] * 6)                       # a list is fine


@pytest.mark.parametrize('spec, words', [
    ('step:u=20/-20/15/-15/10/-10', 'give it in the model'),       # kPa for Pa: a 20 um bend
    ('wave:f=2,amplitude=3.7', 'give it in the model'),            # 3.7 m on a 1.2 m robot
])
def test_references_in_other_units_are_refused(spec, words) -> None:
    model = modal_rom(2)
    ref = parse_reference(spec, model, duration=0.5)
    with pytest.raises(ConfigError, match=words):
        check_moves(ref, model, 0.5)
    with pytest.raises(ConfigError, match=words):
        run_closed_loop(model, ref, plant=ROMPlant(model), duration=0.5)


@pytest.mark.parametrize('duration', [float('nan'), -1.0, 0.0])
def test_a_closed_loop_needs_a_positive_duration(duration) -> None:
    model = modal_rom(2)
    with pytest.raises(ConfigError, match='duration > 0'):
        run_closed_loop(model, _feasible(model, 100, seed=1)[1], plant=ROMPlant(model),
                        duration=duration)


def test_bounds_come_from_the_training_envelope_or_are_asked_for() -> None:
    model = modal_rom(2)
    mpc = MPC(model)
    np.testing.assert_array_equal(mpc.lo, -50e3)
    np.testing.assert_array_equal(mpc.hi, 50e3)
    bare = SecondOrderModel(model.K, model.C, model.B, model.E, dt=model.dt)
    with pytest.raises(ConfigError, match='input bounds'):
        MPC(bare)
    with pytest.raises(ConfigError, match='u_min >= u_max'):
        MPC(model, MPCConfig(u_min=(1.0,), u_max=(0.0,)))


def test_riccati_terminal_cost_makes_the_horizon_infinite() -> None:
    """Without active bounds the first move is the infinite-horizon LQ optimum's."""
    import scipy.linalg as sla
    model = modal_rom(4)
    big = dict(u_min=(-1e6,), u_max=(1e6,), rate_max=1e12, rate_weight=1e-2, horizon=0.03)
    mpc = MPC(model, MPCConfig(terminal='riccati', **big))
    assert mpc.terminal == 'riccati'
    A, B, C, D, _ = mpc.system
    n, m = mpc.n, mpc.m
    S = np.diag(mpc.half)
    wy = 1.0 / (mpc.p * mpc.y_scale ** 2)
    wd = 1e-2 / m
    w0 = 1e-2 / m
    gain = C @ np.linalg.solve(np.eye(n) - A, B) @ S
    _u, sv, vt = np.linalg.svd(gain)
    weak = np.ones(m, dtype=bool)
    weak[:sv.size] = sv < 1e-3 * sv[0]
    P0 = vt.T[:, weak] @ vt.T[:, weak].T
    # the LQ problem in (x, v_prev) with the increment as input, solved independently
    Aa = np.block([[A, B @ S], [np.zeros((m, n)), np.eye(m)]])
    Ba = np.vstack([B @ S, np.eye(m)])
    Ca = np.hstack([C, D @ S])
    Q = wy * Ca.T @ Ca
    Q[n:, n:] += w0 * P0
    R = (wd + w0 * 1e-6) * np.eye(m) + w0 * P0
    Sx = np.zeros((n + m, m))
    Sx[n:] = w0 * P0
    P = sla.solve_discrete_are(Aa, Ba, Q, R, s=Sx)
    K = np.linalg.solve(R + Ba.T @ P @ Ba, Ba.T @ P @ Aa + Sx.T)
    rng = np.random.default_rng(3)
    x0 = 1e-3 * rng.standard_normal(n)
    R_ref = np.repeat(model.y_ref[:, None], mpc.N, axis=1)
    step = mpc.solve(x0, np.zeros(mpc.p), R_ref, mpc.centre)
    assert step.qp.ok
    z0 = np.concatenate([x0, np.zeros(m)])
    v_lq = -K @ z0                                   # v_0 = v_{-1} + delta_0, v_{-1} = 0
    np.testing.assert_allclose(mpc.scale(step.u), v_lq, rtol=1e-5,
                               atol=1e-7 * np.abs(v_lq).max())
    # and without it the 3-step horizon moves differently
    short = MPC(model, MPCConfig(terminal='none', **big))
    v_short = short.scale(short.solve(x0, np.zeros(mpc.p), R_ref, short.centre).u)
    assert np.abs(v_short - v_lq).max() > 0.05 * np.abs(v_lq).max()


def _slow_plant(d0: np.ndarray) -> tuple[DiscreteModel, DiscreteModel, np.ndarray]:
    """A 3-state, 2-input, 3-output linear system with a slow mode (-0.3/s) and fast ones.

    Returns the controller's model, the plant (the same system with a constant output
    disturbance ``d0``: its ``y_ref``) and the steady-state gain.
    """
    import scipy.linalg as sla
    dt = 1e-3
    Ac = np.diag([-0.3, -8.0, -12.0])                  # time constants 3.3 s, 0.13 s, 0.08 s
    Bc = np.array([[1.0, 0.5], [8.0, -4.0], [-6.0, 12.0]])
    C = np.array([[1.0, 1.0, 0.0], [1.0, 0.0, 1.0], [1.0, -0.5, 0.5]])
    M = sla.expm(np.block([[Ac, Bc], [np.zeros((2, 5))]]) * dt)
    A, B = M[:3, :3], M[:3, 3:]
    names = ('a', 'b', 'c')
    model = DiscreteModel(A, B, C, dt=dt, method='dmdc', y_ref=np.zeros(3), output_names=names)
    plant = DiscreteModel(A, B, C, dt=dt, method='dmdc', y_ref=d0, output_names=names)
    return model, plant, C @ np.linalg.solve(np.eye(3) - A, B)


@pytest.mark.parametrize('estimator', [EstimatorConfig(),
                                       EstimatorConfig(slow_mode_noise=0.03),
                                       EstimatorConfig(process_noise=0.0)],
                         ids=['defaults', 'slow-mode-noise', 'output-disturbance-only'])
def test_offset_free_with_a_slow_mode_and_a_constant_output_disturbance(
        estimator: EstimatorConfig) -> None:
    """A reachable step settles within 2 % in 1.5 s and stays there.

    1.5 s is under half the slow mode's time constant; with the disturbance estimate frozen
    the loop keeps an offset.
    """
    d0 = np.array([0.5, -0.4, 0.3])
    model, plant, G = _slow_plant(d0)
    u_star = np.array([1.0, -0.5])
    target = G @ u_star + d0                           # reachable by the plant at u_star
    ref = Reference(t=np.array([0.0, 0.05, 0.0501, 10.0]),
                    Y=np.stack([d0, d0, target, target], axis=1))
    cfg = MPCConfig(u_min=(-3.0,), u_max=(3.0,))
    sensor = Sensor(noise=1e-3)
    dev = np.linalg.norm(target - d0)

    def errors(est: EstimatorConfig) -> tuple[np.ndarray, np.ndarray]:
        est = EstimatorConfig(**{**est.__dict__, 'measurement_noise': 1e-3})
        res = run_closed_loop(model, ref, plant=ROMPlant(plant), mpc=cfg, sensor=sensor,
                              estimator=est, duration=4.0)
        return res.t, np.linalg.norm(res.Y - target[:, None], axis=0) / dev

    t, err = errors(estimator)
    settled = t >= 0.05 + 1.5
    assert err[settled].max() <= 0.02
    assert err[-1] <= 2e-3
    assert err[t >= 0.05 + 0.3].max() > 0.1            # a step, not already there
    # without the disturbance estimate the loop keeps the part of d0 its inputs can reach
    frozen = EstimatorConfig(disturbance_noise=1e-7, process_noise=0.0)
    _t, err0 = errors(frozen)
    assert err0[-1] > 0.1


def test_slow_modes_are_the_modes_slower_than_the_rate() -> None:
    import scipy.linalg as sla

    from soft_rom.control.estimator import slow_modes
    model, _plant, _G = _slow_plant(np.zeros(3))
    A, C = model.A, model.C
    Vs = slow_modes(A, C, model.dt, 1.0)
    assert Vs.shape == (3, 1)
    np.testing.assert_allclose(np.abs(Vs[:, 0]), [1 / np.sqrt(3), 0, 0], atol=1e-12)
    assert slow_modes(A, C, model.dt, 0.1).shape == (3, 0)
    # an unstable mode is not a slow one
    grow = np.diag([np.exp(0.2 * model.dt), np.exp(-0.5 * model.dt), np.exp(-30 * model.dt)])
    Vg = slow_modes(grow, C, model.dt, 1.0)
    assert Vg.shape == (3, 1) and abs(Vg[1, 0]) > 0.9 * np.linalg.norm(Vg)
    # a lightly damped pair gives two columns (real and imaginary parts), unit output each
    om, a = 2.6, 0.1
    Ad = sla.expm(np.array([[-a, om], [-om, -a]]) * 0.01)
    Cd = np.array([[1.0, 0.0], [0.5, 2.0]])
    Vp = slow_modes(Ad, Cd, 0.01, 1.0)
    assert Vp.shape == (2, 2)
    np.testing.assert_allclose(np.linalg.norm(Cd @ Vp, axis=0), 1.0, rtol=1e-12)

