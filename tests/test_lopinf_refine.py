"""Output-error refinement of LOpInf (:mod:`soft_rom.learners.lopinf.refine`).

Known truth: a 3-DOF damped chain simulated exactly with held inputs. The gradient and the
Fréchet derivatives are checked against finite differences and scipy; the refinement
recovers the true operators from a wrong start on exact data, keeps the constraints on
noisy data, and removes the bias that noise puts into the equation-error fit.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from soft_rom.data import Episode
from soft_rom.ddt import SavitzkyGolay
from soft_rom.errors import ConfigError
from soft_rom.learners.lopinf import LOpInf
from soft_rom.learners.lopinf.refine import (
    _frechet_rows,
    _frechet_rows_direct,
    _Problem,
    initial_states,
    refine_output_error,
)
from soft_rom.metrics import relative_deviation_error
from soft_rom.reduce import ReducedData

R, M_IN, DT = 3, 2, 0.01
K_TRUE = np.array([[40.0, -20.0, 0.0], [-20.0, 40.0, -20.0], [0.0, -20.0, 20.0]])
C_TRUE = 0.6 * np.eye(R) + 0.01 * K_TRUE
B_TRUE = np.array([[1.0, 0.0], [0.0, 0.5], [0.3, 1.0]])


def simulate(K, C, B, U, x0=None):
    n = 2 * R
    M = np.zeros((n + M_IN, n + M_IN))
    M[:R, R:n] = np.eye(R)
    M[R:n, :R], M[R:n, R:n], M[R:n, n:] = -K, -C, B
    F = sla.expm(M * DT)
    x = np.zeros(n) if x0 is None else np.asarray(x0, dtype=float)
    X = np.empty((n, U.shape[1]))
    for j in range(U.shape[1]):
        X[:, j] = x
        x = F[:n, :n] @ x + F[:n, n:] @ U[:, j]
    return X[:R]


def episodes(seed, k=800, noise=0.0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(2):
        U = np.repeat(rng.uniform(-1, 1, (M_IN, k // 40 + 1)), 40, axis=1)[:, :k]
        Q = simulate(K_TRUE, C_TRUE, B_TRUE, U)
        out.append((Q + noise * rng.standard_normal(Q.shape), U))
    return out


def test_frechet_rows_match_scipy_also_when_nearly_defective():
    rng = np.random.default_rng(3)
    for k_low, b_scale in ((1.0, 1.0), (1e-9, 1.0), (1.0, 1e4)):
        K = np.diag([k_low, 30.0, 900.0])
        n, N = 2 * R, 2 * R + M_IN
        M = np.zeros((N, N))
        M[:R, R:n] = np.eye(R)
        M[R:n, :R], M[R:n, R:n] = -K, -(0.1 * np.eye(R) + 0.01 * K)
        M[R:n, n:] = b_scale * rng.standard_normal((R, M_IN))
        M *= 0.05
        F, dF = _frechet_rows(M, R, n, 0.05)
        assert np.allclose(F, sla.expm(M), rtol=1e-12, atol=1e-14)
        for a in range(R):
            for b in range(N):
                E = np.zeros((N, N))
                E[R + a, b] = 0.05
                ref = sla.expm_frechet(M, E, compute_expm=False)[:n]
                assert np.max(np.abs(dF[a * N + b] - ref)) <= 1e-10 * max(1.0, np.abs(ref).max())


def test_frechet_rows_match_scipy_over_many_panels():
    # ||A||_1 = 45: 45 panels, each node's exponentials as products of whole-panel and
    # in-panel ones (the direct path takes over above 64)
    rng = np.random.default_rng(0)
    r, m = 8, 6
    n, N = 2 * r, 2 * r + m
    M = np.zeros((N, N))
    M[:r, r:n] = np.eye(r)
    K = np.diag(np.geomspace(1e-3, 900.0, r))
    M[r:n, :r], M[r:n, r:n] = -K, -(0.1 * np.eye(r) + 0.01 * K)
    M[r:n, n:] = rng.standard_normal((r, m))
    M *= 0.05
    assert 40 < np.linalg.norm(M[:n, :n], 1) < 64
    F, dF = _frechet_rows(M, r, n, 0.05)
    F_ref, dF_ref = _frechet_rows_direct(M, r, n, 0.05)
    assert np.allclose(F, F_ref, rtol=1e-12, atol=1e-14)
    assert np.abs(dF - dF_ref).max() <= 1e-10 * np.abs(dF_ref).max()


def test_gradient_matches_finite_differences():
    data = episodes(0, k=300, noise=0.01)
    Lt = np.eye(R) + 0.2 * np.triu(np.ones((R, R)), 1)
    for free_mass in (False, True):
        prob = _Problem(data, DT, Lt, {'alpha': 0.2, 'beta': 0.005, 'eps_K': 0.5},
                        free_mass=free_mass)
        p = prob.pack(1.1 * K_TRUE, 1.2 * C_TRUE, 0.9 * B_TRUE, initial_states(data, Lt, DT))
        _, Jtr, cost = prob.normal(p)
        assert cost == pytest.approx(prob.cost(p), rel=1e-12)
        h = 1e-6 * np.maximum(1.0, np.abs(p))
        fd = np.array([(prob.cost(p + h[i] * e) - prob.cost(p - h[i] * e)) / (4 * h[i])
                       for i, e in enumerate(np.eye(p.size))])
        assert np.max(np.abs(fd - Jtr)) <= 1e-5 * np.max(np.abs(Jtr))


def test_exact_data_recovers_the_operators_from_a_wrong_start():
    data = episodes(1, k=400)
    K, C, B, info = refine_output_error(1.3 * K_TRUE, 0.6 * C_TRUE + 0.2 * np.eye(R),
                                        0.8 * B_TRUE, data, DT, eps=1e-6, max_iter=60,
                                        tol=1e-14)
    assert info['cost'] < 1e-16 * info['cost_start']
    for got, true in ((K, K_TRUE), (C, C_TRUE), (B, B_TRUE)):
        assert np.linalg.norm(got - true) <= 1e-6 * np.linalg.norm(true)


def test_noisy_data_keeps_the_constraints_and_never_gets_worse():
    data = episodes(2, k=500, noise=0.002)
    margin = {'alpha': 0.5, 'beta': 0.01, 'eps_K': 1.0}
    K0, C0 = K_TRUE + 5 * np.eye(R), C_TRUE + 0.5 * np.eye(R)
    K, C, B, info = refine_output_error(K0, C0, B_TRUE, data, DT, margin=margin)
    assert 0.0 <= info['improvement'] and info['cost'] <= info['cost_start']
    assert np.linalg.eigvalsh(K)[0] >= 1.0 - 1e-9
    assert np.linalg.eigvalsh(C - 0.5 * np.eye(R) - 0.01 * K)[0] >= -1e-9
    assert np.linalg.norm(K - K_TRUE) <= 0.03 * np.linalg.norm(K_TRUE)


def test_lopinf_refine_removes_the_noise_bias_of_the_equation_error_fit():
    data = episodes(4, k=1500, noise=0.003)
    test_U = episodes(5, k=1500)[0][1]
    test_Q = simulate(K_TRUE, C_TRUE, B_TRUE, test_U)
    eps_list = [Episode(t=np.arange(q.shape[1]) * DT, U=u, Y=q) for q, u in data]
    errors = {}
    for refine in ('none', 'output-error'):
        lrn = LOpInf(r=R, ddt=SavitzkyGolay(), refine=refine).fit(ReducedData.from_arrays(
            [e.Y for e in eps_list], [e.U for e in eps_list], [e.Y for e in eps_list], DT,
            y_ref=np.zeros(R)))
        Y = lrn.model_.simulate(test_U)
        errors[refine] = relative_deviation_error(test_Q, Y, np.zeros(R))
        assert lrn.model_.stability_margin() > 0
        assert lrn.model_.metadata['diagnostics']['refinement']['criterion'] == refine
    assert errors['output-error'] < 0.5 * errors['none']
    assert errors['output-error'] < 0.01


def test_refine_is_refused_with_cubic_forces_and_unknown_names():
    with pytest.raises(ConfigError, match='refine'):
        LOpInf(r=2, refine='simulation').fit(ReducedData.from_arrays(
            [np.ones((2, 50)) * np.linspace(0, 1, 50)], [np.ones((1, 50))],
            [np.ones((2, 50))], 0.01))


def test_a_refinement_that_predicts_the_held_out_tails_worse_is_rejected():
    # the last 20 % of every episode come from another system (inputs act with the opposite
    # sign), which the start describes: fitted on the heads, the refinement learns the
    # heads' system, predicts the tails worse than the start, and the start is returned
    rng = np.random.default_rng(7)
    data = []
    for _ in range(2):
        U = np.repeat(rng.uniform(-1, 1, (M_IN, 21)), 40, axis=1)[:, :800]
        head = simulate(K_TRUE, C_TRUE, B_TRUE, U)
        tail = simulate(K_TRUE, C_TRUE, -B_TRUE, U)
        data.append((np.hstack([head[:, :640], tail[:, 640:]]), U))
    K, C, B, info = refine_output_error(K_TRUE, C_TRUE, -B_TRUE, data, DT)
    assert info['status'] == 'rejected_on_holdout'
    val = info['validation']
    assert val['tail_error_refined'] > val['tail_error_start']
    assert np.array_equal(B, -B_TRUE) and np.allclose(K, K_TRUE, rtol=1e-9)
    assert info['improvement'] == 0.0
    # without validation the same data are fitted (and the heads' system wins)
    _, _, _, info = refine_output_error(K_TRUE, C_TRUE, -B_TRUE, data, DT, holdout=0.0)
    assert info['status'] != 'rejected_on_holdout' and info['improvement'] > 0


def test_a_problem_too_large_to_refine_here_is_skipped_and_said(monkeypatch):
    import soft_rom.learners.lopinf.refine as lr
    data = episodes(8, k=300)
    monkeypatch.setattr(lr, 'MAX_WORK', 1e3)
    K, C, B, info = lr.refine_output_error(1.2 * K_TRUE, C_TRUE, B_TRUE, data, DT)
    assert info['status'] == 'skipped_too_large' and info['improvement'] == 0.0
    assert np.array_equal(K, 1.2 * K_TRUE) and np.array_equal(B, B_TRUE)
