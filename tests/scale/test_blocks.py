"""Block plans and the local executor (soft_rom.scale.blocks): each byte read once a pass."""

from __future__ import annotations

from _scale_data import lowrank, lowrank_episodes, training_set
import numpy as np
import pytest

from soft_rom.errors import ConfigError
from soft_rom.scale.blocks import LocalExecutor, SnapshotSet
from soft_rom.scale.pod import StreamingPOD


def test_each_chunk_read_once_per_pass(tmp_path):
    arrays, q_ref = lowrank(n=1200, ks=(200, 130))
    eps = lowrank_episodes(arrays)
    ts = training_set(tmp_path, eps, q_ref, np.zeros(1), chunks=(512, 32))
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
    ts2 = training_set(tmp_path / 'b', eps, q_ref, np.zeros(1), chunks=(4096, 32))
    snaps2 = SnapshotSet([ts2.q_array(n) for n in ts2.episode_names], ts2.q_ref)
    with pytest.raises(ConfigError, match='randomized'):
        StreamingPOD(r=5, method='gram', block_bytes=1000).fit(snaps2)
    with pytest.raises(ConfigError, match='memory limit'):
        StreamingPOD(r=5, method='gram', memory_limit=2 ** 20).fit(snaps)

