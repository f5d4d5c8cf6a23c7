"""Corotational tetrahedra: invariance, energy consistency, linearization, cantilever."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse.linalg as spla
from scipy.spatial.transform import Rotation

from soft_rom.errors import ConfigError
from soft_rom.sim import CorotationalFEM, polar_rotation, tetrahedralize
from soft_rom.sim.mesh import box_grid


def _beam(nx: int = 12, n: int = 2, L: float = 1.0, h: float = 0.1, nu: float = 0.3):
    xs, ys, zs = box_grid(L, h, h, nx, n, n)
    mesh = tetrahedralize(xs, ys, zs, np.zeros((nx, n, n), dtype=np.int64))
    return mesh, CorotationalFEM(mesh.nodes, mesh.tets, young=1e6, poisson=nu, density=1000.0)


def test_mesh_is_conforming_and_fills_the_box() -> None:
    mesh, fem = _beam(nx=5, n=3)
    assert mesh.n_nodes == 6 * 4 * 4
    assert len(mesh.tets) == 6 * 5 * 3 * 3
    assert fem.volume.sum() == pytest.approx(1.0 * 0.1 * 0.1, rel=1e-12)
    assert np.all(fem.volume > 0)
    assert fem.mass.sum() == pytest.approx(1000.0 * 0.01, rel=1e-12)
    # conforming: every interior triangle is shared by exactly two tetrahedra
    faces = np.sort(mesh.tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3),
                    axis=1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    boundary = np.sum(counts == 1)
    assert set(np.unique(counts)) <= {1, 2}
    # boundary triangles: 2 per boundary quad of the 5 x 3 x 3 grid
    assert boundary == 2 * 2 * (5 * 3 + 5 * 3 + 3 * 3)


def test_rigid_motion_gives_zero_force() -> None:
    mesh, fem = _beam()
    rng = np.random.default_rng(1)
    scale = np.abs(fem.elastic_force(mesh.nodes + 1e-3 * rng.standard_normal(
        mesh.nodes.shape))).max()
    for k in range(4):
        R = Rotation.from_rotvec(rng.normal(size=3) * (0.5 + k)).as_matrix()
        x = mesh.nodes @ R.T + rng.normal(size=3)
        f = fem.elastic_force(x)
        assert np.abs(f).max() < 1e-9 * scale
        assert fem.energy(x) < 1e-18


def test_force_is_minus_energy_gradient() -> None:
    mesh, fem = _beam()
    rng = np.random.default_rng(2)
    R = Rotation.from_rotvec([0.3, -0.8, 0.4]).as_matrix()
    x = (mesh.nodes + 0.005 * rng.standard_normal(mesh.nodes.shape)) @ R.T
    f = fem.elastic_force(x)
    for _ in range(3):
        d = rng.standard_normal(x.shape)
        eps = 1e-6
        num = (fem.energy(x + eps * d) - fem.energy(x - eps * d)) / (2 * eps)
        assert num == pytest.approx(-np.sum(f * d), rel=1e-6)


def test_small_displacements_follow_the_rest_stiffness() -> None:
    mesh, fem = _beam()
    K = fem.stiffness()
    assert abs(K - K.T).max() < 1e-9 * abs(K).max()
    rng = np.random.default_rng(3)
    d = rng.standard_normal(mesh.nodes.shape)
    rel = []
    for amp in (1e-5, 1e-6):
        f = fem.elastic_force(mesh.nodes + amp * d).ravel()
        lin = -(K @ (amp * d).ravel())
        rel.append(np.linalg.norm(f - lin) / np.linalg.norm(lin))
    # the difference is second order: relative error ~ strain (~ amp / 0.05 m) and it drops
    # 10x when the amplitude drops 10x
    assert rel[0] < 10 * 1e-5 / 0.05
    assert rel[1] == pytest.approx(rel[0] / 10, rel=0.05)
    ident = np.broadcast_to(np.eye(3), (len(mesh.tets), 3, 3))
    dx = rng.standard_normal(mesh.nodes.shape)
    np.testing.assert_allclose(fem.warped_matvec(ident, dx).ravel(), K @ dx.ravel(),
                               rtol=0, atol=1e-9 * np.abs(K @ dx.ravel()).max())


def test_polar_rotation_matches_svd_and_handles_inversion() -> None:
    rng = np.random.default_rng(4)
    F = np.eye(3) + 0.3 * rng.standard_normal((500, 3, 3))
    F[:10, :, 0] *= -1                         # inverted elements
    R = polar_rotation(F)
    np.testing.assert_allclose(R @ np.transpose(R, (0, 2, 1)),
                               np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    ok = np.linalg.det(F) > 0
    assert ok.sum() > 400 and not ok[:10].any()
    U, _, Vt = np.linalg.svd(F[ok])
    np.testing.assert_allclose(R[ok], U @ Vt, atol=1e-11)
    S = np.transpose(R, (0, 2, 1)) @ F
    np.testing.assert_allclose(S[ok], np.transpose(S[ok], (0, 2, 1)), atol=1e-11)
    assert np.all(np.linalg.eigvalsh(0.5 * (S[ok] + np.transpose(S[ok], (0, 2, 1)))) > 0)


def test_cantilever_converges_to_beam_theory() -> None:
    """Tip load, square section, L/h = 10: error vs Euler-Bernoulli shrinks with h."""
    errors = []
    for n in (2, 4):
        L, h, P = 1.0, 0.1, 0.1
        mesh, fem = _beam(nx=10 * n, n=n, L=L, h=h)
        free = np.repeat(mesh.nodes[:, 0] > 1e-12, 3)
        tip = np.nonzero(np.abs(mesh.nodes[:, 0] - L) < 1e-12)[0]
        f = np.zeros(mesh.n_dof)
        f[3 * tip + 2] = P / len(tip)
        u = np.zeros(mesh.n_dof)
        u[free] = spla.spsolve(fem.stiffness()[free][:, free].tocsc(), f[free])
        d_eb = P * L ** 3 / (3 * 1e6 * h ** 4 / 12)
        errors.append(np.mean(u[3 * tip + 2]) / d_eb - 1)
    # linear tetrahedra are too stiff and converge from below (table in benchmarks/)
    assert -0.7 < errors[0] < errors[1] < 0
    assert errors[1] > -0.3


def test_bad_material_is_refused() -> None:
    mesh, _ = _beam(nx=2, n=1)
    with pytest.raises(ConfigError):
        CorotationalFEM(mesh.nodes, mesh.tets, young=1e6, poisson=0.5, density=1.0)


def test_warped_stiffness_is_the_tangent_of_a_rotated_body() -> None:
    """At a rigidly rotated (stress-free) state the exact tangent is R K_0 R^T."""
    mesh, fem = _beam()
    Q = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()
    x = mesh.nodes @ Q.T + [0.1, 0.2, -0.3]
    _, R = fem.elastic_force(x, return_rotations=True)
    np.testing.assert_allclose(R, np.broadcast_to(Q, R.shape), atol=1e-12)
    rng = np.random.default_rng(5)
    dx = rng.standard_normal(x.shape)
    kw = fem.warped_matvec(R, dx)
    np.testing.assert_allclose(kw, ((fem.stiffness() @ (dx @ Q).ravel()).reshape(-1, 3)) @ Q.T,
                               atol=1e-9 * np.abs(kw).max())
    eps = 1e-7
    fd = (fem.elastic_force(x + eps * dx) - fem.elastic_force(x - eps * dx)) / (2 * eps)
    np.testing.assert_allclose(-fd, kw, atol=1e-5 * np.abs(kw).max())
