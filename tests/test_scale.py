"""Streaming POD and streamed fits (soft_rom.scale) against dense in-memory references."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

from soft_rom.basis import BasisBuilder, POD
from soft_rom.data import Episode
from soft_rom.errors import ConfigError, NotFittedError
from soft_rom.scale.blocks import LocalExecutor, SnapshotSet
from soft_rom.scale.fit import (
    fit_reduced_model,
    fit_streaming,
    open_training_data,
    reduce_streaming,
)
from soft_rom.scale.pod import dense_reference, StreamingPOD

N, RT, M, P, DT = 600, 8, 3, 5, 0.01


def _lowrank(seed: int = 1, n: int = 800, ks=(200, 150, 170), rank: int = 25,
             noise: float = 1e-7):
    """Snapshots with a decaying spectrum (1 .. 1e-4) plus white noise."""
    rng = np.random.default_rng(seed)
    modes = np.linalg.qr(rng.standard_normal((n, rank)))[0]
    amp = np.logspace(0, -4, rank)
    q_ref = rng.standard_normal(n)
    arrays = [q_ref[:, None] + modes @ (amp[:, None] * rng.standard_normal((rank, k)))
              + noise * rng.standard_normal((n, k)) for k in ks]
    return arrays, q_ref


def _system_episodes(seed: int = 0, ks=(200, 160), noise: float = 0.0):
    """A stable discrete LTI system lifted to N states by a fixed random map (exact rank RT)."""
    rng = np.random.default_rng(seed)
    A = np.linalg.qr(rng.standard_normal((RT, RT)))[0] * 0.97
    B = rng.standard_normal((RT, M))
    Phi = rng.standard_normal((N, RT))
    C = rng.standard_normal((P, RT))
    q_ref, y_ref = rng.standard_normal(N), rng.standard_normal(P)
    eps = []
    for e, k in enumerate(ks):
        U = rng.standard_normal((M, k))
        X = np.zeros((RT, k))
        for j in range(k - 1):
            X[:, j + 1] = A @ X[:, j] + B @ U[:, j]
        Q = Phi @ X + q_ref[:, None] + noise * rng.standard_normal((N, k))
        eps.append(Episode(t=np.arange(k) * DT, U=U, Y=C @ X + y_ref[:, None], Q=Q,
                           name=f'ep{e + 1}'))
    return eps, q_ref, y_ref


def _training_set(tmp_path, eps, q_ref, y_ref, chunks=(512, 32)):
    from soft_rom.dataset import TrainingSet
    return TrainingSet.from_episodes(tmp_path / 'ts.zarr', eps, q_ref=q_ref, y_ref=y_ref,
                                     q_chunks=chunks)


def _basis_error(V, U):
    """Largest entry difference after the sign convention (both fixed the same way)."""
    return float(np.max(np.abs(V - U)))


@pytest.mark.parametrize('method', ['randomized', 'gram'])
def test_streaming_pod_matches_dense_svd(method):
    arrays, q_ref = _lowrank()
    U, s = dense_reference(arrays, q_ref)
    pod = StreamingPOD(r=12, method=method, n_coords=20, block_cols=64,
                       block_rows=256).fit(arrays, q_ref)
    assert pod.basis_.shape == (800, 12)
    # Modes with sigma_i / sigma_1 >= 1e-3 and a clear gap: equal to dense SVD to 1e-9.
    assert _basis_error(pod.basis_, U[:, :12]) < 1e-9
    assert np.allclose(pod.singular_values_[:12], s[:12], rtol=1e-10, atol=0)
    X = np.concatenate(arrays, axis=1) - q_ref[:, None]
    assert pod.total_energy_ == pytest.approx(float(np.sum(X * X)), rel=1e-12)
    assert np.allclose(pod.energy_[:12], np.cumsum(s ** 2)[:12] / np.sum(s ** 2), rtol=1e-12)
    # Reduced coordinates come with the pass (no extra read) and equal V^T (Q - q_ref).
    for z, a in zip(pod.reduced_, arrays):
        assert np.max(np.abs(z - pod.basis_.T @ (a - q_ref[:, None]))) < 1e-12 * s[0]
    assert pod.n_passes_ == (3 if method == 'randomized' else 2)
    assert isinstance(pod, BasisBuilder)


def test_energy_rule_agrees_with_in_memory_pod():
    arrays, q_ref = _lowrank(seed=3)
    ref = POD(energy=0.99).fit(arrays, q_ref)
    pod = StreamingPOD(energy=0.99, n_coords=25).fit(arrays, q_ref)
    assert pod.r_ == ref.r_
    assert _basis_error(pod.basis_, ref.basis_) < 1e-9
    with pytest.raises(ConfigError, match='n_coords'):
        StreamingPOD(energy=1.0, n_coords=5, oversample=0).fit(arrays, q_ref)
    with pytest.raises(NotFittedError):
        StreamingPOD().project(arrays[0])


def test_each_chunk_read_once_per_pass(tmp_path):
    arrays, q_ref = _lowrank(n=1200, ks=(200, 130))
    eps = [Episode(t=np.arange(a.shape[1]) * DT, U=np.zeros((1, a.shape[1])),
                   Y=np.zeros((1, a.shape[1])), Q=a, name=f'e{i}') for i, a in enumerate(arrays)]
    ts = _training_set(tmp_path, eps, q_ref, np.zeros(1), chunks=(512, 32))
    snaps = SnapshotSet([ts.q_array(n) for n in ts.episode_names], ts.q_ref)
    total_bytes = 8 * 1200 * 330
    for method, passes in (('randomized', 3), ('gram', 2)):
        ex = LocalExecutor()
        pod = StreamingPOD(r=5, method=method, executor=ex, block_bytes=64 * 1200 * 8).fit(snaps)
        assert pod.n_passes_ == passes
        assert ex.bytes_read == passes * total_bytes
    # Projection of new data streams too and equals the dense product.
    assert np.allclose(pod.project(arrays[0]), pod.basis_.T @ (arrays[0] - q_ref[:, None]),
                       atol=1e-12)
    # Gram refuses storage in full-height chunks (it would re-read every chunk per row block).
    ts2 = _training_set(tmp_path / 'b', eps, q_ref, np.zeros(1), chunks=(4096, 32))
    snaps2 = SnapshotSet([ts2.q_array(n) for n in ts2.episode_names], ts2.q_ref)
    with pytest.raises(ConfigError, match='randomized'):
        StreamingPOD(r=5, method='gram', block_bytes=1000).fit(snaps2)
    with pytest.raises(ConfigError, match='memory_limit'):
        StreamingPOD(r=5, method='gram', memory_limit=2 ** 20).fit(snaps)


@pytest.mark.parametrize('pod_method', ['randomized', 'gram'])
def test_streamed_dmdc_equals_in_memory_dmdc(tmp_path, pod_method):
    from soft_rom.learners.dmdc import DMDc
    eps, q_ref, y_ref = _system_episodes(noise=1e-9)
    ts = _training_set(tmp_path, eps, q_ref, y_ref)
    U_test = np.random.default_rng(7).standard_normal((M, 200))
    for r, p in ((8, None), (6, 8)):
        ref = DMDc(r=r, p=p).fit(eps, q_ref=q_ref, y_ref=y_ref).model_
        model = fit_streaming(ts, 'dmdc', r=r, p=p, pod_method=pod_method, n_coords=20)
        Y1, Y2 = ref.simulate(U_test), model.simulate(U_test)
        dev = np.linalg.norm(Y1 - y_ref[:, None])
        assert np.linalg.norm(Y1 - Y2) / dev < 1e-10
        assert np.allclose(np.sort_complex(np.linalg.eigvals(model.A)),
                           np.sort_complex(np.linalg.eigvals(ref.A)), atol=1e-10)
        assert model.metadata['scale']['pod_method'] == pod_method
        assert model.output_names == ts.output_names


def test_t_max_stays_lazy_and_matches_sliced_fit(tmp_path):
    from soft_rom.learners.dmdc import DMDc
    eps, q_ref, y_ref = _system_episodes(ks=(200, 180))
    ts = _training_set(tmp_path, eps, q_ref, y_ref)
    td = open_training_data(ts, t_max=1.2)
    assert [ep.n_samples for ep in td.episodes] == [120, 120]
    assert not isinstance(td.episodes[0].Q, np.ndarray)
    model = fit_streaming(ts, 'dmdc', r=8, t_max=1.2, n_coords=20)
    ref = DMDc(r=8).fit([ep.slice(0, 120) for ep in eps], q_ref=q_ref, y_ref=y_ref).model_
    U_test = np.random.default_rng(2).standard_normal((M, 100))
    Y1 = ref.simulate(U_test)
    assert np.linalg.norm(Y1 - model.simulate(U_test)) / np.linalg.norm(
        Y1 - y_ref[:, None]) < 1e-10


def test_era_needs_no_snapshots_and_equals_direct_fit(tmp_path):
    from soft_rom.learners.era import ERAOKID
    eps, q_ref, y_ref = _system_episodes(ks=(400,))
    ts = _training_set(tmp_path, eps, q_ref, y_ref)
    model = fit_streaming(ts, 'era', r=8, n_markov=40, decimation=1)
    ref = ERAOKID(r=8, n_markov=40, decimation=1).fit(
        Episode(t=eps[0].t, U=eps[0].U, Y=eps[0].Y), y_ref=y_ref).model_
    U_test = np.random.default_rng(3).standard_normal((M, 100))
    assert np.allclose(model.simulate(U_test), ref.simulate(U_test), rtol=0, atol=1e-10)


def test_lopinf_on_streamed_coordinates(tmp_path):
    lopinf = pytest.importorskip('soft_rom.learners.lopinf')
    eps, q_ref, y_ref = _system_episodes()
    ts = _training_set(tmp_path, eps, q_ref, y_ref)
    red = reduce_streaming(ts, r=6, n_coords=20)
    model = fit_reduced_model(red, 'lopinf', 6)
    ref = lopinf.LOpInf(r=6).fit(eps, q_ref=q_ref, y_ref=y_ref).model_
    for name in ('K', 'C', 'B', 'E'):
        a, b = getattr(model, name), getattr(ref, name)
        assert np.linalg.norm(a - b) <= 1e-6 * np.linalg.norm(b)


@pytest.fixture(scope='module')
def dask_client():
    distributed = pytest.importorskip('dask.distributed')
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                       dashboard_address=None)
    client = distributed.Client(cluster)
    yield client
    client.close()
    cluster.close()


@pytest.mark.parametrize('method', ['randomized', 'gram'])
def test_dask_pod_equals_local(tmp_path, dask_client, method):
    from soft_rom.scale.dask_backend import DaskExecutor
    arrays, q_ref = _lowrank(n=1200, ks=(200, 130))
    eps = [Episode(t=np.arange(a.shape[1]) * DT, U=np.zeros((1, a.shape[1])),
                   Y=np.zeros((1, a.shape[1])), Q=a, name=f'e{i}') for i, a in enumerate(arrays)]
    ts = _training_set(tmp_path, eps, q_ref, np.zeros(1))
    snaps = SnapshotSet([ts.q_array(n) for n in ts.episode_names], ts.q_ref)
    kw = dict(r=10, method=method, n_coords=15, block_bytes=64 * 1200 * 8)
    local = StreamingPOD(**kw).fit(snaps)
    dist = StreamingPOD(**kw, executor=DaskExecutor(dask_client)).fit(snaps)
    assert np.max(np.abs(dist.basis_ - local.basis_)) <= 1e-10
    for a, b in zip(dist.coords_, local.coords_):
        assert np.max(np.abs(a - b)) <= 1e-10 * local.singular_values_[0]
    assert dist.total_energy_ == pytest.approx(local.total_energy_, rel=1e-12)


def test_dask_fit_equals_local(tmp_path, dask_client):
    eps, q_ref, y_ref = _system_episodes(noise=1e-8)
    ts = _training_set(tmp_path, eps, q_ref, y_ref)
    # t_max keeps Q lazy (a column window) on the workers too.
    local = fit_streaming(ts, 'dmdc', r=8, n_coords=20, t_max=1.5)
    dist = fit_streaming(ts, 'dmdc', r=8, n_coords=20, t_max=1.5, client=dask_client)
    for name in ('A', 'B', 'C'):
        a, b = getattr(dist, name), getattr(local, name)
        assert np.linalg.norm(a - b) <= 1e-10 * np.linalg.norm(b)
    assert dist.metadata['scale']['backend'] == 'DaskExecutor'
    if importlib.util.find_spec('soft_rom.learners.lopinf') is not None:
        local = fit_streaming(ts, 'lopinf', r=6, n_coords=20)
        dist = fit_streaming(ts, 'lopinf', r=6, n_coords=20, client=dask_client)
        for name in ('K', 'C', 'B', 'E'):
            a, b = getattr(dist, name), getattr(local, name)
            assert np.linalg.norm(a - b) <= 1e-10 * np.linalg.norm(b)
