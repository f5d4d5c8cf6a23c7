"""DMDc against known truth: a random discrete LTI system observed through full states."""

from __future__ import annotations

from _systems import spring_chain_episodes
import numpy as np
import pytest

from soft_rom.data import Episode
from soft_rom.errors import ConfigError, DimensionError, NotFittedError
from soft_rom.evaluation import predict
from soft_rom.learners.dmdc import DMDc
from soft_rom.metrics import relative_deviation_error
from soft_rom.models import load_model


def _system(n=8, m=3, p=5, seed=0, rho=0.9):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, n))
    A *= rho / np.max(np.abs(np.linalg.eigvals(A)))
    return A, rng.standard_normal((n, m)), rng.standard_normal((p, n)), rng


def _episode(A, B, E, U, x0, q_ref, y_ref, name='ep', dt=1e-3):
    n, k = A.shape[0], U.shape[1]
    X = np.empty((n, k))
    x = x0
    for j in range(k):
        X[:, j] = x
        x = A @ x + B @ U[:, j]
    return Episode(t=np.arange(k) * dt, U=U, Y=E @ X + y_ref[:, None],
                   Q=X + q_ref[:, None], name=name)


@pytest.fixture()
def lti():
    A, B, E, rng = _system()
    q_ref, y_ref = rng.standard_normal(8), rng.standard_normal(5)
    U = rng.standard_normal((3, 200))
    ep = _episode(A, B, E, U, np.zeros(8), q_ref, y_ref)
    return A, B, E, q_ref, y_ref, ep, rng


def test_full_rank_recovers_operators_and_trajectories(lti):
    A, B, E, q_ref, y_ref, ep, rng = lti
    dmd = DMDc(r=8, p=11).fit(ep, q_ref=q_ref, y_ref=y_ref)
    model, V = dmd.model_, dmd.basis_
    # In the original coordinates (q = V x): V Ã Vᵀ = A, V B̃ = B, Ẽ Vᵀ = E.
    np.testing.assert_allclose(V @ model.A @ V.T, A, atol=1e-10 * np.abs(A).max())
    np.testing.assert_allclose(V @ model.B, B, atol=1e-10 * np.abs(B).max())
    np.testing.assert_allclose(model.C @ V.T, E, atol=1e-10 * np.abs(E).max())
    np.testing.assert_allclose(np.sort_complex(np.linalg.eigvals(model.A)),
                               np.sort_complex(np.linalg.eigvals(A)), atol=1e-10)
    # Trajectories on new inputs, from a new initial state.
    U = rng.standard_normal((3, 300))
    x0 = rng.standard_normal(8)
    test = _episode(A, B, E, U, x0, q_ref, y_ref)
    Y_hat = model.simulate(U, x0=dmd.reduce(test.Q[:, :1])[:, 0])
    assert np.max(np.abs(Y_hat - test.Y)) <= 1e-10 * np.max(np.abs(test.Y))
    assert model.method == 'dmdc' and np.all(model.D == 0)
    assert model.metadata['p'] == 11 and model.metadata['r'] == 8


def test_paper_output_fit_equals_reduced_fit_at_full_rank(lti):
    A, B, E, q_ref, y_ref, ep, _ = lti
    a = DMDc(r=8, output_fit='paper').fit(ep, q_ref, y_ref).model_
    b = DMDc(r=8).fit(ep, q_ref, y_ref).model_
    np.testing.assert_allclose(a.C, b.C, atol=1e-10 * np.abs(b.C).max())


def test_pairs_never_straddle_episodes():
    A, B, E, rng = _system(seed=3)
    q_ref, y_ref = np.zeros(8), np.zeros(5)
    ep1 = _episode(A, B, E, rng.standard_normal((3, 80)), rng.standard_normal(8) * 5,
                   q_ref, y_ref, 'a')
    ep2 = _episode(A, B, E, rng.standard_normal((3, 80)), rng.standard_normal(8) * 5,
                   q_ref, y_ref, 'b')
    dmd = DMDc(r=8, p=11).fit([ep1, ep2], q_ref, y_ref)
    V = dmd.basis_
    np.testing.assert_allclose(V @ dmd.model_.A @ V.T, A, atol=1e-10 * np.abs(A).max())
    assert dmd.n_pairs_ == 2 * 79
    # Gluing the two records into one episode creates a false pair at the seam: wrong A.
    glued = Episode(t=np.arange(160) * 1e-3, U=np.hstack([ep1.U, ep2.U]),
                    Y=np.hstack([ep1.Y, ep2.Y]), Q=np.hstack([ep1.Q, ep2.Q]))
    bad = DMDc(r=8, p=11).fit(glued, q_ref, y_ref)
    Vb = bad.basis_
    assert np.max(np.abs(Vb @ bad.model_.A @ Vb.T - A)) > 1e-3


def test_model_for_matches_fresh_fit_and_roundtrips(lti, tmp_path):
    *_, q_ref, y_ref, ep, _ = lti
    big = DMDc(r=8).fit(ep, q_ref, y_ref)
    for r in (3, 5):
        fresh = DMDc(r=r).fit(ep, q_ref, y_ref).model_
        again = big.model_for(r)
        np.testing.assert_allclose(again.A, fresh.A, atol=1e-12)
        np.testing.assert_allclose(again.B, fresh.B, atol=1e-12)
        np.testing.assert_allclose(again.C, fresh.C, atol=1e-12)
    path = big.model_.save(tmp_path / 'd.npz')
    loaded = load_model(path)
    np.testing.assert_array_equal(loaded.A, big.model_.A)
    assert loaded.metadata['singular_values_qp'][0] == big.singular_values_qp_[0]


def test_energy_rule_and_truncated_fit_is_accurate():
    # A system whose states live in a 4-dim subspace of R^30 (slow, well-excited modes).
    rng = np.random.default_rng(5)
    Vtrue, _ = np.linalg.qr(rng.standard_normal((30, 4)))
    Ar = np.diag([0.99, 0.97, 0.95, 0.9])
    Br = rng.standard_normal((4, 2))
    U = rng.standard_normal((2, 400))
    x, X = np.zeros(4), np.empty((4, 400))
    for j in range(400):
        X[:, j] = x
        x = Ar @ x + Br @ U[:, j]
    Q = Vtrue @ X
    Y = rng.standard_normal((3, 30)) @ Q
    ep = Episode(t=np.arange(400) * 1e-3, U=U, Y=Y, Q=Q)
    dmd = DMDc(energy=0.999999).fit(ep, np.zeros(30), np.zeros(3))
    assert dmd.model_.r == 4
    Y_hat = dmd.model_.simulate(U)
    assert np.linalg.norm(Y_hat - Y) <= 1e-9 * np.linalg.norm(Y)


def test_rank_deficient_inputs_do_not_blow_up():
    # Antagonistic chambers: u2 = -u1, so U has rank 1 and Ω has a zero singular value.
    A, B, E, rng = _system(n=6, m=2, seed=7)
    u = rng.standard_normal(300)
    U = np.vstack([u, -u]) * 2e4
    ep = _episode(A, B, E, U, np.zeros(6), np.zeros(6), np.zeros(5))
    dmd = DMDc(r=6).fit(ep)
    assert dmd.model_.metadata['p'] == 7 < dmd.model_.metadata['p_requested'] == 8
    assert np.all(np.isfinite(dmd.model_.B))
    Y_hat = dmd.model_.simulate(U)
    assert np.linalg.norm(Y_hat - ep.Y) <= 1e-9 * np.linalg.norm(ep.Y)


def test_pod_coordinates_give_the_snapshots_model():
    # DMDc works in any orthonormal basis: on the coordinates of the snapshots in the full
    # POD basis (as a streamed reducer hands them) it learns the model of the snapshots.
    from soft_rom.reduce import InMemoryPOD, training_data
    A, B, E, rng = _system(n=10, m=2, p=4, seed=11, rho=0.95)
    U = rng.standard_normal((2, 300))
    ep = _episode(A, B, E, U, np.zeros(10), np.zeros(10), np.zeros(4))
    ref = DMDc(r=6).fit(ep).model_
    red = InMemoryPOD().reduce(training_data(ep), basis='pod', r=10)
    assert red.basis == 'pod' and red.n_coordinates == 10
    model = DMDc(r=6).fit(red).model_
    # Same ROM up to the sign of the basis vectors: compare Markov parameters C A^k B.
    for k in range(10):
        mk_ref = ref.C @ np.linalg.matrix_power(ref.A, k) @ ref.B
        mk = model.C @ np.linalg.matrix_power(model.A, k) @ model.B
        np.testing.assert_allclose(mk, mk_ref, rtol=0, atol=1e-10 * np.abs(mk_ref).max())


def test_errors():
    with pytest.raises(NotFittedError):
        DMDc().model_for(2)
    ep = Episode(t=[0.0, 1.0, 2.0], U=np.ones((1, 3)), Y=np.ones((1, 3)))
    with pytest.raises(DimensionError, match='no full states Q: DMDc needs them'):
        DMDc().fit(ep)
    A, B, E, rng = _system()
    good = _episode(A, B, E, rng.standard_normal((3, 50)), np.zeros(8), np.zeros(8),
                    np.zeros(5))
    with pytest.raises(ConfigError, match='r must be between'):
        DMDc(r=50).fit(good)
    with pytest.raises(ConfigError, match='output_fit'):
        DMDc(output_fit='bogus').fit(good)
    other = Episode(t=good.t, U=good.U[:2], Y=good.Y, Q=good.Q)
    with pytest.raises(DimensionError, match='first episode'):
        DMDc().fit([good, other])


def test_clip_spectral_radius_moves_only_the_outside_eigenvalues():
    from soft_rom.learners.dmdc import clip_spectral_radius
    rng = np.random.default_rng(3)
    lam = np.array([1.2, 0.5, -0.3])
    pair = 1.05 * np.array([[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]])
    T = np.zeros((5, 5))
    T[:3, :3] = np.diag(lam)
    T[3:, 3:] = pair
    S = rng.standard_normal((5, 5))
    A = S @ T @ np.linalg.inv(S)
    Ac, moved = clip_spectral_radius(A, 1.0)
    ev = np.sort_complex(np.linalg.eigvals(Ac))
    assert moved == 3 and np.isrealobj(Ac)
    expect = np.sort_complex(np.array([1.0, 0.5, -0.3, np.exp(0.3j), np.exp(-0.3j)]))
    np.testing.assert_allclose(ev, expect, atol=1e-9)
    same, none = clip_spectral_radius(0.5 * np.eye(3))
    assert none == 0 and np.array_equal(same, 0.5 * np.eye(3))


def test_stable_variant_on_a_linear_chain():
    # Positions-only DMDc of a second-order chain is marginally unstable at larger r; the
    # lagged variant is the exact ARX form of the sampled chain: exact at full rank, stable.
    eps = spring_chain_episodes(n_dof=12, m=2, p=4, k=500, dt=2e-3, seed=0, stiffness=400.0,
                                drive_nodes=(4, 8), input_gain=1e-3, amplitude=30e3, hold=25,
                                q_span=1.0)
    paper = DMDc(r=12).fit(eps[:1])
    stable = DMDc(r=12, variant='stable').fit(eps[:1])
    assert paper.model_.stability_margin() < 0            # the paper's DMDc diverges here
    for r in (4, 8, 12):
        model = stable.model_for(r)
        assert 1.0 - model.stability_margin() <= 1.0
        # The state is [x_k; x_{k-1}; u_{k-1}]: 2 r + m states for a rank-r basis.
        assert model.metadata['variant'] == 'stable' and model.metadata['r'] == r
        assert model.n_states == 2 * r + 2
    Yh = predict(stable.model_, eps[1])
    err = relative_deviation_error(eps[1].Y, Yh, stable.model_.y_ref)
    assert err <= 1e-6
    with pytest.raises(ConfigError, match='variant'):
        DMDc(r=2, variant='lagged').fit(eps[:1])


def _embedded(n=1500, k=700, seed=3):
    """The 8-state system seen through n = 1500 full states (``q = Φ x``, Φ orthonormal)."""
    A, B, E, rng = _system()
    Phi = np.linalg.qr(rng.standard_normal((n, 8)))[0]
    q_ref, y_ref = rng.standard_normal(n), rng.standard_normal(5)
    eps = []
    for i in range(2):
        U = rng.standard_normal((3, k))
        ep = _episode(A, B, E, U, rng.standard_normal(8), np.zeros(8), y_ref, name=f'ep{i}')
        eps.append(Episode(t=ep.t, U=U, Y=ep.Y, Q=Phi @ ep.Q + q_ref[:, None], name=ep.name))
    return A, Phi, q_ref, y_ref, eps


def test_many_states_fit_on_their_range_and_give_the_full_svd_model(monkeypatch):
    """Many states: the SVDs are taken on a basis of the snapshots' range, same model.

    n = 1500 states and 1,400 snapshots: ``snapshot_range`` finds the range, and the model
    is the one of the SVDs of the full snapshots.
    """
    import soft_rom.learners.dmdc as dmdc_module
    A, Phi, q_ref, y_ref, eps = _embedded()
    calls = []
    real = dmdc_module.snapshot_range

    def spy(arrays, tol):
        calls.append(real(arrays, tol))
        return calls[-1]

    monkeypatch.setattr(dmdc_module, 'snapshot_range', spy)
    fast = DMDc(r=8).fit(eps, q_ref=q_ref, y_ref=y_ref)
    assert calls and calls[0] is not None and calls[0].shape == (1500, 512)
    monkeypatch.setattr(dmdc_module, 'snapshot_range', lambda arrays, tol: None)
    full = DMDc(r=8).fit(eps, q_ref=q_ref, y_ref=y_ref)
    for dmd in (fast, full):          # known truth: Φᵀ V Ã Vᵀ Φ = A
        T = Phi.T @ dmd.basis_
        np.testing.assert_allclose(T @ dmd.model_.A @ T.T, A, atol=1e-10)
    U = np.random.default_rng(9).standard_normal((3, 500))
    np.testing.assert_allclose(fast.model_.simulate(U), full.model_.simulate(U), rtol=0,
                               atol=1e-10 * np.abs(full.model_.simulate(U)).max())
    assert fast.state_scale_ == pytest.approx(full.state_scale_, rel=1e-13)
    np.testing.assert_allclose(fast.singular_values_qp_[:8], full.singular_values_qp_[:8],
                               rtol=1e-12)


def test_snapshot_range_reaches_its_tolerance_or_declines():
    from soft_rom.basis import snapshot_range
    rng = np.random.default_rng(4)
    # a decaying spectrum (singular values 10^(-j/20)) and noise at 1e-14 of the largest
    n, K = 1200, 1100
    Ul, Vr = (np.linalg.qr(rng.standard_normal((d, 600)))[0] for d in (n, K))
    A = (Ul * 10.0 ** (-np.arange(600) / 20.0)) @ Vr.T + 1e-16 * rng.standard_normal((n, K))
    parts = [A[:, :500], A[:, 500:]]
    W = snapshot_range(parts, 1e-12)
    assert W is not None and W.shape[0] == n and W.shape[1] < 600
    np.testing.assert_allclose(W.T @ W, np.eye(W.shape[1]), atol=1e-12)
    assert np.linalg.norm(A - W @ (W.T @ A)) <= 1e-12 * np.linalg.norm(A)
    np.testing.assert_array_equal(W, snapshot_range(parts, 1e-12))       # a fixed seed
    # no decay (white noise), or too few columns to gain: the caller takes the full SVDs
    assert snapshot_range([rng.standard_normal((n, K))], 1e-13) is None
    assert snapshot_range([A[:, :1000]], 1e-12) is None


def test_snapshot_range_gives_up_early_on_noise(monkeypatch):
    """A decaying spectrum under noise at 1e-8: no range to 1e-13, said after 2 tries."""
    from soft_rom.basis import snapshot_range
    rng = np.random.default_rng(8)
    n = K = 2600                                           # tries at 512, 768, 1152 allowed
    Ul, Vr = (np.linalg.qr(rng.standard_normal((n, 300)))[0] for _ in range(2))
    A = (Ul * 10.0 ** (-np.arange(300) / 20.0)) @ Vr.T + 1e-8 * rng.standard_normal((n, K))
    tries = []
    qr = np.linalg.qr
    monkeypatch.setattr(np.linalg, 'qr', lambda a, *args, **kw: tries.append(a.shape[1])
                        or qr(a, *args, **kw))
    assert snapshot_range([A], 1e-13) is None
    assert tries == [512, 768]
