"""The steady-state gain in the trust checks (soft_rom.gain): absurd models are flagged.

The absurd models are those of the adversarial audit, made the same way: a model fitted on
a known system, its ``B`` multiplied in the file (``_hostile.with_arrays``) so that the
largest training input moves an output by about 17 km (LOpInf and DMDc), or by 1e12.
"""

from __future__ import annotations

import itertools

from _hostile import with_arrays
from _systems import spring_chain_episodes
import numpy as np
import pytest

from soft_rom.cli import main
from soft_rom.gain import (
    box_response,
    GAIN_FACTOR,
    gain_issue,
    peak_response,
    steady_state_gain,
)
from soft_rom.learners.dmdc import DMDc
from soft_rom.learners.lopinf import LOpInf
from soft_rom.models import DiscreteModel, load_model, SecondOrderModel


@pytest.fixture(scope='module')
def fitted():
    eps = spring_chain_episodes(n_dof=12, m=2, p=4, k=600, dt=2e-3, seed=0, stiffness=400.0,
                                drive_nodes=(4, 8), input_gain=1e-3, amplitude=30e3, hold=25,
                                q_span=1.0)
    lopinf = LOpInf(r=6).fit(eps).model_
    dmdc = DMDc(r=8, variant='stable').fit(eps).model_
    return eps, {'lopinf': lopinf, 'dmdc': dmdc}


def test_steady_state_gain_is_the_held_input_limit():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 5))
    A *= 0.8 / np.max(np.abs(np.linalg.eigvals(A)))
    model = DiscreteModel(A, rng.normal(size=(5, 2)), rng.normal(size=(3, 5)),
                          rng.normal(size=(3, 2)), dt=1e-3, method='dmdc')
    u = np.array([0.7, -1.3])
    Y = model.simulate(np.repeat(u[:, None], 400, axis=1))
    np.testing.assert_allclose(Y[:, -1] - model.y_ref, steady_state_gain(model) @ u,
                               rtol=1e-12, atol=1e-12)
    K = np.diag([4.0, 9.0])
    so = SecondOrderModel(K, np.eye(2), np.array([[1.0], [2.0]]), np.array([[1.0, 1.0]]),
                          dt=1e-3)
    np.testing.assert_allclose(steady_state_gain(so), [[1 / 4 + 2 / 9]], rtol=1e-14)
    integrator = DiscreteModel(np.eye(1), np.ones((1, 1)), np.ones((1, 1)), dt=1e-3,
                               method='dmdc')
    assert np.all(np.isinf(steady_state_gain(integrator)))


def test_box_response_is_the_worst_corner():
    rng = np.random.default_rng(1)
    G = rng.normal(size=(4, 3))
    lo, hi = np.array([-1.0, 0.0, 2.0]), np.array([0.5, 3.0, 5.0])
    corners = np.array(list(itertools.product(*zip(lo, hi)))).T       # (3, 8)
    np.testing.assert_allclose(box_response(G, lo, hi), np.max(np.abs(G @ corners), axis=1),
                               rtol=1e-14)


def test_fitted_models_are_trusted(fitted):
    _eps, models = fitted
    for model in models.values():
        assert model.trust_issues() == [], model
        env = model.metadata['envelope']
        peak = np.max(box_response(steady_state_gain(model), np.array(env['u_min']),
                                   np.array(env['u_max'])))
        assert peak < 10 * env['y_dev_max']       # a sane model: far below the limit


def _absurd(model, tmp_path, name, factor):
    return load_model(with_arrays(model, tmp_path / f'{name}.npz', B=model.B * factor))


@pytest.mark.parametrize('kind, target', [('lopinf', 17e3), ('dmdc', 17e3), ('dmdc', None)])
def test_absurd_gain_is_flagged_by_trust_info_and_strict(fitted, tmp_path, capsys, kind,
                                                         target):
    _eps, models = fitted
    model = models[kind]
    env = model.metadata['envelope']
    peak = float(np.max(peak_response(model, np.array(env['u_min']), np.array(env['u_max']),
                                      env['samples'])))
    factor = 1e12 if target is None else target / peak      # the output moves 17 km
    bad = _absurd(model, tmp_path, kind, factor)
    issues = bad.trust_issues()
    assert len(issues) == 1 and issues[0].startswith('absurd gain: inputs held within the '
                                                     'training range move output'), issues
    expect = peak * factor
    assert f"by {expect:.3g} within the training length ({env['samples']} steps)" in issues[0]
    assert f'limit {GAIN_FACTOR:g} x' in issues[0]
    path = str(tmp_path / f'{kind}.npz')
    assert main(['info', path]) == 0
    out = capsys.readouterr().out
    assert 'trust: NOT TRUSTED: absurd gain' in out
    assert main(['info', path, '--strict']) == 2
    assert 'cannot be trusted' in capsys.readouterr().err


def test_just_below_the_limit_is_not_flagged(fitted):
    _eps, models = fitted
    model = models['dmdc']
    env = model.metadata['envelope']
    peak = float(np.max(peak_response(model, np.array(env['u_min']), np.array(env['u_max']),
                                      env['samples'])))
    ratio = peak / env['y_dev_max']
    assert gain_issue(model) is None
    assert gain_issue(model, factor=0.99 * ratio) is not None
    assert gain_issue(model, factor=1.01 * ratio) is None
    assert gain_issue(model, metadata={}) is None          # no recorded range: not judged


def test_a_stiffening_cubic_model_is_judged_by_its_equilibria():
    from soft_rom.models import CubicSecondOrderModel
    from soft_rom.models.tensors import symmetrize
    r = 2
    I2 = np.eye(r)
    H = 6e6 * symmetrize(np.einsum('ij,kl->ijkl', I2, I2))     # V = 1e6 |q|^4 / 4 + ...
    B, E = np.array([[1.0, 0.0], [0.0, 2.0]]), np.array([[1.0, 0.5]])
    env = {'u_min': [0.0, 0.0], 'u_max': [1e3, 1e3], 'y_dev_max': 0.2, 'samples': 4000}
    model = CubicSecondOrderModel(0.01 * I2, I2, np.zeros((r, r, r)), H, B, E, dt=1e-3,
                                  metadata={'envelope': env})
    q = equilibrium_of(model, B @ np.array([1e3, 1e3]))
    np.testing.assert_allclose(model.force(q), B @ np.array([1e3, 1e3]), rtol=1e-9)
    # its linear part alone (K = 0.01) would move the output by 2.5e5 / 0.2 = 1e6 x ...
    steady = {k: v for k, v in env.items() if k != 'samples'}       # held for ever
    assert gain_issue(model.linear_part(), {'envelope': steady}) is not None
    # ... but the quartic stiffness holds it near 0.1: trusted
    assert model.trust_issues() == []
    stiff = CubicSecondOrderModel(0.01 * I2, I2, np.zeros((r, r, r)), H * 1e-12, B, E,
                                  dt=1e-3, metadata={'envelope': env})
    assert any(i.startswith('absurd gain') for i in stiff.trust_issues())


def equilibrium_of(model, force):
    from soft_rom.gain import equilibrium
    return equilibrium(model, force)


def test_held_input_gains_reach_the_steady_state():
    rng = np.random.default_rng(2)
    A = np.diag([0.5, 0.9, 0.99])
    model = DiscreteModel(A, rng.normal(size=(3, 2)), rng.normal(size=(2, 3)), dt=1e-3,
                          method='dmdc')
    gains = held_input_gains(model, 4096)
    u = np.array([1.0, -2.0])
    Y = model.simulate(np.repeat(u[:, None], 4097, axis=1))
    for j, G in enumerate(gains):                   # held 2**j steps: the simulation's
        np.testing.assert_allclose(G @ u, Y[:, 2 ** j] - model.y_ref, rtol=1e-10,
                                   atol=1e-12)
    np.testing.assert_allclose(gains[-1], steady_state_gain(model), rtol=1e-12)


def held_input_gains(model, horizon):
    from soft_rom.gain import held_input_gains as gains
    return gains(model, horizon)
