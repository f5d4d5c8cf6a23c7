"""The controller never commands NaN or out-of-bounds pressures, whatever it is fed."""

from __future__ import annotations

import copy

from _eel_rom import modal_rom
from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from soft_rom.control import Controller, MPCConfig, Reference
from soft_rom.control.qp import DaqpSolver

LO, HI = -20e3, 30e3


@pytest.fixture(scope='module')
def model():
    return modal_rom(4)


def _controller(model, **kw) -> Controller:
    return Controller(model, MPCConfig(u_min=(LO,), u_max=(HI,), **kw))


def _ok(u: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(u)) and np.all(u >= LO) and np.all(u <= HI))


def _ref(model, t_end: float = 5.0, bend: float = 0.01) -> Reference:
    Y = np.repeat(model.y_ref[:, None], 2, axis=1)
    Y[20:, 1] += bend * np.linspace(0, 1, 20)
    return Reference(t=np.array([0.0, t_end]), Y=Y)


def test_missing_measurement_holds_a_safe_command(model) -> None:
    ctl = _controller(model)
    ctl.set_reference(_ref(model))
    cmd = ctl.step(0.0)
    assert cmd.status == 'missing' and _ok(cmd.u)
    np.testing.assert_array_equal(cmd.u, np.clip(0.0, LO, HI))


def test_stale_measurement_holds_the_last_command(model) -> None:
    ctl = _controller(model)
    ctl.set_reference(_ref(model))
    for k in range(10):
        ctl.measure(model.y_ref, 0.01 * k)
        last = ctl.step(0.01 * k)
    assert last.status == 'ok'
    cmd = ctl.step(0.09 + 0.5)
    assert cmd.status == 'stale' and 'old' in cmd.detail
    np.testing.assert_array_equal(cmd.u, last.u)


@pytest.mark.parametrize('stale_after', [0.0, -1.0, float('nan'), float('inf')])
def test_a_stale_limit_that_would_hold_every_command_is_refused(model, stale_after) -> None:
    # <= 0 would call every measurement stale (commands held for ever); inf never would
    with pytest.raises(ValueError, match='stale_after must be a positive number'):
        Controller(model, stale_after=stale_after)


@pytest.mark.parametrize('bad, why', [
    (np.zeros(39), 'model has 40 outputs'),
    (np.full(40, np.nan), 'NaN/Inf'),
    ('not numbers', 'model has 40 outputs'),
    (np.zeros((20, 2)), 'shape (20, 2)'),             # a (points, components) centerline
    (np.full(40, 1e3), 'wrong units'),                # mm for a model in m: 1 km off
])
def test_bad_measurements_are_dropped_with_the_reason(model, bad, why) -> None:
    ctl = _controller(model)
    assert why in ctl.measure(bad, 0.0)
    assert ctl.counters.measurements_dropped == 1 and ctl.t_measured is None
    ctl.measure(model.y_ref, 0.02)
    assert 'not newer' in ctl.measure(model.y_ref, 0.01)


def test_the_last_dropped_input_is_kept_while_held_commands_overwrite_last_problem(
        model) -> None:
    ctl = _controller(model)
    bad = model.y_ref.copy()
    bad[3] = np.nan
    why = ctl.measure(bad, 0.0)
    assert ctl.counters.last_dropped == f'measurement dropped: {why}' and 'NaN' in why
    cmd = ctl.step(0.01)                            # no reference, no measurement: held
    assert cmd.status != 'ok' and ctl.counters.last_problem == cmd.detail != why
    assert ctl.counters.last_dropped == f'measurement dropped: {why}'
    ctl.set_state(np.zeros(3), 0.0)
    assert ctl.counters.last_dropped.startswith('state dropped: state of 3 values')


def test_bad_references_are_refused_and_the_old_one_stays(model) -> None:
    ctl = _controller(model)
    good = _ref(model)
    assert ctl.set_reference(good) == ''
    wrong = Reference(t=np.array([0.0, 1.0]), Y=np.zeros((39, 2)))
    assert '39 outputs' in ctl.set_reference(wrong)
    past = _ref(model, t_end=0.5)
    assert 'before now' in ctl.set_reference(past, now=2.0)
    with pytest.raises(ValueError, match='NaN'):
        Reference(t=np.array([0.0, 1.0]), Y=np.full((40, 2), np.nan))
    assert ctl.reference is good and ctl.counters.references_refused == 2


def test_infeasible_qp_holds_the_last_command_in_bounds(model) -> None:
    ctl = _controller(model, rate_max=1e3)          # 10 Pa per step
    ctl.set_reference(_ref(model))
    ctl.u = np.full(6, 45e3)                         # outside the bounds (bounds were changed)
    ctl.measure(model.y_ref, 0.0)
    cmd = ctl.step(0.0)
    assert cmd.status == 'infeasible' and _ok(cmd.u)
    np.testing.assert_array_equal(cmd.u, np.full(6, HI))
    assert ctl.counters.qp_infeasible == 1


def test_failed_qp_holds_the_last_command(model) -> None:
    ctl = _controller(model)
    ctl.mpc.solver = DaqpSolver(ctl.mpc.H, ctl.mpc.A_rate, iter_limit=1)
    ctl.set_reference(_ref(model, bend=0.05))
    ctl.measure(model.y_ref, 0.0)
    before = ctl.u.copy()
    cmd = ctl.step(0.0)
    assert cmd.status == 'failed' and 'QP failed' in cmd.detail
    np.testing.assert_array_equal(cmd.u, before)


_event = st.one_of(
    st.tuples(st.just('measure'), st.floats(allow_nan=True, allow_infinity=True, width=64),
              st.floats(-1.0, 10.0), st.integers(38, 41)),
    st.tuples(st.just('step'), st.floats(-1.0, 10.0)),
    st.tuples(st.just('reference'), st.one_of(st.floats(-1e3, 1e3), st.just(float('nan'))),
              st.floats(0.0, 10.0), st.integers(39, 40)),
)


@pytest.fixture(scope='module')
def fresh(model):
    base = _controller(model, rate_max=5e5, horizon=0.05)
    return lambda: copy.deepcopy(base)


@settings(max_examples=40, deadline=None, suppress_health_check=[
    HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(st.lists(_event, min_size=1, max_size=25))
def test_no_sequence_of_inputs_gives_a_nan_or_out_of_bounds_command(model, fresh, events
                                                                     ) -> None:
    ctl = fresh()
    for ev in events:
        if ev[0] == 'measure':
            _, scale, t, size = ev
            y = np.resize(model.y_ref, size) + scale * 1e-3     # NaN, Inf, huge included
            ctl.measure(y, t)
        elif ev[0] == 'reference':
            _, bend, t_end, size = ev
            Y = np.repeat(np.resize(model.y_ref, size)[:, None], 2, axis=1)
            Y[:, 1] += bend
            try:
                ctl.set_reference(Reference(t=np.array([0.0, t_end + 1e-3]), Y=Y), now=0.0)
            except ValueError:
                pass                                  # refused before it reaches the node
        else:
            cmd = ctl.step(ev[1])
            assert _ok(cmd.u), (ev, cmd)
        assert _ok(ctl.u)


def _run(ctl, model, times, t_meas=None) -> list:
    cmds = []
    for t in times:
        ctl.measure(model.y_ref, t if t_meas is None else t_meas)
        cmds.append(ctl.step(t))
    return cmds


def test_a_second_run_after_start_is_closed_loop_again(model) -> None:
    # a user restarting with start(0): the first run's last measurement time is forgotten
    ctl = _controller(model)
    ctl.set_reference(_ref(model))
    _run(ctl, model, [0.0, 0.1, 0.3])
    ctl.start(0.0)
    assert ctl.measure(model.y_ref, 0.01) == ''
    assert ctl.step(0.01).status == 'ok'


@pytest.mark.parametrize('t, why', [(float('nan'), 'not finite'), (float('inf'), 'not finite'),
                                    (0.02, 'before the last one')])
def test_a_step_time_that_is_not_finite_or_goes_back_holds_the_command(model, t, why) -> None:
    ctl = _controller(model)
    ctl.set_reference(_ref(model))
    last = _run(ctl, model, [0.0, 0.01, 0.05, 0.07])[-1]
    n_hist = len(ctl._history)
    cmd = ctl.step(t)
    assert cmd.status == 'bad_time' and why in cmd.detail
    np.testing.assert_array_equal(cmd.u, last.u)
    assert len(ctl._history) == n_hist and ctl.t_step == 0.07
    assert ctl.step(0.08).status == 'ok'


def test_measurements_stamped_far_after_the_steps_are_not_ok(model) -> None:
    # two clocks: measurements in one, steps 0.5 s behind in another
    ctl = _controller(model)
    ctl.set_reference(_ref(model))
    ctl.measure(model.y_ref, 0.5)
    cmd = ctl.step(0.0)
    assert cmd.status == 'bad_time' and 'two clocks' in cmd.detail


def test_steps_faster_than_h_keep_the_rate_bound_per_second(model) -> None:
    # the user ticks every 1 ms where h is 10 ms: the command moves at most rate_max per s
    rate = 100e3
    ctl = _controller(model, rate_max=rate)
    ctl.set_reference(_ref(model, bend=0.05))
    U = np.array([c.u for c in _run(ctl, model, 1e-3 * np.arange(100))])
    assert np.abs(np.diff(U, axis=0)).max() <= rate * 1e-3 * (1 + 1e-9)
    assert np.abs(U[-1] - U[0]).max() > 0.5 * rate * 0.099       # it did move


def test_rate_bound_per_input(model) -> None:
    ctl = _controller(model, rate_max=(1e5, 2e5, 3e5, 1e5, 2e5, 3e5))
    np.testing.assert_allclose(ctl.mpc.rate, np.array([1, 2, 3, 1, 2, 3]) * 1e5 * ctl.h)
    with pytest.raises(ValueError, match='1 or 6 values'):
        _controller(model, rate_max=(1e5, 2e5))
    with pytest.raises(ValueError, match='rate_max must be one number > 0'):
        _controller(model, rate_max=(1e5, -1.0))


def test_a_restarted_clock_starts_a_new_run(model) -> None:
    # a simulation started again: steps and measurements from 0 after 2 s
    ctl = _controller(model)
    ctl.set_reference(_ref(model))
    _run(ctl, model, [1.9, 1.95, 2.0])
    assert ctl.step(0.0).status == 'missing' and ctl.counters.clock_resets == 1
    assert [c.status for c in _run(ctl, model, [0.01, 0.02])] == ['ok', 'ok']
    # a measurement from the restarted clock first
    _run(ctl, model, [1.9, 1.95, 2.0])
    assert ctl.measure(model.y_ref, 0.0) == '' and ctl.counters.clock_resets == 2
    assert ctl.step(0.0).status == 'ok'
    assert 'not newer' in ctl.measure(model.y_ref, -0.5)      # within clock_reset: dropped
