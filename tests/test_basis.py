"""Tests of soft_rom.basis: POD recovers a known subspace; lazy snapshots; rank selection."""

from __future__ import annotations

import numpy as np
import pytest

from soft_rom.basis import BasisBuilder, POD, project, select_rank
from soft_rom.data import Episode
from soft_rom.errors import ConfigError, DimensionError, NotFittedError


class LazyArray:
    """Minimal lazy array: only ``shape`` and ``[:, a:b]`` (counts the columns read)."""

    def __init__(self, data):
        self._data = np.asarray(data)
        self.shape = self._data.shape
        self.max_cols = 0

    def __getitem__(self, key):
        rows, cols = key
        assert rows == slice(None) and isinstance(cols, slice)
        out = self._data[:, cols]
        self.max_cols = max(self.max_cols, out.shape[1])
        return out.copy()


def _low_rank(seed=0, n=50, r=3):
    rng = np.random.default_rng(seed)
    Phi, _ = np.linalg.qr(rng.standard_normal((n, r)))
    q_ref = rng.standard_normal(n)
    eps = []
    for j in range(2):
        t = np.linspace(0, 1, 200 + 50 * j)
        a = np.vstack([np.sin((i + 1) * 3.0 * t + j) * 10.0 ** -i for i in range(r)])
        eps.append(q_ref[:, None] + Phi @ a)
    return Phi, q_ref, eps


def test_pod_recovers_known_subspace():
    Phi, q_ref, eps = _low_rank()
    pod = POD(energy=0.999999).fit(eps, q_ref)
    assert pod.r_ == 3
    V = pod.basis_
    np.testing.assert_allclose(V.T @ V, np.eye(3), atol=1e-12)
    assert np.linalg.norm(V @ V.T - Phi @ Phi.T) < 1e-10
    assert pod.singular_values_[3] < 1e-10 * pod.singular_values_[0]
    assert np.all(np.diff(pod.energy_) >= -1e-15) and abs(pod.energy_[-1] - 1.0) < 1e-12
    # Projection and reconstruction are exact on the subspace.
    for Q in eps:
        np.testing.assert_allclose(pod.reconstruct(pod.project(Q)), Q, atol=1e-10)
    assert isinstance(pod, BasisBuilder)


def test_lazy_snapshots_read_in_blocks():
    Phi, q_ref, eps = _low_rank(seed=1)
    lazy = [LazyArray(Q) for Q in eps]
    pod_lazy = POD(r=3, block_columns=64).fit(lazy, q_ref)
    pod = POD(r=3).fit(eps, q_ref)
    np.testing.assert_allclose(pod_lazy.basis_, pod.basis_, atol=1e-12)
    Qhat = project(lazy[1], pod.basis_, q_ref, block_columns=37)
    np.testing.assert_allclose(Qhat, pod.basis_.T @ (eps[1] - q_ref[:, None]), atol=1e-12)
    assert lazy[1].max_cols == 64  # never read whole


def test_rank_selection_and_errors():
    s = np.array([10.0, 5.0, 1.0, 0.1])
    total = np.sum(s ** 2)
    assert select_rank(s, energy=100 / total) == 1
    assert select_rank(s, energy=125 / total + 1e-9) == 3
    assert select_rank(s, energy=1.0) == 4
    assert select_rank(s, r=2, energy=0.1) == 2
    with pytest.raises(ConfigError):
        select_rank(s, r=5)
    with pytest.raises(ConfigError):
        select_rank(s, energy=1.5)
    with pytest.raises(DimensionError):
        select_rank(np.zeros(3))
    with pytest.raises(NotFittedError):
        POD().project(np.zeros((3, 2)))
    with pytest.raises(DimensionError):
        POD().fit([np.zeros((3, 4))], np.zeros(2))


def test_sign_convention_is_scale_invariant():
    Phi, q_ref, eps = _low_rank(seed=2)
    a = POD(r=3).fit(eps, q_ref)
    b = POD(r=3).fit([1e3 * Q for Q in eps], 1e3 * q_ref)
    np.testing.assert_allclose(a.basis_, b.basis_, atol=1e-10)


def test_shared_svd_gives_the_same_pod_bit_for_bit_and_only_for_the_same_arrays() -> None:
    from soft_rom.reduce import InMemoryPOD
    from soft_rom.reduce.memory import training_data

    rng = np.random.default_rng(4)
    t = np.arange(120) * 1e-3
    eps = [Episode(t=t, U=rng.standard_normal((2, 120)), Y=rng.standard_normal((3, 120)),
                   Q=rng.standard_normal((40, 120)) @ np.diag(np.linspace(1, 0.01, 120)),
                   name=f'ep{i}') for i in (1, 2)]
    data = training_data(eps, q_ref=np.zeros(40))
    shared = InMemoryPOD(share_svd=True)
    for r in (8, 3, 8):
        a, b = shared.reduce(data, r=r), InMemoryPOD().reduce(data, r=r)
        assert np.array_equal(a.modes, b.modes) and a.modes.shape == (40, r)
        assert all(np.array_equal(x, y) for x, y in zip(a.coordinates, b.coordinates))
        assert np.array_equal(a.singular_values, b.singular_values)
    held = shared._svd
    # The same values in other arrays, or another q_ref: a new SVD, never the kept one.
    copies = training_data([Episode(t=e.t, U=e.U, Y=e.Y, Q=e.Q.copy(), name=e.name)
                            for e in eps], q_ref=np.zeros(40))
    shared.reduce(copies, r=3)
    assert shared._svd is not held
    other_ref = training_data(copies.episodes, q_ref=np.full(40, 0.5))
    a = shared.reduce(other_ref, r=3)
    assert np.array_equal(a.modes, InMemoryPOD().reduce(other_ref, r=3).modes)


def test_many_states_give_the_pod_of_the_full_svd(monkeypatch):
    """A POD taken on the snapshots' range is the POD of the full thin SVD.

    1,300 states, 1,200 snapshots with a decaying spectrum and noise at 1e-17; to 1e-10.
    """
    import soft_rom.basis as basis_module
    rng = np.random.default_rng(6)
    n, k, s = 1300, 1200, 10.0 ** (-np.arange(300) / 15.0)
    Ul, Vr = (np.linalg.qr(rng.standard_normal((d, 300)))[0] for d in (n, k))
    q_ref = rng.standard_normal(n)
    Q = (Ul * s) @ Vr.T + 1e-17 * rng.standard_normal((n, k)) + q_ref[:, None]
    used = []
    real = basis_module.snapshot_range
    monkeypatch.setattr(basis_module, 'snapshot_range',
                        lambda arrays, tol: used.append(real(arrays, tol)) or used[-1])
    fast = POD(r=12).fit([Q[:, :700], Q[:, 700:]], q_ref)
    assert used and used[0] is not None and used[0].shape[1] == 512
    monkeypatch.setattr(basis_module, 'snapshot_range', lambda arrays, tol: None)
    full = POD(r=12).fit([Q[:, :700], Q[:, 700:]], q_ref)
    np.testing.assert_allclose(fast.basis_, full.basis_, atol=1e-10)
    np.testing.assert_allclose(fast.singular_values_[:12], full.singular_values_[:12],
                               rtol=1e-12)
    assert fast.energy_[11] == pytest.approx(full.energy_[11], rel=1e-12)
    # known truth: the span of the leading 12 singular vectors (gaps of 10^(1/15))
    np.testing.assert_allclose(np.abs(np.sum(fast.basis_ * Ul[:, :12], axis=0)), 1.0,
                               atol=1e-9)
