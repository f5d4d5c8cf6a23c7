"""The Dask executor (soft_rom.scale.dask_backend) gives the local results on a cluster."""

from __future__ import annotations

from _scale_data import lowrank, lowrank_episodes, system_episodes, training_set
import numpy as np
import pytest

from soft_rom.learners import DMDc, LOpInf
from soft_rom.pipeline import fit_models, open_training_data
from soft_rom.reduce import StreamingReducer
from soft_rom.scale.blocks import SnapshotSet
from soft_rom.scale.pod import StreamingPOD


def fit_streaming(ts, learner, r, *, n_coords, t_max=None, client=None):
    """One model of ``learner`` streamed with the randomized POD of ``n_coords``."""
    reducer = StreamingReducer(method='randomized', n_coords=n_coords, client=client)
    return fit_models(open_training_data(ts, t_max=t_max), learner, (r,), reducer)[0].model


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
    arrays, q_ref = lowrank(n=1200, ks=(200, 130))
    eps = lowrank_episodes(arrays)
    ts = training_set(tmp_path, eps, q_ref, np.zeros(1))
    snaps = SnapshotSet([ts.q_array(n) for n in ts.episode_names], ts.q_ref)
    kw = dict(r=10, method=method, n_coords=15, block_bytes=64 * 1200 * 8)
    local = StreamingPOD(**kw).fit(snaps)
    dist = StreamingPOD(**kw, executor=DaskExecutor(dask_client)).fit(snaps)
    assert np.max(np.abs(dist.basis_ - local.basis_)) <= 1e-10
    for a, b in zip(dist.coords_, local.coords_):
        assert np.max(np.abs(a - b)) <= 1e-10 * local.singular_values_[0]
    assert dist.total_energy_ == pytest.approx(local.total_energy_, rel=1e-12)


def test_dask_fit_equals_local(tmp_path, dask_client):
    eps, q_ref, y_ref = system_episodes(noise=1e-8)
    ts = training_set(tmp_path, eps, q_ref, y_ref)
    # t_max keeps Q lazy (a column window) on the workers too.
    local = fit_streaming(ts, DMDc(), 8, n_coords=20, t_max=1.5)
    dist = fit_streaming(ts, DMDc(), 8, n_coords=20, t_max=1.5, client=dask_client)
    for name in ('A', 'B', 'C'):
        a, b = getattr(dist, name), getattr(local, name)
        assert np.linalg.norm(a - b) <= 1e-10 * np.linalg.norm(b)
    assert dist.metadata['scale']['backend'] == 'DaskExecutor'
    local = fit_streaming(ts, LOpInf(), 6, n_coords=20)
    dist = fit_streaming(ts, LOpInf(), 6, n_coords=20, client=dask_client)
    for name in ('K', 'C', 'B', 'E'):
        a, b = getattr(dist, name), getattr(local, name)
        assert np.linalg.norm(a - b) <= 1e-10 * np.linalg.norm(b)
