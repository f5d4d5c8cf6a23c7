"""The cubic LOpInf's projected quartic (``quartic='projected'``): known truth and refusals.

The route keeps ``K`` and ``C`` of the least squares and moves the quartic alone to the nearest
sum of squares in the data's metric, certified in the coordinates scaled by their largest
values (:mod:`soft_rom.learners.lopinf.quartic`). The truth it is checked against is the same
constrained least squares solved directly by Clarabel on the uncompressed rows.
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest

from soft_rom.errors import ConfigError, SolverError
from soft_rom.learners.lopinf import cubic as lc
from soft_rom.learners.lopinf.cubic import fit_cubic
from soft_rom.learners.lopinf.quartic import scaled_quartic_bound
from soft_rom.models import CubicSecondOrderModel
from soft_rom.models.tensors import (
    gram_map,
    quartic_certified_positive,
    quartic_lower_bound,
    symmetric_from_entries,
)

DT = 1e-3


def chain(r: int, seed: int, quartic_sign: float) -> CubicSecondOrderModel:
    """A chain of springs with cubic and quartic terms (``quartic_sign`` -1: unbounded below)."""
    rng = np.random.default_rng(seed)
    eye = np.eye(r)
    rows = [eye[0]] + [eye[i] - eye[i - 1] for i in range(1, r)]
    K = sum(k * np.outer(a, a) for k, a in zip(rng.uniform(50, 150, r), rows))
    G = sum(g * np.einsum('i,j,k->ijk', a, a, a) for g, a in zip(rng.uniform(-300, 300, r), rows))
    H = sum(h * np.einsum('i,j,k,l->ijkl', a, a, a, a)
            for h, a in zip(rng.uniform(500, 2000, r), rows))
    return CubicSecondOrderModel(K, 0.5 * eye + 2e-3 * K, G, quartic_sign * H,
                                 rng.standard_normal((r, 2)), rng.standard_normal((3, r)), dt=DT)


def equation_data(model: CubicSecondOrderModel, extents: np.ndarray, k: int, seed: int,
                  noise: float = 0.0):
    """States spread over ``extents`` (decades apart, as POD coordinates are), exact q̈ + noise."""
    rng = np.random.default_rng(seed)
    Q = extents[:, None] * rng.uniform(-1.0, 1.0, (len(extents), k))
    Qd = rng.standard_normal(Q.shape)
    U = rng.standard_normal((2, k))
    Qdd = np.column_stack([model.B @ u - model.C @ v - model.force(q)
                           for q, v, u in zip(Q.T, Qd.T, U.T)])
    return Q, Qd, Qdd + noise * np.abs(Qdd).max() * rng.standard_normal(Qdd.shape), U


def direct_projection(Q, Qd, Qdd, U, K, C, t4, e):
    """The projection solved directly: Clarabel on the uncompressed rows.

    ``min |q̈ + C q̇ + ∇V - B u|²`` over ``G``, ``B`` and a sum-of-squares ``H`` with
    ``X ⪰ t4 I`` in the coordinates ``q / e``, ``K`` and ``C`` held.
    """
    r = Q.shape[0]
    lay = lc._Layout(r, U.shape[0])
    o = lay.t_off
    A, b, _ = lc._compressed(lay, Q, Qd, Qdd, U)
    kc = np.concatenate([K[tuple(np.array(lay.idx[2]).T)], C[tuple(np.array(lay.idx[2]).T)]])
    Tg, ns = gram_map(r)
    w = np.array([np.prod(e[list(a)]) for a in lay.idx[4]])
    g, bb = cp.Variable(o['H'] - o['G']), cp.Variable(lay.n_theta - o['B'])
    X = cp.Variable((ns, ns), symmetric=True)
    h = cp.multiply(1.0 / w, Tg @ cp.vec(X, order='C'))
    theta = cp.hstack([kc[:o['G']], g, h, kc[o['G']:], bb])
    scale = float(np.linalg.norm(b))
    prob = cp.Problem(cp.Minimize(cp.sum_squares(A @ theta - b) / scale ** 2),
                      [X - t4 * np.eye(ns) >> 0])
    prob.solve(solver='CLARABEL')
    assert prob.status == 'optimal'
    return lay.unpack(np.concatenate([kc[:o['G']], g.value, np.asarray(h.value).ravel(),
                                      kc[o['G']:], bb.value]))


def test_projected_quartic_is_the_constrained_least_squares() -> None:
    """A negative quartic: the route's is the directly solved projection's, and certified.

    Data of a chain whose quartic is negative (so the least squares' is): the route's
    quartic, G and B are those of the directly solved constrained problem.
    """
    truth = chain(3, seed=2, quartic_sign=-1.0)
    e_true = np.array([1.0, 0.3, 0.05])                 # extents two decades apart
    Q, Qd, Qdd, U = equation_data(truth, e_true, 600, seed=5, noise=1e-4)
    sol = fit_cubic(Q, Qd, Qdd, U, reg=0.0, quartic='projected')
    info = sol.info
    assert info['method'] == 'least-squares K, C; quartic projected onto sums of squares'
    assert info['quartic_certificate'].startswith('sos')
    e = np.abs(Q).max(axis=1)
    np.testing.assert_allclose(info['quartic_scale'], e, rtol=1e-15)
    t4 = info['quartic_target']
    assert t4 == pytest.approx(1e-6 * np.linalg.eigvalsh(sol.K * np.outer(e, e))[-1], rel=1e-12)
    K, C, G, H, B = direct_projection(Q, Qd, Qdd, U, sol.K, sol.C, t4, e)
    for name, got, want in (('H', sol.H, H), ('G', sol.G, G), ('B', sol.B, B)):
        err = np.linalg.norm(got - want) / np.linalg.norm(want)
        assert err < 2e-3, (name, err)
    # K and C are the least squares' (G, B refitted, H moved); its quartic was not certified
    lay = lc._Layout(3, 2)
    K_ls, C_ls, _G, H_ls, _B = lay.unpack(lc._least_squares(lay, Q, Qd, Qdd, U, 0.0)[0].theta)
    np.testing.assert_allclose(sol.K, K_ls, rtol=1e-10, atol=0)
    np.testing.assert_allclose(sol.C, C_ls, rtol=1e-10, atol=1e-12)
    assert scaled_quartic_bound(H_ls, e) < 0
    # certified in the scaled coordinates, checked independently by a sum-of-squares SDP
    He = np.einsum('ijkl,i,j,k,l->ijkl', sol.H, e, e, e, e)
    t, _how = quartic_lower_bound(He, target=t4)
    assert t >= 0.99 * t4 > 0
    # the potential grows along every direction, beyond the radius (in q / e) where
    # t |q / e|^4 / 24 dominates the cubic term: bounded below
    model = CubicSecondOrderModel(sol.K, sol.C, sol.G, sol.H, sol.B, truth.E, dt=DT)
    radius = 8.0 * np.linalg.norm(np.einsum('ijk,i,j,k->ijk', sol.G, e, e, e)) / t
    for d in np.random.default_rng(0).standard_normal((20, 3)):
        d = e * d / np.linalg.norm(d)
        assert model.potential(2 * radius * d) > model.potential(radius * d) > 0


def test_projected_quartic_of_a_positive_chain_keeps_its_forces() -> None:
    """A positive quartic just below the floor: moved, and the forces on the data kept.

    Data of a chain with a positive quartic, no noise. Its quartic is a sum of squares with
    a margin just below the floor in ``q / e`` (the route moves it): the fitted forces on
    the data are the truth's to 1e-5, ``K`` and ``C`` exactly.
    """
    truth = chain(3, seed=4, quartic_sign=1.0)
    Q, Qd, Qdd, U = equation_data(truth, np.array([1.0, 0.2, 0.04]), 400, seed=1)
    sol = fit_cubic(Q, Qd, Qdd, U, reg=0.0, quartic='projected')
    e, t4 = np.array(sol.info['quartic_scale']), sol.info['quartic_target']
    t_truth, _how = quartic_lower_bound(np.einsum('ijkl,i,j,k,l->ijkl', truth.H, e, e, e, e),
                                        target=1e9)
    assert 0 < t_truth < t4 <= sol.info['certificate']
    assert sol.info['method'] == 'least-squares K, C; quartic projected onto sums of squares'
    for name in ('K', 'C'):
        want = getattr(truth, name)
        assert np.linalg.norm(getattr(sol, name) - want) <= 1e-10 * np.linalg.norm(want), name
    model = CubicSecondOrderModel(sol.K, sol.C, sol.G, sol.H, sol.B, truth.E, dt=DT)
    F, F0 = (np.column_stack([m.force(q) for q in Q.T]) for m in (model, truth))
    assert np.linalg.norm(F - F0) <= 1e-5 * np.linalg.norm(F0)
    assert sol.info['objective_relative'] <= 1e-5


def test_projected_refuses_an_indefinite_least_squares_and_unknown_routes() -> None:
    """K of the least squares indefinite (data of a softening spring): one line, no fit."""
    truth = chain(3, seed=2, quartic_sign=1.0)
    soft = CubicSecondOrderModel(truth.K - 200.0 * np.eye(3), truth.C, truth.G, truth.H,
                                 truth.B, truth.E, dt=DT)
    Q, Qd, Qdd, U = equation_data(soft, np.array([1.0, 0.3, 0.1]), 300, seed=2)
    with pytest.raises(SolverError, match='quartic="projected" keeps K and C') as err:
        fit_cubic(Q, Qd, Qdd, U, reg=0.0, quartic='projected')
    assert '\n' not in str(err.value)
    with pytest.raises(ConfigError, match='known: conic, projected'):
        fit_cubic(Q, Qd, Qdd, U, quartic='nearest')


def test_trust_check_certifies_a_sum_of_squares_whose_coordinates_span_decades() -> None:
    """A certified model's quartic in coordinates three decades apart is trusted.

    ``H(q) = H̃(q / e)`` with ``H̃`` a sum of squares (Gram matrix ``⪰ 1e-3 I``) and ``e`` from 1
    to 1e-3, as the projected route returns on POD coordinates. In these coordinates the
    sum-of-squares solver's tolerance, relative to the largest coefficient (1e12 times the
    smallest), loses the certificate; with the diagonal made one it holds. Its negative is
    refused either way.
    """
    r = 4
    rng = np.random.default_rng(0)
    Tg, ns = gram_map(r)
    F = rng.standard_normal((ns, 3))
    Ht = symmetric_from_entries(Tg @ (F @ F.T + 1e-3 * np.eye(ns)).ravel(), r, 4)
    s = 1.0 / np.array([1.0, 1e-1, 1e-2, 1e-3])
    H = np.einsum('ijkl,i,j,k,l->ijkl', Ht, s, s, s, s)
    assert quartic_lower_bound(H, target=0.0)[0] < 0         # unscaled: not certified
    assert quartic_certified_positive(H) and not quartic_certified_positive(-H)
    K = np.diag(s ** 2)
    model = CubicSecondOrderModel(K, 0.1 * np.eye(r), np.zeros((r, r, r)), H,
                                  rng.standard_normal((r, 2)), rng.standard_normal((3, r)),
                                  dt=DT)
    assert not any('quartic' in issue for issue in model.trust_issues()), model.trust_issues()
    bad = CubicSecondOrderModel(K, 0.1 * np.eye(r), np.zeros((r, r, r)), -H, model.B, model.E,
                                dt=DT)
    assert any('quartic' in issue for issue in bad.trust_issues())


def test_learner_takes_the_projected_route_and_its_file_loads_trusted(tmp_path) -> None:
    """``LOpInf(cubic_options={'quartic': 'projected'})`` through POD, saved and loaded.

    Trajectories of a chain with a positive quartic. Its least squares is certified here, so
    both routes keep it: the option reaches the fit, the model predicts as the default
    route's does (to 1e-3 relative), and the file loads trusted.
    """
    from soft_rom.data import Episode
    from soft_rom.learners.lopinf import LOpInf
    from soft_rom.metrics import relative_error
    from soft_rom.models import load_model
    truth = chain(3, seed=4, quartic_sign=1.0)
    rng = np.random.default_rng(3)
    U = np.repeat(5.0 * rng.standard_normal((2, 30)), 100, axis=1)
    Y, X = truth.simulate(U, return_states=True)
    q_ref = np.array([0.1, 0.2, 0.3])
    eps = [Episode(t=np.arange(1500) * DT, U=U[:, s], Y=Y[:, s], Q=X[:3, s] + q_ref[:, None],
                   name=f'ep{i}') for i, s in enumerate((slice(0, 1500), slice(1500, 3000)))]
    fits = {route: LOpInf(r=3, forces='cubic', cubic_options={'reg': 0.0, 'quartic': route})
            .fit(eps, q_ref=q_ref) for route in ('conic', 'projected')}
    Yp = {route: f.model_.simulate(eps[0].U) for route, f in fits.items()}
    assert relative_error(Yp['conic'], Yp['projected']) < 1e-3
    assert relative_error(eps[0].Y, Yp['projected']) < 0.05
    back = load_model(fits['projected'].model_.save(tmp_path / 'projected.npz'))
    assert back.trusted, back.trust_issues()
    np.testing.assert_array_equal(back.simulate(eps[0].U), Yp['projected'])
