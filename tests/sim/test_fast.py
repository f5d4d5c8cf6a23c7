"""The ``fast`` extra: compiled element loop (numba) and CHOLMOD change nothing but the cost.

Skipped where the extra is not installed (the minimum-versions run), a failure in CI
(environment variable ``CI`` set), where ``.ci/run`` installs it.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.spatial.transform import Rotation

from soft_rom.errors import ConfigError
from soft_rom.sim import _kernels, CorotationalFEM, EelModel, simulate_episode, tetrahedralize
from soft_rom.sim.eel import cholmod_available
from soft_rom.sim.linsolve import _SPDFactor
from soft_rom.sim.mesh import box_grid


def _require(available: bool, what: str) -> None:
    if available:
        return
    if os.environ.get('CI'):
        raise RuntimeError(f'CI is set but {what} cannot be imported: .ci/run installs the '
                           "'fast' extra, whose tests must run in CI.")
    pytest.skip(f'{what} not installed (the fast extra)')


def _beam() -> tuple[np.ndarray, CorotationalFEM]:
    xs, ys, zs = box_grid(1.0, 0.1, 0.1, 12, 2, 2)
    mesh = tetrahedralize(xs, ys, zs, np.zeros((12, 2, 2), dtype=np.int64))
    return mesh.nodes, CorotationalFEM(mesh.nodes, mesh.tets, young=1e6, poisson=0.3,
                                       density=1000.0)


def test_compiled_force_equals_the_numpy_force() -> None:
    _require(_kernels.AVAILABLE, 'numba')
    X, fem = _beam()
    rng = np.random.default_rng(3)
    for k in range(3):
        R = Rotation.from_rotvec(rng.normal(size=3) * (0.4 + k)).as_matrix()
        x = (X + 0.004 * rng.standard_normal(X.shape)) @ R.T + rng.normal(size=3)
        fem.compiled = True
        fast = fem.elastic_force(x)
        fem.compiled = False
        ref = fem.elastic_force(x)
        scale = np.abs(ref).max()
        assert scale > 1.0
        assert np.abs(fast - ref).max() <= 1e-12 * scale


def test_compiled_force_hands_inverted_elements_to_the_svd_path() -> None:
    _require(_kernels.AVAILABLE, 'numba')
    X, fem = _beam()
    x = X.copy()
    t = fem.tets[7]
    n = np.cross(x[t[2]] - x[t[1]], x[t[3]] - x[t[1]])
    n /= np.linalg.norm(n)
    x[t[0]] -= 2.0 * np.dot(x[t[0]] - x[t[1]], n) * n   # mirror node 0 through the far face
    F = fem.deformation_gradient(x)
    assert np.linalg.det(F[7]) < 0                     # element 7 is inverted
    assert _kernels.elastic_force(x, fem.tets, fem._dm_inv, fem._two_mu_v,
                                  fem._lam_v) is None
    fem.compiled = True
    fast = fem.elastic_force(x)
    fem.compiled = False
    np.testing.assert_array_equal(fast, fem.elastic_force(x))
    assert np.all(np.isfinite(fast))


def test_cholmod_solves_the_rest_system_like_the_banded_factor() -> None:
    _require(cholmod_available(), 'scikit-sparse (CHOLMOD)')
    eel = EelModel()
    chol, K, _m = eel._rest_factor(1e-3, 'cholmod')
    band, _K, _m = eel._rest_factor(1e-3, 'banded')
    assert (chol.kind, band.kind) == ('cholmod', 'banded-cholesky')
    m = np.repeat(eel.fem.mass, 3)[eel.free]
    A = sp.diags(m * (1 + 1e-3 * eel.config.rayleigh_mass)) + (
        1e-3 * eel.config.rayleigh_stiffness + 1e-6) * K
    B = np.random.default_rng(0).standard_normal((A.shape[0], 3))
    ref = spla.spsolve(A.tocsc(), B)
    for X in (chol.solve(B), np.stack([chol.solve(B[:, j]) for j in range(3)], axis=1),
              band.solve(B)):
        assert np.linalg.norm(X - ref) <= 1e-10 * np.linalg.norm(ref)


def test_fast_trajectories_equal_the_banded_numpy_ones() -> None:
    """200 steps at 40 kPa: CHOLMOD + compiled forces against banded Cholesky + numpy."""
    _require(cholmod_available() and _kernels.AVAILABLE, 'the fast extra')
    eel = EelModel()
    fast = simulate_episode(eel, 1, n_steps=200, amplitude=40e3, store_states=True)
    eel.fem.compiled = False
    ref = simulate_episode(eel, 1, n_steps=200, amplitude=40e3, store_states=True,
                           linear_solver='banded')
    assert (fast.info['solver'], ref.info['solver']) == ('cholmod', 'banded-cholesky')
    dev = ref.states - ref.states[:, :, :1]
    assert np.linalg.norm(dev) > 1e-3                  # it moved (mm over the body)
    assert np.linalg.norm(fast.states - ref.states) <= 1e-8 * np.linalg.norm(dev)
    np.testing.assert_allclose(fast.centerline, ref.centerline, rtol=0, atol=1e-12)


def test_an_unknown_linear_solver_is_refused() -> None:
    eel = EelModel()
    with pytest.raises(ConfigError, match='linear solver'):
        eel.simulate(np.zeros((6, 3)), 3, linear_solver='pardiso')
    with pytest.raises(ConfigError, match='linear solver'):
        _SPDFactor(sp.identity(3, format='csr'), 'lu')
