"""Tests of the frozen models and of the model file format (no pickle, strict validation)."""

from __future__ import annotations

import json
import os
import re
import zipfile

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from soft_rom.errors import DimensionError, ModelFileError
from soft_rom.models import (
    DiscreteModel,
    FORMAT_VERSION,
    load_model,
    SecondOrderModel,
)


def _random_spd(rng: np.random.Generator, r: int, lo: float, hi: float) -> np.ndarray:
    Qm, _ = np.linalg.qr(rng.normal(size=(r, r)))
    return (Qm * rng.uniform(lo, hi, r)) @ Qm.T


def _second_order(seed: int = 0, r: int = 4, m: int = 3, p: int = 5) -> SecondOrderModel:
    rng = np.random.default_rng(seed)
    return SecondOrderModel(
        _random_spd(rng, r, 10.0, 400.0), _random_spd(rng, r, 0.5, 5.0),
        rng.normal(size=(r, m)), rng.normal(size=(p, r)), dt=1e-3,
        y_ref=rng.normal(size=p), input_names=[f'chamber_{i}' for i in range(m)],
        input_units=['Pa'] * m, output_units=['m'] * p,
        metadata={'provenance': {'bags': ['ep1.mcap']}, 'diagnostics': {'training_error': 0.01}})


def _discrete(seed: int = 1, r: int = 5, m: int = 2, p: int = 3) -> DiscreteModel:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(r, r))
    A *= 0.9 / np.max(np.abs(np.linalg.eigvals(A)))
    return DiscreteModel(A, rng.normal(size=(r, m)), rng.normal(size=(p, r)),
                         rng.normal(size=(p, m)), dt=2e-3, method='era', y_ref=np.ones(p))


def test_zoh_matches_fine_ode_solution() -> None:
    model = _second_order()
    rng = np.random.default_rng(3)
    k = 400
    U = np.repeat(rng.normal(size=(model.n_inputs, k // 20)), 20, axis=1)
    Y = model.simulate(U)
    Ac, Bc, Cc = model.first_order()
    t_grid = np.arange(k) * model.dt
    x = np.zeros(model.n_states)
    ref = np.empty_like(Y)
    for j in range(k):
        ref[:, j] = Cc @ x + model.y_ref
        sol = solve_ivp(lambda _t, z, u=U[:, j]: Ac @ z + Bc @ u,
                        (t_grid[j], t_grid[j] + model.dt), x, rtol=1e-12, atol=1e-14,
                        method='DOP853')
        x = sol.y[:, -1]
    dev = Y - model.y_ref[:, None]
    assert np.linalg.norm(Y - ref) / np.linalg.norm(dev) < 1e-6


def test_step_and_simulate_agree() -> None:
    model = _discrete()
    U = np.random.default_rng(0).normal(size=(model.n_inputs, 50))
    Y, X = model.simulate(U, return_states=True)
    x = model.initial_state()
    for j in range(U.shape[1]):
        np.testing.assert_allclose(model.output(x, U[:, j]), Y[:, j], rtol=0, atol=1e-13)
        x = model.step(x, U[:, j])
    np.testing.assert_array_equal(X[:, 0], np.zeros(model.n_states))


def test_step_and_output_name_a_wrong_state_or_input() -> None:
    """A controller passing the wrong vector gets the shape it needs, not a matmul error."""
    for model in (_discrete(), _second_order()):
        n, m = model.n_states, model.n_inputs
        x, u = model.initial_state(), np.zeros(m)
        with pytest.raises(DimensionError, match=rf'u must have shape \({m},\)'):
            model.step(x, np.zeros(m + 1))
        with pytest.raises(DimensionError, match=rf'x must have shape \({n},\)'):
            model.step(np.zeros(n - 1), u)
        with pytest.raises(DimensionError, match='x must have shape'):
            model.output(np.zeros((n + 2, 3)))
        # k states at once still work, column by column
        X = np.random.default_rng(0).normal(size=(n, 3))
        Y = model.output(X)
        np.testing.assert_allclose(Y[:, 1], model.output(X[:, 1]), rtol=0, atol=1e-12)
        np.testing.assert_allclose(model.step(X, np.zeros((m, 3)))[:, 2],
                                   model.step(X[:, 2], u), rtol=0, atol=1e-12)


def test_step_and_output_refuse_a_vector_mixed_with_columns() -> None:
    """``u`` as a column (MATLAB habit) with a vector ``x`` broadcast to an (n, n) "state"."""
    for model in (_discrete(), _second_order()):
        n, m = model.n_states, model.n_inputs
        x, u = np.ones(n), np.ones(m)
        for xs, us in ((x, u[:, None]), (x[:, None], u), (np.ones((n, 3)), np.ones((m, 2))),
                       (np.ones((n, 2)), u)):
            with pytest.raises(DimensionError,
                               match=re.escape(f'x has shape {xs.shape} and u {us.shape}')):
                model.step(xs, us)
            with pytest.raises(DimensionError, match='give both as vectors'):
                model.output(xs, us)
        np.testing.assert_allclose(model.step(x[:, None], u[:, None])[:, 0], model.step(x, u),
                                   rtol=0, atol=1e-12)


def test_state_from_output_names_a_wrong_or_non_finite_measurement() -> None:
    for model in (_discrete(), _second_order()):
        p, m = model.n_outputs, model.n_inputs
        with pytest.raises(DimensionError, match=re.escape(f'y must have shape ({p},)')):
            model.state_from_output(np.zeros(p + 1))
        with pytest.raises(DimensionError, match='y contains NaN or Inf'):
            model.state_from_output(np.full(p, np.nan))
        with pytest.raises(DimensionError, match=re.escape(f'u must have shape ({m},)')):
            model.state_from_output(model.y_ref, np.zeros(m + 1))
        assert np.abs(model.state_from_output(model.y_ref)).max() < 1e-12


def test_inputs_that_are_not_real_numbers_are_named() -> None:
    """Complex, ragged or text inputs get a DimensionError naming the signal, not a cast."""
    model = _second_order()
    m = model.n_inputs
    with pytest.raises(DimensionError, match='U must be real'):
        model.simulate(np.ones((m, 5)) * (1 + 1j))
    with pytest.raises(DimensionError, match='U must be an array of numbers'):
        model.simulate([[0.0, 1.0], [0.0]] + [[0.0, 1.0]] * (m - 2))
    with pytest.raises(DimensionError, match='U must be an array of numbers'):
        model.simulate([['a', 'b']] * m)
    # a list of real numbers and integer arrays are still accepted as they are
    Y = model.simulate(np.ones((m, 5), dtype=int).tolist())
    np.testing.assert_allclose(Y, model.simulate(np.ones((m, 5))), rtol=0, atol=0)


def test_discrete_multiple_of_dt() -> None:
    model = _discrete()
    u = np.array([0.3, -1.0])
    x0 = np.arange(model.r, dtype=float)
    x = x0.copy()
    for _ in range(3):
        x = model.step(x, u)
    np.testing.assert_allclose(model.step(x0, u, dt=3 * model.dt), x, atol=1e-12)
    with pytest.raises(DimensionError, match='whole'):
        model.discretize(1.5 * model.dt)


def test_second_order_variable_dt_composes() -> None:
    model = _second_order()
    u = np.ones(model.n_inputs)
    x0 = np.r_[np.ones(model.r), np.zeros(model.r)]
    two = model.step(model.step(x0, u, dt=0.0007), u, dt=0.0013)
    np.testing.assert_allclose(model.step(x0, u, dt=0.002), two, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize('factory', [_second_order, _discrete])
def test_round_trip_bit_exact(tmp_path, factory) -> None:
    model = factory()
    path = model.save(tmp_path / 'm.npz')
    loaded = load_model(path)
    assert type(loaded) is type(model)
    for name, arr in model.matrices().items():
        assert np.array_equal(arr, loaded.matrices()[name])
        assert arr.tobytes() == loaded.matrices()[name].tobytes()
    assert loaded.y_ref.tobytes() == model.y_ref.tobytes()
    assert loaded.metadata == model.metadata
    assert loaded.input_names == model.input_names
    assert loaded.method == model.method and loaded.dt == model.dt
    U = np.random.default_rng(1).normal(size=(model.n_inputs, 30))
    assert np.array_equal(model.simulate(U), loaded.simulate(U))


def _rewrite(src, dst, *, arrays=None, header_update=None, raw_extra=None) -> None:
    with np.load(src, allow_pickle=False) as npz:
        data = {k: npz[k] for k in npz.files}
    header = json.loads(data['__metadata__'].tobytes())
    header.update(header_update or {})
    data['__metadata__'] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    data.update(arrays or {})
    np.savez(dst, **data)
    if raw_extra:
        with zipfile.ZipFile(dst, 'a') as zf:
            for name, payload in raw_extra.items():
                zf.writestr(name, payload)


class _Boom:
    def __reduce__(self):  # executed only if someone unpickles
        return (exec, ("open('/tmp/soft_rom_pwned', 'w').write('x')",))


def test_hostile_pickled_object_array_is_refused(tmp_path) -> None:
    good = _second_order().save(tmp_path / 'good.npz')
    bad = tmp_path / 'bad.npz'
    with np.load(good) as npz:
        data = {k: npz[k] for k in npz.files}
    data['K'] = np.array([_Boom()], dtype=object)  # np.savez pickles object arrays
    np.savez(bad, **data)
    if os.path.exists('/tmp/soft_rom_pwned'):
        os.remove('/tmp/soft_rom_pwned')
    with pytest.raises(ModelFileError, match='object array|pickle'):
        load_model(bad)
    assert not os.path.exists('/tmp/soft_rom_pwned')


@pytest.mark.parametrize('case, match', [
    ('nan', 'NaN'),
    ('shape', 'shape|must have'),
    ('version', 'version'),
    ('int', 'dtype'),
    ('missing', 'needs arrays'),
    ('format', 'format'),
])
def test_bad_files_are_refused(tmp_path, case, match) -> None:
    model = _second_order()
    good = model.save(tmp_path / 'good.npz')
    bad = tmp_path / 'bad.npz'
    if case == 'nan':
        K = model.K.copy()
        K[0, 0] = np.nan
        _rewrite(good, bad, arrays={'K': K})
    elif case == 'shape':
        _rewrite(good, bad, arrays={'B': np.zeros((model.r + 1, model.n_inputs))})
    elif case == 'version':
        _rewrite(good, bad, header_update={'format_version': FORMAT_VERSION + 1})
    elif case == 'int':
        _rewrite(good, bad, arrays={'K': np.eye(model.r, dtype=np.int64)})
    elif case == 'missing':
        with np.load(good) as npz:
            data = {k: npz[k] for k in npz.files if k != 'E'}
        np.savez(bad, **data)
    elif case == 'format':
        _rewrite(good, bad, header_update={'format': 'something.else'})
    with pytest.raises(ModelFileError, match=match):
        load_model(bad)


def test_a_newer_file_with_arrays_this_version_does_not_know_says_it_is_newer(tmp_path) -> None:
    """As the cubic model's G and H were to the soft_rom before it: not "not a model file"."""
    good = _second_order().save(tmp_path / 'good.npz')
    newer = tmp_path / 'newer.npz'
    _rewrite(good, newer, arrays={'N': np.eye(4)},
             header_update={'format_version': 99, 'class': 'FutureModel'})
    with pytest.raises(ModelFileError, match='format version 99 is not supported by this '
                                             'soft_rom.*upgrade soft_rom'):
        load_model(newer)
    _rewrite(good, newer, arrays={'N': np.eye(4)}, header_update={'class': 'FutureModel'})
    with pytest.raises(ModelFileError, match="unknown model class 'FutureModel' "
                                             r'\(a newer soft_rom may read it\)'):
        load_model(newer)
    # an extra entry in a file that is no newer, or no model file at all: refused as before
    _rewrite(good, newer, arrays={'N': np.eye(4)})
    with pytest.raises(ModelFileError, match="unexpected archive entry 'N.npy'"):
        load_model(newer)
    np.savez(newer, a=np.eye(2))
    with pytest.raises(ModelFileError, match="unexpected archive entry 'a.npy'"):
        load_model(newer)


def test_missing_and_corrupt_files(tmp_path) -> None:
    with pytest.raises(FileNotFoundError):
        load_model(tmp_path / 'nope.npz')
    junk = tmp_path / 'junk.npz'
    junk.write_bytes(b'not a zip at all')
    with pytest.raises(ModelFileError, match='corrupt'):
        load_model(junk)
    good = _second_order().save(tmp_path / 'good.npz')
    trunc = tmp_path / 'trunc.npz'
    trunc.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(ModelFileError):
        load_model(trunc)


def test_constructor_validation() -> None:
    with pytest.raises(DimensionError):
        SecondOrderModel(np.eye(2), np.eye(2), np.ones((3, 1)), np.ones((1, 2)), dt=1e-3)
    with pytest.raises(DimensionError):
        DiscreteModel(np.eye(2), np.ones((2, 1)), np.ones((1, 2)), dt=0.0)
    with pytest.raises(DimensionError):
        DiscreteModel(np.eye(2) * np.nan, np.ones((2, 1)), np.ones((1, 2)), dt=1.0)


def test_stability_margin_and_eigenvalues() -> None:
    model = _second_order()
    assert np.all(model.eigenvalues().real < 0)
    assert 0 < model.stability_margin() < 1
    unstable = DiscreteModel(np.diag([1.1, 0.5]), np.ones((2, 1)), np.ones((1, 2)), dt=1.0)
    assert unstable.stability_margin() == pytest.approx(-0.1)


def test_non_finite_inputs_are_named_not_propagated() -> None:
    """A NaN pressure is named with its index, not propagated or misreported.

    It made every later output NaN (linear models, a RuntimeWarning at most); the cubic
    model said its implicit step "did not converge".
    """
    from soft_rom.models import CubicSecondOrderModel
    base = _second_order()
    r = base.r
    cubic = CubicSecondOrderModel(base.K, base.C, np.zeros((r, r, r)), np.zeros((r, r, r, r)),
                                  base.B, base.E, dt=base.dt, y_ref=base.y_ref)
    for model in (_discrete(), base, cubic):
        m, n = model.n_inputs, model.n_states
        for bad in (np.nan, np.inf):
            U = np.ones((m, 20))
            U[m - 1, 7] = bad
            with pytest.raises(DimensionError,
                               match=re.escape(f'U contains NaN or Inf (first at index '
                                               f'({m - 1}, 7))')):
                model.simulate(U)
            u = np.ones(m)
            u[0] = bad
            with pytest.raises(DimensionError, match='u .*(NaN or Inf|must be finite)'):
                model.step(model.initial_state(), u)
            x = np.zeros(n)
            x[1] = bad
            with pytest.raises(DimensionError, match='x .*(NaN or Inf|must be finite)'):
                model.step(x, np.ones(m))


def test_a_step_length_that_is_not_a_number_is_one_line() -> None:
    """``discretize('0.01')`` was a TypeError traceback for a DMDc/ERA model."""
    for model in (_discrete(), _second_order()):
        with pytest.raises(DimensionError, match='dt must be a positive number of seconds'):
            model.discretize('ten ms')
        with pytest.raises(DimensionError, match='dt must be a positive number of seconds'):
            model.step(model.initial_state(), np.zeros(model.n_inputs), dt=[0.01, 0.02])
        with pytest.raises(DimensionError, match='dt must be positive'):
            model.discretize(-model.dt)
        assert model.discretize(np.float64(2 * model.dt)).dt == pytest.approx(2 * model.dt)


def test_a_newer_version_of_a_known_class_says_so_with_an_extra_array(tmp_path) -> None:
    """A known class's file of a newer version: its version and an upgrade hint (README).

    Also when it holds arrays this version does not know: a SecondOrderModel file of
    version 2 with a new array was called "not a soft_rom model file"; without the array,
    "at most 1, not 2" (no hint).
    """
    good = _second_order().save(tmp_path / 'good.npz')
    newer = tmp_path / 'newer.npz'
    for arrays in ({'N': np.eye(4)}, None):
        _rewrite(good, newer, arrays=arrays, header_update={'format_version': FORMAT_VERSION + 1})
        with pytest.raises(ModelFileError, match=f'SecondOrderModel file of format version '
                                                 f'{FORMAT_VERSION + 1} is newer than this '
                                                 'soft_rom reads.*upgrade soft_rom'):
            load_model(newer)


def test_a_string_is_one_name_or_every_input_s_unit_not_its_letters(tmp_path) -> None:
    """A string is every channel's unit, or one name.

    ``input_units='Pa'`` for two inputs gave units ['P', 'a'] (saved so in the file);
    ``input_names='pq'`` gave two inputs named 'p' and 'q'.
    """
    rng = np.random.default_rng(0)
    K, C = _random_spd(rng, 2, 10.0, 20.0), np.eye(2)
    model = SecondOrderModel(K, C, np.ones((2, 2)), np.eye(2), dt=1e-3, input_units='Pa',
                             output_units='m')
    assert model.input_units == ['Pa', 'Pa'] and model.output_units == ['m', 'm']
    assert load_model(model.save(tmp_path / 'u.npz')).input_units == ['Pa', 'Pa']
    with pytest.raises(DimensionError, match='input_names must list 2 names; got 1'):
        SecondOrderModel(K, C, np.ones((2, 2)), np.eye(2), dt=1e-3, input_names='pq')
    one = SecondOrderModel(K, C, np.ones((2, 1)), np.eye(2), dt=1e-3, input_names='chamber')
    assert one.input_names == ['chamber']


def test_metadata_of_numpy_values_and_nan_is_saved_as_json(tmp_path) -> None:
    """Metadata: numpy values become Python ones, NaN and Inf None (JSON has neither).

    Numpy values were a TypeError at construction ("Object of type int64 is not JSON
    serializable"); a NaN diagnostic made save() fail with "Out of range float values are
    not JSON compliant".
    """
    meta = {'n': np.int64(3), 'scale': np.ones(2, dtype=np.float32), 'fit': (1, 2),
            'diagnostics': {'training_error': float('nan'), 'margin': np.float64(np.inf)}}
    model = _second_order()
    model = SecondOrderModel(model.K, model.C, model.B, model.E, dt=model.dt, metadata=meta)
    expected = {'n': 3, 'scale': [1.0, 1.0], 'fit': [1, 2],
                'diagnostics': {'training_error': None, 'margin': None}}
    assert model.metadata == expected and type(model.metadata['n']) is int
    assert load_model(model.save(tmp_path / 'm.npz')).metadata == expected


def test_a_model_dt_that_is_not_a_number_is_one_line() -> None:
    """``dt='0.001'`` was numpy's "ufunc 'isfinite' not supported" TypeError."""
    model = _second_order()
    for bad, words in (('1 ms', 'a positive number of seconds'), (None, 'a positive number'),
                       (0.0, 'positive'), (float('nan'), 'positive')):
        with pytest.raises(DimensionError, match=f'dt must be {words}'):
            SecondOrderModel(model.K, model.C, model.B, model.E, dt=bad)
    assert SecondOrderModel(model.K, model.C, model.B, model.E, dt='0.002').dt == 0.002
