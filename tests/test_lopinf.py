"""Tests of LOpInf and its operator solvers against known truth."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.integrate as sint
import scipy.linalg as sla

from soft_rom.data import Episode
from soft_rom.ddt import FiniteDifference
from soft_rom.errors import DimensionError, NotFittedError, ResourceError
from soft_rom.learners.lopinf import LOpInf
from soft_rom.learners.lopinf.solvers import (
    CvxpySolver,
    DEFAULT_EPS,
    FastSPDSolver,
    objective,
    OperatorSolver,
    reduce_data,
)
from soft_rom.models import load_model


def _spd(rng, r, lo, hi):
    Qm, _ = np.linalg.qr(rng.standard_normal((r, r)))
    return (Qm * np.linspace(lo, hi, r)) @ Qm.T


def _rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def _chain_episodes(n=30, m=4, k=1500, dt=1e-3, noise=1e-3, seeds=(1, 2, 3)):
    """Damped chain driven by antagonistic pairs (u2 = -u1, u4 = -u3); noisy states."""
    kk = 4e3 * np.linspace(1.0, 0.2, n)
    Kf = np.diag(kk + np.r_[kk[1:], 0.0]) - np.diag(kk[1:], 1) - np.diag(kk[1:], -1)
    Cf = 0.5 * np.eye(n) + 2e-3 * Kf
    Bf = np.zeros((n, m))
    Bf[n // 3:n // 3 + 3, 0] = 50.0
    Bf[n // 3 + 3:n // 3 + 6, 1] = -40.0
    Bf[2 * n // 3:2 * n // 3 + 3, 2] = 50.0
    Bf[2 * n // 3 + 3:2 * n // 3 + 6, 3] = -40.0
    M = np.zeros((2 * n + m, 2 * n + m))
    M[:n, n:2 * n] = np.eye(n) * dt
    M[n:2 * n, :n] = -Kf * dt
    M[n:2 * n, n:2 * n] = -Cf * dt
    M[n:2 * n, 2 * n:] = Bf * dt
    E = sla.expm(M)
    Ad, Bd = E[:2 * n, :2 * n], E[:2 * n, 2 * n:]
    q0 = np.linspace(0.0, 0.3, n)
    out = []
    for seed in seeds:
        rng = np.random.default_rng(seed)
        t = np.arange(k) * dt
        U = np.zeros((m, k))
        for i in (0, 2):
            U[i] = 1e3 * sum(np.sin(2 * np.pi * rng.uniform(0.5, 4) * t + rng.uniform(0, 6))
                             for _ in range(3))
            U[i + 1] = -U[i]
        X = np.zeros((2 * n, k))
        for j in range(k - 1):
            X[:, j + 1] = Ad @ X[:, j] + Bd @ U[:, j]
        Q = q0[:, None] + X[:n] + noise * np.std(X[:n]) * rng.standard_normal((n, k))
        out.append(Episode(t=t, U=U, Y=Q[[5, 15, n - 1]], Q=Q, name=f'ep{seed}',
                           metadata={'input_names': [f'p{i}' for i in range(m)],
                                     'input_units': ['Pa'] * m}))
    return out


def test_solver_recovers_exact_operators():
    rng = np.random.default_rng(0)
    r, m, k = 6, 3, 400
    K, C = _spd(rng, r, 1.0, 50.0), _spd(rng, r, 0.1, 5.0)
    B = rng.standard_normal((r, m))
    Q, Qd, U = (rng.standard_normal((r, k)), rng.standard_normal((r, k)),
                rng.standard_normal((m, k)))
    Qdd = B @ U - C @ Qd - K @ Q
    Ks, Cs, Bs, info = FastSPDSolver().solve(Q, Qd, Qdd, U)
    assert isinstance(FastSPDSolver(), OperatorSolver)
    assert info['method'] == 'symmetric-least-squares'
    assert _rel(Ks, K) < 1e-8 and _rel(Cs, C) < 1e-8 and _rel(Bs, B) < 1e-8


def test_lopinf_recovers_operators_from_exact_derivative_data():
    # Polynomial trajectories of degree 8: 8th-order central differences are exact.
    rng = np.random.default_rng(1)
    r, n, dt, k = 3, 20, 0.01, 60
    K, C = _spd(rng, r, 2.0, 30.0), _spd(rng, r, 0.5, 4.0)
    B = rng.standard_normal((r, r)) + 3 * np.eye(r)
    Phi, _ = np.linalg.qr(rng.standard_normal((n, r)))
    q_ref = rng.standard_normal(n)
    t = np.arange(k) * dt
    episodes = []
    for j in range(4):
        polys = [np.polynomial.Polynomial(rng.standard_normal(9)) for _ in range(r)]
        q = np.array([p(t) for p in polys])
        qd = np.array([p.deriv(1)(t) for p in polys])
        qdd = np.array([p.deriv(2)(t) for p in polys])
        U = np.linalg.solve(B, qdd + C @ qd + K @ q)
        Qf = q_ref[:, None] + Phi @ q
        episodes.append(Episode(t=t, U=U, Y=Qf[:4], Q=Qf, name=f'p{j}'))
    est = LOpInf(r=r).fit(episodes, q_ref=q_ref, y_ref=q_ref[:4])
    R = est.basis_.T @ Phi                    # q̂ = R q, R orthogonal
    assert _rel(est.K_, R @ K @ R.T) < 1e-8
    assert _rel(est.C_, R @ C @ R.T) < 1e-8
    assert _rel(est.B_, R @ B) < 1e-8
    assert _rel(est.E_, Phi[:4] @ R.T) < 1e-8
    assert est.solver_info_['method'] == 'symmetric-least-squares'


def _noisy_indefinite(seed=3, r=6, m=4, k=400, rank_deficient=False):
    rng = np.random.default_rng(seed)
    K, C = _spd(rng, r, 1e-3, 10.0), _spd(rng, r, 1e-3, 2.0)
    B = rng.standard_normal((r, m))
    Q, Qd, U = (rng.standard_normal((r, k)), rng.standard_normal((r, k)),
                rng.standard_normal((m, k)))
    if rank_deficient:
        U[m // 2:] = -U[:m // 2]
    Qdd = B @ U - C @ Qd - K @ Q + 3.0 * rng.standard_normal((r, k))
    return Q, Qd, Qdd, U


@pytest.mark.parametrize('rank_deficient', [False, True])
def test_constrained_fit_is_spd_and_matches_clarabel(rank_deficient):
    Q, Qd, Qdd, U = _noisy_indefinite(rank_deficient=rank_deficient)
    # The symmetric least-squares fit is indefinite: the constraints are active.
    r = Q.shape[0]
    D = np.vstack([Qd, Q, U])
    W, *_ = np.linalg.lstsq(D.T, -Qdd.T, rcond=None)
    W = W.T
    lam = min(np.linalg.eigvalsh(0.5 * (W[:, :r] + W[:, :r].T))[0],
              np.linalg.eigvalsh(0.5 * (W[:, r:2 * r] + W[:, r:2 * r].T))[0])
    assert lam < 0
    fast = FastSPDSolver().solve(Q, Qd, Qdd, U)
    assert fast.info['method'] == 'primal-dual-interior-point'
    for M in (fast.K, fast.C):
        np.testing.assert_array_equal(M, M.T)
        assert np.linalg.eigvalsh(M)[0] >= DEFAULT_EPS * (1 - 1e-9)
    o_fast = objective(*fast[:3], Q, Qd, Qdd, U)
    for form in ('reduced', 'raw'):
        ref = CvxpySolver('CLARABEL', formulation=form).solve(Q, Qd, Qdd, U)
        o_ref = objective(*ref[:3], Q, Qd, Qdd, U)
        assert (o_fast - o_ref) / o_ref <= 1e-6, (form, o_fast, o_ref)   # not worse
        assert abs(o_fast - o_ref) / o_ref <= 1e-6
    assert abs(fast.info['objective'] - o_fast) <= 1e-9 * o_fast


def test_rank_deficient_inputs_give_minimum_norm_B():
    rng = np.random.default_rng(4)
    r, m, k = 4, 4, 300
    K, C = _spd(rng, r, 1.0, 20.0), _spd(rng, r, 0.2, 3.0)
    B = rng.standard_normal((r, m))
    Q, Qd = rng.standard_normal((r, k)), rng.standard_normal((r, k))
    U = rng.standard_normal((m, k))
    U[2:] = -U[:2]                                    # antagonistic pairs: rank 2
    Qdd = B @ U - C @ Qd - K @ Q
    Ks, Cs, Bs, info = FastSPDSolver().solve(Q, Qd, Qdd, U)
    assert info['rank_u'] == 2
    assert np.all(np.isfinite(Bs))
    assert _rel(Ks, K) < 1e-8 and _rel(Cs, C) < 1e-8
    assert _rel(Bs @ U, B @ U) < 1e-8
    # Minimum norm: the two columns of a pair share the effect equally, with opposite signs.
    np.testing.assert_allclose(Bs[:, 2:], -Bs[:, :2], atol=1e-8 * np.abs(B).max())
    np.testing.assert_allclose(Bs[:, :2], 0.5 * (B[:, :2] - B[:, 2:]), rtol=1e-8, atol=1e-10)
    prob = reduce_data(Q, Qd, Qdd, U)
    assert prob.A.shape == (2 * r, 3 * r) and prob.G.shape == (r, 3 * r)


def test_zoh_model_matches_fine_ode_solution():
    episodes = _chain_episodes(seeds=(1,), k=800)
    est = LOpInf(r=4).fit(episodes)
    model = est.model_
    U = episodes[0].U[:, :120]
    Y = model.simulate(U)
    Ac, Bc, Cc = model.first_order()
    x = np.zeros(2 * model.r)
    Y_ode = np.empty_like(Y)
    for j in range(U.shape[1]):
        Y_ode[:, j] = Cc @ x + model.y_ref
        sol = sint.solve_ivp(lambda _t, z, u=U[:, j]: Ac @ z + Bc @ u, (0.0, model.dt), x,
                             method='DOP853', rtol=1e-12, atol=1e-14 * (1 + np.abs(x).max()))
        x = sol.y[:, -1]
    dev = Y - model.y_ref[:, None]
    assert np.linalg.norm(Y - Y_ode) / np.linalg.norm(dev) < 1e-6


def test_unit_invariance_and_metadata(tmp_path):
    episodes = _chain_episodes(noise=3e-2)
    est = LOpInf(r=8).fit(episodes[:2])
    # Heavy noise makes the constraints active, so the barrier path is what is tested here.
    assert est.solver_info_['method'] == 'primal-dual-interior-point'
    test = episodes[2]
    Y = est.predict(test.U)
    # Pa -> kPa for the inputs, m -> mm for the states and outputs.
    scaled = [Episode(t=e.t, U=e.U / 1e3, Y=e.Y * 1e3, Q=e.Q * 1e3, name=e.name)
              for e in episodes[:2]]
    Y2 = LOpInf(r=8).fit(scaled).predict(test.U / 1e3) / 1e3
    dev = Y - est.y_ref_[:, None]
    assert np.linalg.norm(Y2 - Y) / np.linalg.norm(dev) < 1e-6
    model = est.model_
    assert model.input_names == ['p0', 'p1', 'p2', 'p3'] and model.input_units[0] == 'Pa'
    diag = model.metadata['diagnostics']
    assert diag['eps'] == DEFAULT_EPS and min(diag['eigenvalues_K']) >= DEFAULT_EPS * 0.999
    assert model.metadata['provenance']['episodes'] == ['ep1', 'ep2']
    assert model.stability_margin() > 0
    path = tmp_path / 'rom.npz'
    model.save(path)
    loaded = load_model(path)
    np.testing.assert_array_equal(loaded.K, model.K)
    np.testing.assert_array_equal(loaded.simulate(test.U[:, :50]), model.simulate(test.U[:, :50]))


class _Lazy:
    def __init__(self, data):
        self._data = data
        self.shape = data.shape

    def __getitem__(self, key):
        return self._data[key].copy()


def test_lazy_states_and_errors():
    episodes = _chain_episodes(seeds=(5,), k=400, noise=1e-3)
    ep = episodes[0]
    lazy = Episode(t=ep.t, U=ep.U, Y=ep.Y, Q=_Lazy(ep.Q), name='lazy')
    a = LOpInf(r=3, ddt=6).fit([ep])
    b = LOpInf(r=3, ddt=6).fit([lazy])
    np.testing.assert_allclose(b.K_, a.K_, rtol=1e-10)
    with pytest.raises(NotFittedError):
        LOpInf().predict(ep.U)
    with pytest.raises(DimensionError):
        LOpInf().fit([Episode(t=ep.t, U=ep.U, Y=ep.Y)])


def test_fast_solver_on_ill_conditioned_pod_data_matches_clarabel():
    # Reduced data as LOpInf builds them from a noisy simulated body (POD, 8th-order FD):
    # ill-conditioned, antagonistic inputs (rank-deficient U), constraints active.
    episodes = _chain_episodes(noise=3e-2, seeds=(6, 7))
    est = LOpInf(r=8).fit(episodes)
    V, q_ref = est.basis_, est.q_ref_
    Qhat = [V.T @ (e.Q - q_ref[:, None]) for e in episodes]
    Q, Qd, Qdd, (U,) = FiniteDifference(8).episodes(Qhat, 1e-3, [[e.U for e in episodes]])
    assert np.linalg.cond(np.vstack([Qd, Q])) > 1e2
    tight = dict(tol_gap_abs=1e-10, tol_gap_rel=1e-10, tol_feas=1e-10)
    ref = CvxpySolver('CLARABEL', **tight).solve(Q, Qd, Qdd, U)
    fast = FastSPDSolver().solve(Q, Qd, Qdd, U)
    assert fast.info['method'] == 'primal-dual-interior-point' and fast.info['rank_u'] == 2
    o_ref = objective(*ref[:3], Q, Qd, Qdd, U)
    o_fast = objective(*fast[:3], Q, Qd, Qdd, U)
    assert abs(o_fast - o_ref) / o_ref < 1e-6
    assert min(np.linalg.eigvalsh(fast.K)[0], np.linalg.eigvalsh(fast.C)[0]) >= DEFAULT_EPS


def _random_problem(seed, r=6, k=400, m=2):
    rng = np.random.default_rng(seed)
    K, C = _spd(rng, r, -2.0, 10.0), _spd(rng, r, -1.0, 3.0)      # indefinite truth
    B = rng.standard_normal((r, m))
    Q, Qd, U = (rng.standard_normal((r, k)), rng.standard_normal((r, k)),
                rng.standard_normal((m, k)))
    Qdd = -C @ Qd - K @ Q + B @ U + 0.1 * rng.standard_normal((r, k))
    return Q, Qd, Qdd, U


@pytest.mark.parametrize('eps', [1e-6, (0.5, 1e-6), (1e-6, 3.0), (0.2, 2.0)])
def test_interior_point_matches_clarabel_with_separate_margins(eps):
    # Both constraints active (no K elimination) or only C's (K eliminated exactly).
    Q, Qd, Qdd, U = _random_problem(11)
    tight = dict(tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11)
    ref = CvxpySolver('CLARABEL', **tight).solve(Q, Qd, Qdd, U, eps=eps)
    fast = FastSPDSolver().solve(Q, Qd, Qdd, U, eps=eps)
    e_c, e_k = (eps, eps) if np.isscalar(eps) else eps
    assert np.linalg.eigvalsh(fast.C)[0] >= e_c * (1 - 1e-9)
    assert np.linalg.eigvalsh(fast.K)[0] >= e_k * (1 - 1e-9)
    o_ref = objective(*ref[:3], Q, Qd, Qdd, U)
    o_fast = objective(*fast[:3], Q, Qd, Qdd, U)
    assert (o_fast - o_ref) / o_ref <= 1e-8
    # The certified bound brackets the optimum.
    assert fast.info['objective_lower_bound'] <= o_ref * (1 + 1e-9)
    assert fast.info['gap_bound'] <= 1e-9


def test_symmetric_kronecker_hessian_matches_the_quadratic_form():
    from soft_rom.learners.lopinf.ipm import SymIndex
    rng = np.random.default_rng(0)
    for r in (1, 3, 7):
        idx = SymIndex(r)
        A = rng.standard_normal((2 * r, 3 * r))
        M = A @ A.T
        H = idx.hessian_quadratic(M)
        np.testing.assert_allclose(H, idx._hessian_quadratic_reference(M), atol=1e-12)
        th = rng.standard_normal(2 * idx.n)
        C, K = idx.split(th)
        W = np.hstack([C, K])
        assert th @ H @ th == pytest.approx(np.trace(W @ M @ W.T), rel=1e-12)
        Xi = _spd(rng, r, 0.5, 2.0)
        D = idx.smat(th[:idx.n])
        np.testing.assert_allclose(idx.skron(Xi) @ th[:idx.n], idx.svec(Xi @ D @ Xi),
                                   atol=1e-12)


def test_modal_table_of_known_oscillators():
    from soft_rom.learners.lopinf.margins import least_damped_mode, modal_table
    w = np.array([2.0, 30.0])
    z = np.array([0.05, 0.3])
    modes = modal_table(np.diag(w ** 2), np.diag(2 * z * w))
    assert len(modes) == 2
    for mode, wi, zi in zip(modes, w, z):
        assert mode['frequency_hz'] == pytest.approx(wi / (2 * np.pi), rel=1e-12)
        assert mode['damping_ratio'] == pytest.approx(zi, rel=1e-12)
    assert least_damped_mode(np.diag(w ** 2), np.diag(2 * z * w))['damping_ratio'] == \
        pytest.approx(0.05)


def test_damping_margin_holds_for_every_mode():
    # Noisy chain data at r = 8: the margin 0.3 is active; every mode has ζ >= 0.3, even
    # though K and C do not commute; with ζ_min = 0 the absolute margin alone is used.
    episodes = _chain_episodes(noise=3e-2, seeds=(6, 7))
    est = LOpInf(r=8, min_damping_ratio=0.3).fit(episodes)
    from soft_rom.learners.lopinf.margins import modal_table
    zetas = [m['damping_ratio'] for m in modal_table(est.K_, est.C_)]
    assert min(zetas) >= 0.3 * (1 - 1e-7)
    diag = est.diagnostics_
    assert diag['margin']['active'] and diag['margin']['min_damping_ratio'] == 0.3
    assert diag['least_damped_mode']['damping_ratio'] == pytest.approx(min(zetas))
    assert est.model_.metadata['diagnostics']['least_damped_mode'] == diag['least_damped_mode']
    plain = LOpInf(r=8, min_damping_ratio=0.0).fit(episodes)
    assert not plain.diagnostics_['margin']['active']
    assert min(m['damping_ratio'] for m in modal_table(plain.K_, plain.C_)) < 0.3


def test_tikhonov_columns_add_the_penalty_and_selection_is_reported():
    from soft_rom.learners.lopinf.margins import augment_tikhonov
    Q, Qd, Qdd, U = _random_problem(3)
    Qa, Qda, Qdda, Ua, lam = augment_tikhonov(Q, Qd, Qdd, U, 1e-3)
    rng = np.random.default_rng(1)
    K, C, B = rng.standard_normal((6, 6)), rng.standard_normal((6, 6)), rng.standard_normal((6, 2))
    lhs = objective(K, C, B, Qa, Qda, Qdda, Ua) ** 2
    rhs = (objective(K, C, B, Q, Qd, Qdd, U) ** 2 + lam['C'] * np.sum(C ** 2)
           + lam['K'] * np.sum(K ** 2) + lam['B'] * np.sum(B ** 2))
    assert lhs == pytest.approx(rhs, rel=1e-12)
    assert lam['K'] == pytest.approx(1e-3 * np.sum(Q ** 2) / 6)
    episodes = _chain_episodes(noise=3e-2, seeds=(6, 7))
    est = LOpInf(r=6, regularization='auto', reg_grid=(0.0, 1e-6, 1e-3, 1e3)).fit(episodes)
    reg = est.diagnostics_['regularization']
    table = reg['candidates']
    assert reg['mode'] == 'auto' and [row['gamma'] for row in table] == [0.0, 1e-6, 1e-3, 1e3]
    ok = [row for row in table if not row['rejected']]
    assert reg['gamma'] == min(ok, key=lambda row: row['tail_error'])['gamma']
    fixed = LOpInf(r=6, regularization=1e-3).fit(episodes)
    assert fixed.diagnostics_['regularization'] == {'mode': 'fixed', 'gamma': 1e-3,
                                                    'lambda': fixed.diagnostics_[
                                                        'regularization']['lambda']}
    with pytest.raises(Exception, match='regularization'):
        LOpInf(r=6, regularization='sometimes').fit(episodes)


def test_model_for_equals_a_fit_at_that_r() -> None:
    # a sweep over r is one POD plus one operator solve per r: model_for(r) must equal a
    # learner fitted at r directly (same basis, same coordinates), and refuse r out of range
    from soft_rom.errors import ConfigError

    eps = _chain_episodes(n=20, k=800, seeds=(1, 2))
    big = LOpInf(r=6).fit(eps)
    for r in (2, 4, 6):
        small = LOpInf(r=r).fit(eps).model_
        got = big.model_for(r)
        assert got.r == r
        for name in ('K', 'C', 'B', 'E'):
            a, b = getattr(got, name), getattr(small, name)
            assert np.linalg.norm(a - b) <= 1e-8 * max(np.linalg.norm(b), 1e-300), name
        assert got.metadata['diagnostics']['energy_captured'] == pytest.approx(
            small.metadata['diagnostics']['energy_captured'], rel=1e-12)
    assert big.model_for(6) is big.model_
    for bad in (0, 7, 2.5):
        with pytest.raises(ConfigError):
            big.model_for(bad)


def test_an_r_whose_solve_cannot_fit_in_memory_is_one_line() -> None:
    """A too large r is refused before the solve, with the memory it would need.

    LOpInf(r=500) (the POD allows r up to the number of singular values) ended in numpy's
    MemoryError "Unable to allocate 117. GiB for an array with shape (125250, 125250)".
    """
    rng = np.random.default_rng(0)
    k = 620
    ep = Episode(t=np.arange(k) * 1e-3, U=rng.normal(size=(2, k)), Y=rng.normal(size=(3, k)),
                 Q=rng.normal(size=(600, k)), name='wide')
    with pytest.raises(ResourceError, match=r'the LOpInf operator solve at r=500 \(250500 '
                                            r'unknowns\) needs about .* GiB.*smaller r'):
        LOpInf(r=500).fit([ep])
