"""StreamingPOD (soft_rom.scale.pod) against a dense SVD and the in-memory POD."""

from __future__ import annotations

from _scale_data import basis_error, dense_reference, lowrank
import numpy as np
import pytest

from soft_rom.basis import BasisBuilder, POD
from soft_rom.errors import ConfigError, NotFittedError
from soft_rom.scale.pod import StreamingPOD


@pytest.mark.parametrize('method', ['randomized', 'gram'])
def test_streaming_pod_matches_dense_svd(method):
    arrays, q_ref = lowrank()
    U, s = dense_reference(arrays, q_ref)
    pod = StreamingPOD(r=12, method=method, n_coords=20, block_cols=64,
                       block_rows=256).fit(arrays, q_ref)
    assert pod.basis_.shape == (800, 12)
    # Modes with sigma_i / sigma_1 >= 1e-3 and a clear gap: equal to dense SVD to 1e-9.
    assert basis_error(pod.basis_, U[:, :12]) < 1e-9
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
    arrays, q_ref = lowrank(seed=3)
    ref = POD(energy=0.99).fit(arrays, q_ref)
    pod = StreamingPOD(energy=0.99, n_coords=25).fit(arrays, q_ref)
    assert pod.r_ == ref.r_
    assert basis_error(pod.basis_, ref.basis_) < 1e-9
    with pytest.raises(ConfigError, match='n_coords'):
        StreamingPOD(energy=1.0, n_coords=5, oversample=0).fit(arrays, q_ref)
    with pytest.raises(NotFittedError):
        StreamingPOD().project(arrays[0])
