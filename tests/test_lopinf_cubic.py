"""Cubic (quartic-potential) LOpInf: known truth, integrator, files, predictor."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from soft_rom.data import Episode
from soft_rom.errors import ConfigError, DimensionError, ModelFileError, SolverError
from soft_rom.learners.lopinf import LOpInf
from soft_rom.learners.lopinf.cubic import fit_cubic
from soft_rom.metrics import relative_error
from soft_rom.models import CubicSecondOrderModel, load_model
from soft_rom.models.tensors import (
    quartic_lower_bound,
    symmetric_entries,
    symmetric_from_entries,
    symmetric_index,
    symmetrize,
)

DT = 1e-3


def duffing_chain(n: int, m: int = 2, p: int = 3, seed: int = 0) -> CubicSecondOrderModel:
    """Fixed-free chain of Duffing springs: V_e = k/2 d² + g/6 d³ + h/24 d⁴, d = a_eᵀ q."""
    rng = np.random.default_rng(seed)
    eye = np.eye(n)
    rows = [eye[0]] + [eye[i] - eye[i - 1] for i in range(1, n)]
    k = rng.uniform(50, 150, n)
    g = rng.uniform(-300, 300, n)
    h = rng.uniform(500, 2000, n)
    K = sum(ki * np.outer(a, a) for ki, a in zip(k, rows))
    G = sum(gi * np.einsum('i,j,k->ijk', a, a, a) for gi, a in zip(g, rows))
    H = sum(hi * np.einsum('i,j,k,l->ijkl', a, a, a, a) for hi, a in zip(h, rows))
    C = 0.5 * eye + 2e-3 * K
    return CubicSecondOrderModel(K, C, G, H, rng.standard_normal((n, m)),
                                 rng.standard_normal((p, n)), dt=DT)


def exact_data(model: CubicSecondOrderModel, T: float = 3.0, seed: int = 1):
    """A trajectory (fine solve_ivp) with inputs held 0.1 s, and its exact accelerations."""
    n, m = model.r, model.n_inputs
    rng = np.random.default_rng(seed)
    levels = 20.0 * rng.standard_normal((m, int(T / 0.1) + 1))
    t = np.arange(0.0, T, DT)

    def u(s: float) -> np.ndarray:
        return levels[:, int(s / 0.1)]

    def rhs(s: float, x: np.ndarray) -> np.ndarray:
        q, v = x[:n], x[n:]
        return np.concatenate([v, model.B @ u(s) - model.C @ v - model.force(q)])

    sol = solve_ivp(rhs, (0.0, T), np.zeros(2 * n), t_eval=t, rtol=1e-10, atol=1e-12,
                    max_step=DT)
    X = sol.y
    U = np.column_stack([u(s) for s in t])
    Qdd = np.column_stack([rhs(s, x)[n:] for s, x in zip(t, X.T)])
    return X[:n], X[n:], Qdd, U


def test_symmetric_tensor_helpers() -> None:
    rng = np.random.default_rng(0)
    T = symmetrize(rng.standard_normal((3, 3, 3, 3)))
    assert len(symmetric_index(3, 4)) == 15 and len(symmetric_index(12, 4)) == 1365
    assert len(symmetric_index(12, 3)) == 364
    np.testing.assert_allclose(symmetric_from_entries(symmetric_entries(T), 3, 4), T,
                               atol=1e-15)
    assert np.allclose(T, np.transpose(T, (2, 0, 3, 1)))


@pytest.mark.parametrize('n', [3, 4])
def test_known_truth_recovered(n: int) -> None:
    truth = duffing_chain(n)
    Q, Qd, Qdd, U = exact_data(truth)
    sol = fit_cubic(Q, Qd, Qdd, U, reg=0.0)
    assert sol.info['method'].startswith('least-squares')
    for name in ('K', 'C', 'G', 'H', 'B'):
        got, want = getattr(sol, name), getattr(truth, name)
        assert np.linalg.norm(got - want) <= 1e-8 * np.linalg.norm(want), name
    # The Duffing quartic is rank deficient as a Gram matrix: only the SOS search certifies it.
    t, how = quartic_lower_bound(sol.H, target=1.0)
    assert how == 'sos' and t > 1.0


def unstable_quartic_data(r: int, k: int, q_scale: float, *, seed: int):
    """Random states and exact accelerations of the Duffing chain with its quartic negated.

    Returns ``Q, Q̇, Q̈, U`` (``k`` samples), the chain and the generator (drawn on after).
    """
    base = duffing_chain(r)
    bad = CubicSecondOrderModel(base.K, base.C, base.G, -base.H, base.B, base.E, dt=DT)
    rng = np.random.default_rng(seed)
    Q = q_scale * rng.standard_normal((r, k))
    Qd = rng.standard_normal((r, k))
    U = rng.standard_normal((2, k))
    Qdd = np.column_stack([bad.B @ u - bad.C @ v - bad.force(q)
                           for q, v, u in zip(Q.T, Qd.T, U.T)])
    return Q, Qd, Qdd, U, base, rng


def test_constraints_enforced_when_data_violate_them() -> None:
    """Data of an unstable quartic (negative H): the fit keeps K, C SPD and H positive."""
    Q, Qd, Qdd, U, base, rng = unstable_quartic_data(3, 400, 0.3, seed=3)
    sol = fit_cubic(Q, Qd, Qdd, U, reg=1e-6)
    assert sol.info['method'].startswith('conic')
    assert np.linalg.eigvalsh(sol.K)[0] >= 0.999e-6 and np.linalg.eigvalsh(sol.C)[0] >= 0.999e-6
    t, _how = quartic_lower_bound(sol.H, target=sol.info['quartic_target'])
    assert t >= 0.99 * sol.info['quartic_target'] > 0
    # the potential grows: V(s d) -> +inf along random unit directions, beyond the radius
    # where t |q|^4 / 24 dominates |G| |q|^3 / 6
    model = CubicSecondOrderModel(sol.K, sol.C, sol.G, sol.H, sol.B, base.E, dt=DT)
    radius = 8.0 * np.linalg.norm(sol.G) / t
    for d in rng.standard_normal((20, 3)):
        d /= np.linalg.norm(d)
        assert model.potential(2 * radius * d) > model.potential(radius * d) > 0


def test_conic_solve_retried_with_other_settings_then_one_line(monkeypatch) -> None:
    """A numerical error of Clarabel is retried without equilibration, then one line.

    Clarabel stops on a numerical error on ill-conditioned data, depending on round-off; the
    retried result is certified like the first. When every setting fails, one line says so
    and what to try.
    """
    import cvxpy as cp
    Q, Qd, Qdd, U, _base, _rng = unstable_quartic_data(3, 400, 0.3, seed=3)
    first = fit_cubic(Q, Qd, Qdd, U, reg=1e-6)
    assert first.info['conic_settings'] == 0
    solve = cp.Problem.solve
    calls = []

    def failing(self, *args, **kwargs):
        if 'iterative_refinement_reltol' not in kwargs:      # not the fit's conic problem
            return solve(self, *args, **kwargs)
        calls.append(kwargs.get('equilibrate_enable', True))
        if kwargs.get('equilibrate_enable', True):
            raise cp.error.SolverError("Solver 'CLARABEL' failed. Try another solver, or "
                                       'solve with verbose=True for more information.')
        return solve(self, *args, **kwargs)

    monkeypatch.setattr(cp.Problem, 'solve', failing)
    sol = fit_cubic(Q, Qd, Qdd, U, reg=1e-6)
    assert calls == [True, False] and sol.info['conic_settings'] == 1
    assert np.linalg.eigvalsh(sol.C)[0] >= 0.999e-6 and sol.info['quartic_lower_bound'] > 0
    # the same optimum (H itself sits on the quartic floor here, poorly determined)
    assert sol.info['objective'] == pytest.approx(first.info['objective'], rel=1e-7)

    def always(self, *args, **kwargs):
        if 'iterative_refinement_reltol' not in kwargs:
            return solve(self, *args, **kwargs)
        raise cp.error.SolverError("Solver 'CLARABEL' failed. Try another solver.")

    monkeypatch.setattr(cp.Problem, 'solve', always)
    with pytest.raises(SolverError) as err:
        fit_cubic(Q, Qd, Qdd, U, reg=1e-6)
    msg = str(err.value)
    assert '\n' not in msg and 'numerical error' in msg and '--cubic-reg' in msg
    assert 'verbose=True' not in msg


def test_energy_never_increases_without_input() -> None:
    model = duffing_chain(4)
    x0 = np.concatenate([0.8 * np.ones(4), -2.0 * np.ones(4)])
    _Y, X = model.simulate(np.zeros((2, 3000)), x0, return_states=True)
    E = np.array([model.energy(x) for x in X.T])
    assert np.all(np.diff(E) <= 1e-12 * E[0])
    assert E[-1] < 0.5 * E[0]
    # undamped: the discrete energy is conserved to round-off and Newton tolerance
    free = CubicSecondOrderModel(model.K, np.zeros((4, 4)), model.G, model.H, model.B,
                                 model.E, dt=DT)
    _Y, X = free.simulate(np.zeros((2, 2000)), x0, return_states=True)
    E = np.array([free.energy(x) for x in X.T])
    assert np.max(np.abs(E - E[0])) <= 1e-9 * E[0]


def test_integrator_second_order_against_solve_ivp() -> None:
    model = duffing_chain(4)
    x0 = np.concatenate([0.8 * np.ones(4), np.zeros(4)])
    u0 = np.array([10.0, -5.0])
    T = 0.2

    def rhs(_t: float, x: np.ndarray) -> np.ndarray:
        return np.concatenate([x[4:], model.B @ u0 - model.C @ x[4:] - model.force(x[:4])])

    ref = solve_ivp(rhs, (0, T), x0, method='DOP853', rtol=1e-12, atol=1e-13).y[:, -1]
    errs = []
    for h in (4e-3, 2e-3, 1e-3):
        k = int(round(T / h))
        _Y, X = model.simulate(np.tile(u0[:, None], (1, k + 1)), x0, return_states=True, dt=h)
        errs.append(np.linalg.norm(X[:, -1] - ref) / np.linalg.norm(ref))
    orders = np.log2(np.array(errs[:-1]) / np.array(errs[1:]))
    assert np.all(np.abs(orders - 2.0) < 0.1), orders
    assert errs[-1] < 1e-3


def test_exact_for_the_linear_part() -> None:
    model = duffing_chain(4)
    zero = CubicSecondOrderModel(model.K, model.C, 0 * model.G, 0 * model.H, model.B,
                                 model.E, dt=DT)
    U = np.random.default_rng(0).standard_normal((2, 500))
    x0 = np.linspace(-1, 1, 8)
    np.testing.assert_allclose(zero.simulate(U, x0), model.linear_part().simulate(U, x0),
                               rtol=0, atol=1e-13)


def test_output_takes_k_states_at_once_as_the_linear_models_do() -> None:
    """LinearROM.output took x (n, k); the cubic model's refused it ('x must have shape')."""
    model = duffing_chain(3)
    X = np.random.default_rng(3).normal(size=(6, 4))
    Y = model.output(X)
    assert Y.shape == (3, 4)
    for j in range(4):
        np.testing.assert_allclose(Y[:, j], model.output(X[:, j]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(Y, model.linear_part().output(X), rtol=0, atol=1e-12)
    np.testing.assert_allclose(model.output(X, np.zeros((2, 4))), Y, rtol=0, atol=0)
    with pytest.raises(DimensionError, match='give both as vectors'):
        model.output(X, np.zeros(2))          # mixed shapes, refused as LinearROM does


def test_step_and_output_name_a_wrong_state_or_input() -> None:
    model = duffing_chain(3)                 # x = [q; q'] has 6 entries, u has 2
    x, u = np.zeros(6), np.zeros(2)
    with pytest.raises(DimensionError, match=r'x must have shape \(6,\)'):
        model.output(np.zeros(3))            # q alone used to be taken silently
    with pytest.raises(DimensionError, match=r'u must have shape \(2,\)'):
        model.step(x, np.zeros(3))
    with pytest.raises(DimensionError, match=r'x must have shape \(6,\)'):
        model.step_jacobian(np.zeros((6, 2)), u)


def test_step_jacobian_matches_finite_differences() -> None:
    model = duffing_chain(3)
    x = np.array([0.3, -0.2, 0.5, 1.0, 0.0, -1.0])
    u = np.array([3.0, 1.0])
    x1, A, Bu = model.step_jacobian(x, u)
    np.testing.assert_allclose(x1, model.step(x, u), atol=1e-14)
    d = 1e-6
    An = np.column_stack([(model.step(x + d * e, u) - model.step(x - d * e, u)) / (2 * d)
                          for e in np.eye(6)])
    Bn = np.column_stack([(model.step(x, u + d * e) - model.step(x, u - d * e)) / (2 * d)
                          for e in np.eye(2)])
    np.testing.assert_allclose(A, An, atol=1e-7)
    np.testing.assert_allclose(Bu, Bn, atol=1e-7)


def test_learner_and_file_round_trip(tmp_path) -> None:
    """LOpInf(forces='cubic') through POD on the physical chain, then save and load."""
    truth = duffing_chain(4)
    Q, Qd, _Qdd, U = exact_data(truth, T=4.0)
    q_ref = np.linspace(0.0, 0.5, 4)
    Y = truth.E @ Q + truth.y_ref[:, None]
    half = Q.shape[1] // 2
    eps = [Episode(t=np.arange(half) * DT, U=U[:, s], Y=Y[:, s], Q=Q[:, s] + q_ref[:, None],
                   name=f'ep{i}') for i, s in enumerate((slice(0, half), slice(half, 2 * half)))]
    eps[1] = Episode(t=eps[1].t, U=eps[1].U, Y=eps[1].Y, Q=eps[1].Q, name='ep1b')
    lin = LOpInf(r=4).fit(eps, q_ref=q_ref)
    cub = LOpInf(r=4, forces='cubic', cubic_options={'reg': 0.0}).fit(eps, q_ref=q_ref)
    assert isinstance(cub.model_, CubicSecondOrderModel)
    err_lin = relative_error(Y, np.hstack([lin.model_.simulate(e.U) for e in eps[:1]] +
                                          [lin.model_.simulate(e.U) for e in eps[1:]]))
    Yc = cub.model_.simulate(eps[0].U)
    err_cub = relative_error(eps[0].Y, Yc)
    assert err_cub < 0.2 * err_lin
    path = cub.model_.save(tmp_path / 'cubic.npz')
    back = load_model(path)
    assert isinstance(back, CubicSecondOrderModel) and back.trusted
    np.testing.assert_array_equal(back.H, cub.model_.H)
    np.testing.assert_array_equal(back.simulate(eps[0].U), Yc)
    assert back.header()['format_version'] == 2
    assert lin.model_.header()['format_version'] == 1
    with pytest.raises(ConfigError):
        LOpInf(r=4, forces='quadratic').fit(eps, q_ref=q_ref)


def test_file_with_wrong_tensor_shape_refused(tmp_path) -> None:
    model = duffing_chain(3)
    path = model.save(tmp_path / 'm.npz')
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays['H'] = arrays['H'][:, :, :4]
    bad = tmp_path / 'bad.npz'
    np.savez(bad, **arrays)
    with pytest.raises(ModelFileError):
        load_model(bad)
    arrays['H'] = np.zeros((3, 3, 9))
    arrays['G'] = np.random.default_rng(0).standard_normal((3, 3, 3))   # not symmetric
    np.savez(bad, **arrays)
    with pytest.raises(ModelFileError):
        load_model(bad)


def test_predictor_replay_equals_simulate() -> None:
    from soft_rom.predictor import Predictor, PredictorConfig, replay_episode
    model = duffing_chain(3)
    rng = np.random.default_rng(5)
    k = 400
    U = np.repeat(20 * rng.standard_normal((2, k // 20)), 20, axis=1)
    t = np.arange(k) * DT
    ep = Episode(t=t, U=U, Y=model.simulate(U), name='ep')
    pred = Predictor(model, PredictorConfig(kalman=False))
    res = replay_episode(pred, ep, measured=False)
    np.testing.assert_allclose(res.Y, model.simulate(U), rtol=0, atol=1e-12)
    # Kalman (extended) correction from noisy measurements of a perturbed start
    noisy = Episode(t=t, U=U, Y=ep.Y + 1e-3 * rng.standard_normal(ep.Y.shape), name='n')
    pk = Predictor(model, PredictorConfig(kalman=True, measurement_noise=1e-6))
    out = replay_episode(pk, noisy, measured=True)
    assert np.all(np.isfinite(out.Y))
    assert relative_error(ep.Y, out.Y) < 0.05


def test_cli_fit_forces_cubic_then_info(tmp_path, capsys) -> None:
    pytest.importorskip('zarr')
    from soft_rom.cli import main
    from soft_rom.dataset import TrainingSet
    truth = duffing_chain(4)
    Q, _Qd, _Qdd, U = exact_data(truth, T=2.0)
    k = Q.shape[1] // 2
    q_ref = np.linspace(0.0, 0.5, 4)
    eps = [Episode(t=np.arange(k) * DT, U=U[:, s], Y=truth.E @ Q[:, s] + 1.0,
                   Q=Q[:, s] + q_ref[:, None], name=f'ep{i + 1}')
           for i, s in enumerate((slice(0, k), slice(k, 2 * k)))]
    ts = TrainingSet.from_episodes(tmp_path / 'chain.zarr', eps, q_ref=q_ref,
                                   y_ref=eps[0].Y[:, 0]).path
    out = tmp_path / 'models'
    rc = main(['fit', str(ts), '--method', 'lopinf', '--forces', 'cubic', '--r', '3,4',
               '-o', str(out), '--no-progress'])
    assert rc == 0
    assert 'chain_lopinf_cubic_r4.npz' in capsys.readouterr().out
    model = load_model(out / 'chain_lopinf_cubic_r4.npz')
    assert isinstance(model, CubicSecondOrderModel) and model.r == 4
    assert main(['info', str(out / 'chain_lopinf_cubic_r4.npz')]) == 0
    text = capsys.readouterr().out
    assert 'forces: cubic' in text and 'H 35' in text
    # Streamed (the exact Gram POD at this size): the same settings chosen, the same model to
    # the conic solver's tolerance (its constraints are active on these data).
    rc = main(['fit', str(ts), '--forces', 'cubic', '--r', '4', '--streaming', '-o',
               str(tmp_path / 'm2'), '--quiet'])
    assert rc == 0
    streamed = load_model(tmp_path / 'm2' / 'chain_lopinf_cubic_r4.npz')
    sel, streamed_sel = model.metadata['forces_selection'], streamed.metadata['forces_selection']
    for key in ('kept', 'scheme', 'folds', 'forces_auto'):
        assert streamed_sel[key] == sel[key]
    assert (streamed_sel['choice']['reg'], streamed_sel['choice']['eps4']) == \
        (sel['choice']['reg'], sel['choice']['eps4'])
    Y1, Y2 = model.simulate(U[:, :500]), streamed.simulate(U[:, :500])
    assert np.linalg.norm(Y1 - Y2) <= 1e-4 * np.linalg.norm(Y1 - model.y_ref[:, None])


def test_quartic_certificate_known_values() -> None:
    """|q|⁴: canonical Gram bound 2/3, sum-of-squares bound 1 (the exact minimum on |q| = 1)."""
    from soft_rom.learners.lopinf.cubic import isotropic_quartic
    S = isotropic_quartic(3)
    t, how = quartic_lower_bound(S, target=None)
    assert how == 'gram' and abs(t - 2.0 / 3.0) < 1e-12
    t, how = quartic_lower_bound(S, target=0.9)
    assert how == 'sos' and abs(t - 1.0) < 1e-5
    t, _how = quartic_lower_bound(-S, target=0.0)
    assert t < 0


def test_conic_certificate_is_the_gram_matrix_bound() -> None:
    """The compressed conic fit returns H rebuilt from its Gram matrix: the certificate holds.

    Noisy data of a chain with an indefinite quartic (r = 4, so the problem is the compressed
    one with G and B eliminated): H(q, q, q, q) >= certificate |q|^4 on random directions,
    the certificate reaches the floor, and the free unknowns solve their normal equations.
    """
    Q, Qd, Qdd, U, base, rng = unstable_quartic_data(4, 600, 0.4, seed=7)
    Qdd += 1e-3 * rng.standard_normal(Qdd.shape)
    sol = fit_cubic(Q, Qd, Qdd, U, reg=1e-5)
    assert sol.info['method'].startswith('conic')
    cert = sol.info['certificate']
    assert cert >= 0.99 * sol.info['quartic_target'] > 0
    for q in rng.standard_normal((200, 4)):
        h = np.einsum('ijkl,i,j,k,l->', sol.H, q, q, q, q)
        assert h >= (cert - 1e-9 * abs(cert)) * float(q @ q) ** 2
    # optimality in B: the residual is orthogonal to the input rows (B is unconstrained)
    model = CubicSecondOrderModel(sol.K, sol.C, sol.G, sol.H, sol.B, base.E, dt=DT)
    res = Qdd + sol.C @ Qd + np.column_stack([model.force(q) for q in Q.T]) - sol.B @ U
    assert np.max(np.abs(res @ U.T)) <= 1e-6 * np.linalg.norm(res) * np.linalg.norm(U)


def test_step_with_a_non_finite_state_input_or_dt_is_named() -> None:
    """A NaN input, state or dt is refused at once.

    Not after a sub-stepping search that ended in "did not converge (state norm 0)"; the
    discrete linear models name a NaN dt.
    """
    from soft_rom.models import DiscreteModel

    model = duffing_chain(3)
    x, u = model.initial_state(), np.zeros(model.n_inputs)
    for bad_x, bad_u, what in ((x, np.array([np.nan, 0.0]), 'u must be finite'),
                               (np.full(x.shape, np.inf), u, 'x must be finite')):
        with pytest.raises(DimensionError, match=what):
            model.step(bad_x, bad_u)
        with pytest.raises(DimensionError, match=what):
            model.step_jacobian(bad_x, bad_u)
    for dt in (float('nan'), -DT, 0.0):
        with pytest.raises(DimensionError, match='dt must be positive'):
            model.step(x, u, dt=dt)
    assert np.all(np.isfinite(model.step(x, np.ones(model.n_inputs))))
    disc = DiscreteModel(0.5 * np.eye(2), np.ones((2, 1)), np.ones((1, 2)), np.zeros((1, 1)),
                         dt=0.01)
    with pytest.raises(DimensionError, match='dt must be positive'):
        disc.step(np.zeros(2), np.zeros(1), dt=float('nan'))
