"""The eel FOM: geometry, loads, outputs, linearization, small/large pressure response."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from soft_rom.errors import ConfigError, DimensionError
from soft_rom.sim import EelModel, random_pressures, simulate_episode


@pytest.fixture(scope='module')
def eel() -> EelModel:
    return EelModel()


def test_default_mesh_size_and_body(eel: EelModel) -> None:
    assert eel.n_dof == 5145
    X = eel.mesh.nodes
    assert X[:, 0].min() == 0.0 and X[:, 0].max() == pytest.approx(1.2)
    # mass of the body minus six chamber cavities (8 x 2 x 1 cells each at r = 1)
    cell = 0.025 * 0.015 * (0.08 / 6)
    vol = 1.2 * 0.06 * 0.08 - 6 * 16 * cell
    assert eel.fem.mass.sum() == pytest.approx(1100.0 * vol, rel=1e-12)
    assert eel.fem.volume.sum() == pytest.approx(vol, rel=1e-12)
    # clamped head: exactly the nodes of the face x = 0
    clamped = ~eel.free.reshape(-1, 3)[:, 0]
    np.testing.assert_array_equal(clamped, X[:, 0] == 0.0)


def test_chamber_loads_are_balanced_and_bend_in_xz(eel: EelModel) -> None:
    B = eel.B.toarray()
    assert B.shape == (eel.n_dof, 6)
    X = eel.mesh.nodes
    for c in range(6):
        f = B[:, c].reshape(-1, 3)
        np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-15)       # no net force
        np.testing.assert_allclose(np.cross(X, f).sum(axis=0), 0.0, atol=1e-15)  # nor moment
        # end caps push apart along x, above (even c) or below (odd c) the neutral plane
        loaded = np.abs(f[:, 0]) > 0
        assert np.all(np.sign(X[loaded, 2]) == (1 if c % 2 == 0 else -1))
        assert np.abs(f[:, 1:]).max() == 0 and np.abs(f[:, 0]).sum() > 1e-4
    # static response of the linearization: top chamber bends the tail down (-z)
    lin = eel.linearization()
    free = lin.free
    for c, sign in ((0, -1), (1, 1)):
        q = np.zeros(eel.n_dof)
        q[free] = spla.spsolve(lin.K[free][:, free].tocsc(), 1e4 * lin.B[free, c])
        y = lin.E @ q
        assert np.sign(y[-1]) == sign and 1e-3 < abs(y[-1]) < 0.1       # 10 kPa: mm range
        assert abs(y[20]) == 0.0                                          # head point clamped


def test_centerline_at_rest_and_output_map(eel: EelModel) -> None:
    lin = eel.linearization()
    np.testing.assert_allclose(lin.y_ref[:20], np.linspace(0, 1.2, 20), atol=1e-15)
    np.testing.assert_allclose(lin.y_ref[20:], 0.0, atol=1e-15)
    W = eel.centerline_map
    np.testing.assert_allclose(np.asarray(W.sum(axis=1)).ravel(), 1.0, rtol=1e-14)
    # a rigid translation moves every centerline point by the same amount
    shift = np.array([0.01, -0.02, 0.03])
    np.testing.assert_allclose(W @ (eel.mesh.nodes + shift) - W @ eel.mesh.nodes,
                               np.broadcast_to(shift, (20, 3)), atol=1e-15)


def test_linearization_matrices(eel: EelModel) -> None:
    lin = eel.linearization()
    n = eel.n_dof
    for A in (lin.M, lin.C, lin.K):
        assert A.shape == (n, n)
        assert abs(A - A.T).max() < 1e-9 * abs(A).max()
    assert lin.E.shape == (40, n) and lin.B.shape == (n, 6)
    fixed = ~lin.free
    assert abs(lin.K[fixed]).max() == 0 and not lin.B[fixed].any()
    # positive definite on the free DOFs: smallest eigenvalue of K_ff > 0
    Kf = lin.K[lin.free][:, lin.free]
    lam = spla.eigsh(Kf.tocsc(), k=1, sigma=0, which='LM', return_eigenvectors=False)
    assert lam[0] > 0


def test_rest_stays_at_rest_and_head_stays_still(eel: EelModel) -> None:
    r = eel.simulate(np.zeros((6, 20)), 20)
    np.testing.assert_allclose(r.centerline, r.centerline[:, :, :1].repeat(20, axis=2),
                               atol=1e-14)
    U = random_pressures(60, 1e-3, seed=3, episode=2, amplitude=30e3)
    r = eel.simulate(U, 60)
    assert np.all(r.centerline[0, :, :] == r.centerline[0, :, :1])    # clamped head point
    assert np.abs(r.centerline[-1, 2, :]).max() > 10 * np.abs(r.centerline[1, 2, :]).max()
    assert r.t.shape == (60,) and r.pressures.shape == (6, 60)
    assert r.centerline.shape == (20, 3, 60)
    np.testing.assert_array_equal(r.t, np.arange(60) * 1e-3)


def test_linear_mode_is_the_exported_linearization(eel: EelModel) -> None:
    """simulate(linear=True) == backward Euler on (M, C, K, B, E) from linearization()."""
    k = 60
    U = random_pressures(k, 1e-3, seed=0, episode=1, amplitude=20e3)
    r = eel.simulate(U, k, linear=True)
    lin = eel.linearization()
    f = lin.free
    h = 1e-3
    M, C, K = (A[f][:, f].tocsc() for A in (lin.M, lin.C, lin.K))
    solve = spla.factorized((M + h * C + h * h * K).tocsc())
    q = np.zeros(f.sum())
    v = np.zeros(f.sum())
    Y = np.empty((40, k))
    for j in range(k):
        qq = np.zeros(eel.n_dof)
        qq[f] = q
        Y[:, j] = lin.E @ qq + lin.y_ref
        v = solve(M @ v + h * (-(K @ q) + lin.B[f] @ U[:, j]))
        q = q + h * v
    np.testing.assert_allclose(r.outputs(), Y, rtol=0, atol=1e-12)


def test_small_pressures_are_linear_large_ones_are_not(eel: EelModel) -> None:
    k = 150
    U = np.zeros((6, k))
    U[0::2] = np.linspace(0, 1, k)
    U[1::2] = -U[0::2]
    yl = eel.simulate(U, k, linear=True).outputs()
    dl = yl - yl[:, :1]                  # linear response to 1 Pa (deviation from rest)

    def deviation(amp: float) -> float:
        yn = eel.simulate(amp * U, k).outputs()
        return float(np.linalg.norm(yn - yn[:, :1] - amp * dl) / np.linalg.norm(amp * dl))

    small, large = deviation(100.0), deviation(60e3)
    assert small < 1e-3                  # the FOM equals its linearization at 100 Pa
    assert large > 10 * small            # geometric nonlinearity at 60 kPa
    assert large > 0.01


def test_corotated_and_rest_tangents_agree(eel: EelModel) -> None:
    U = random_pressures(60, 1e-3, seed=1, episode=4, amplitude=30e3)
    a = eel.simulate(U, 60, jacobian='rest')
    b = eel.simulate(U, 60, jacobian='corotated', cg_rtol=1e-10)
    assert b.info['cg_worst_residual'] <= 1e-10
    dev = np.abs(b.centerline - b.centerline[:, :, :1]).max()
    assert dev > 1e-5
    # both are first-order consistent discretizations of the same ODE
    assert np.abs(a.centerline - b.centerline).max() < 0.05 * dev


def test_callback_streams_the_stored_states(eel: EelModel) -> None:
    seen = []

    def cb(j, t, u, cl, x):
        seen.append((j, t, u.copy(), cl.copy(), x.copy()))

    U = random_pressures(20, 1e-3, seed=0, episode=1)
    r = eel.simulate(U, 20, store_states=True, callback=cb)
    assert [s[0] for s in seen] == list(range(20))
    for j, t, u, cl, x in seen:
        assert t == r.t[j]
        np.testing.assert_array_equal(u, r.pressures[:, j])
        np.testing.assert_array_equal(cl, r.centerline[:, :, j])
        np.testing.assert_array_equal(x, r.states[:, :, j])
    ep = r.to_episode('ep1')
    assert ep.Y.shape == (40, 20) and ep.Q.shape == (eel.n_dof, 20)
    np.testing.assert_array_equal(ep.Y[20:], r.centerline[:, 2, :])


def test_episodes_are_reproducible_and_distinct() -> None:
    a = random_pressures(2000, 1e-3, seed=0, episode=1)
    np.testing.assert_array_equal(a, random_pressures(2000, 1e-3, seed=0, episode=1))
    b = random_pressures(2000, 1e-3, seed=0, episode=2)
    assert not np.allclose(a, b)
    np.testing.assert_allclose(a[0::2], -a[1::2], rtol=0, atol=0)      # antagonistic pairs
    assert np.abs(a).max() <= 50e3 and a[:, 0].max() < 50e3 * 0.1     # starts near zero
    c = random_pressures(500, 1e-3, seed=0, episode=1, antagonistic=False, amplitude=1e4)
    assert c.min() >= 0 and c.max() <= 1e4


def test_simulate_episode_reports_provenance(eel: EelModel) -> None:
    r = simulate_episode(eel, 3, seed=7, n_steps=10)
    assert r.info['episode'] == 3 and r.info['seed'] == 7 and r.info['n_dof'] == 5145


def test_bad_arguments_are_refused(eel: EelModel) -> None:
    with pytest.raises(DimensionError):
        eel.simulate(np.zeros((5, 10)), 10)
    with pytest.raises(DimensionError):
        eel.simulate(np.full((6, 10), np.nan), 10)
    with pytest.raises(ConfigError):
        eel.simulate(np.zeros((6, 10)), 10, jacobian='newton')
    with pytest.raises(ConfigError):
        EelModel(resolution=0)
    with pytest.raises(ConfigError):
        EelModel(colour='red')


def test_resolution_two_is_finer(eel: EelModel) -> None:
    fine = EelModel(resolution=2)
    assert fine.n_dof == 33237
    assert sp.issparse(fine.B) and fine.B.shape == (fine.n_dof, 6)


def test_lockstep_episodes_equal_their_own_simulations(eel: EelModel) -> None:
    Us = [random_pressures(40, 1e-3, seed=0, episode=e) for e in (1, 2, 3)]
    seen: list[tuple[int, int]] = []

    def cb(e: int):
        return lambda j, t, u, cl, x: seen.append((j, e))

    many = eel.simulate_lockstep(Us, 40, callbacks=[cb(0), cb(1), cb(2)])
    assert seen[:6] == [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2)]
    for U, r in zip(Us, many):
        one = eel.simulate(U, 40)
        assert np.abs(r.centerline - one.centerline).max() <= 1e-12
        assert np.abs(one.centerline[-1, 2] - one.centerline[-1, 2, 0]).max() > 1e-4
        assert r.info['lockstep'] == 3 and r.info['solver'] == one.info['solver']
    with pytest.raises(DimensionError):
        eel.simulate_lockstep([Us[0][:5]], 40)
    with pytest.raises(DimensionError):
        eel.simulate_lockstep(Us, 40, callbacks=[None])
