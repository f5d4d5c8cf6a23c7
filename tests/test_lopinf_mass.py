"""LOpInf with a learned mass matrix (:mod:`soft_rom.learners.lopinf.mass`), on known truth.

A random mechanical system ``M q'' + C q' + K q = B u`` (M, C, K SPD, M far from the
identity, non-proportional damping) observed in random non-orthogonal coordinates
``y = T q``: the identity-mass form in ``y`` has non-symmetric stiffness, so the
identity-mass LOpInf is biased, while the learned mass recovers the system exactly.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp
import scipy.linalg as sla

from soft_rom.errors import ConfigError
from soft_rom.learners.lopinf import LOpInf
from soft_rom.learners.lopinf.mass import mass_candidates, solve_learned_mass
from soft_rom.models import SecondOrderModel
from soft_rom.reduce import ReducedData

R, M_IN, DT = 4, 3, 1e-3


def _spd(rng: np.random.Generator, n: int, lo: float) -> np.ndarray:
    A = rng.standard_normal((n, n))
    return A @ A.T + lo * np.eye(n)


def _inputs(t: np.ndarray, phase: float) -> np.ndarray:
    return np.vstack([np.sin((i + 1) * 3.1 * t + i + phase) + 0.5 * np.cos(1.7 * t * (i + 2))
                      for i in range(M_IN)])


@pytest.fixture(scope='module')
def system():
    rng = np.random.default_rng(3)
    M0, C0, K0 = _spd(rng, R, 1.0), _spd(rng, R, 0.5), 50.0 * _spd(rng, R, 1.0)
    B0 = rng.standard_normal((R, M_IN))
    T = rng.standard_normal((R, R))                     # non-orthogonal observation
    Minv = np.linalg.inv(M0)
    A = np.block([[np.zeros((R, R)), np.eye(R)], [-Minv @ K0, -Minv @ C0]])

    def run(k: int, phase: float, x0: np.ndarray):
        t = np.arange(k) * DT

        def f(tt, x):
            u = _inputs(np.array([tt]), phase)[:, 0]
            return A @ x + np.concatenate([np.zeros(R), Minv @ B0 @ u])
        sol = solve_ivp(f, (0.0, t[-1]), x0, t_eval=t, method='DOP853', rtol=1e-13,
                        atol=1e-13)
        return t, _inputs(t, phase), T @ sol.y[:R]
    L0 = np.linalg.cholesky(M0)
    Li = sla.solve_triangular(L0, np.eye(R), lower=True)
    truth = SecondOrderModel(Li @ K0 @ Li.T, Li @ C0 @ Li.T, Li @ B0, T @ Li.T, dt=DT,
                             y_ref=np.zeros(R))
    episodes = [run(3000, ph, x0) for ph, x0 in
                ((0.0, rng.standard_normal(2 * R)), (1.3, rng.standard_normal(2 * R)))]
    return truth, episodes


def _fit(episodes, mass: str) -> LOpInf:
    # min_damping_ratio=0: the paper's margins only (the default damping-ratio bound is a
    # sufficient condition that binds for this lightly damped truth)
    return LOpInf(r=R, ddt=8, mass=mass, min_damping_ratio=0.0).fit(ReducedData.from_arrays(
        [y for _, _, y in episodes], [u for _, u, _ in episodes],
        [y for _, _, y in episodes], DT, np.zeros(R)))


def test_learned_mass_recovers_a_mechanical_system_in_oblique_coordinates(system):
    truth, episodes = system
    learned = _fit(episodes, 'learned')
    t = np.arange(5000) * DT
    U = _inputs(t, 2.1) + 0.3
    Y = truth.simulate(U)
    Yl = learned.model_.simulate(U)
    err = np.linalg.norm(Yl - Y) / np.linalg.norm(Y)
    assert err < 1e-8, err
    assert np.allclose(np.sort(np.abs(learned.model_.eigenvalues())),
                       np.sort(np.abs(truth.eigenvalues())), rtol=1e-8)
    # the model is the ordinary identity-mass class with SPD K, C
    assert isinstance(learned.model_, SecondOrderModel)
    assert np.linalg.eigvalsh(learned.K_)[0] > 0 and np.linalg.eigvalsh(learned.C_)[0] > 0
    assert learned.model_.metadata['mass'] == 'learned'
    assert learned.mass_factor_ is not None and learned.mass_factor_.shape == (R, R)
    # the identity-mass LOpInf cannot represent it
    ident = _fit(episodes, 'identity')
    err_id = np.linalg.norm(ident.model_.simulate(U) - Y) / np.linalg.norm(Y)
    assert err_id > 1e-3, err_id
    assert ident.model_.metadata['mass'] == 'identity'


def test_mass_candidates_are_spd_with_trace_r_and_include_identity(system):
    rng = np.random.default_rng(0)
    A1, A2 = rng.standard_normal((R, R)), rng.standard_normal((R, R))
    cands = mass_candidates(A1, A2, rho=0.5)
    assert np.isinf(cands[-1][0]) and np.array_equal(cands[-1][1], np.eye(R))
    for _, M in cands:
        assert np.allclose(M, M.T) and abs(np.trace(M) - R) < 1e-9
        assert np.linalg.eigvalsh(M)[0] > 0


def test_without_episodes_a_fixed_shrinkage_is_used(system):
    _, episodes = system
    _, _, y = episodes[0]
    from soft_rom.ddt import FiniteDifference
    Q, Qd, Qdd, (U,) = FiniteDifference(8).episodes([y], DT, [[episodes[0][1]]])
    sol, Lt = solve_learned_mass(Q, Qd, Qdd, U)
    assert set(sol.info['mass']['training_simulation_errors']) == {'0.1'}
    assert np.allclose(Lt, np.triu(Lt))


def test_bad_mass_choice_is_refused(system):
    _, episodes = system
    with pytest.raises(ConfigError, match='mass'):
        _fit(episodes, 'heavy')
    with pytest.raises(ConfigError, match='mass'):
        LOpInf(r=R, mass='learned', forces='cubic').fit(ReducedData.from_arrays(
            [y for _, _, y in episodes], [u for _, u, _ in episodes],
            [y for _, _, y in episodes], DT, np.zeros(R)))
