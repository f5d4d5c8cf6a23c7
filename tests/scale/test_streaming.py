"""Reduce once, then fit (soft_rom.scale.streaming) against the in-memory learners."""

from __future__ import annotations

from _scale_data import M, system_episodes, training_set
import numpy as np
import pytest

from soft_rom.data import Episode
from soft_rom.scale.streaming import (
    fit_reduced_model,
    fit_streaming,
    open_training_data,
    reduce_streaming,
)


@pytest.mark.parametrize('pod_method', ['randomized', 'gram'])
def test_streamed_dmdc_equals_in_memory_dmdc(tmp_path, pod_method):
    from soft_rom.learners.dmdc import DMDc
    eps, q_ref, y_ref = system_episodes(noise=1e-9)
    ts = training_set(tmp_path, eps, q_ref, y_ref)
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
    eps, q_ref, y_ref = system_episodes(ks=(200, 180))
    ts = training_set(tmp_path, eps, q_ref, y_ref)
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
    eps, q_ref, y_ref = system_episodes(ks=(400,))
    ts = training_set(tmp_path, eps, q_ref, y_ref)
    model = fit_streaming(ts, 'era', r=8, n_markov=40, decimation=1)
    ref = ERAOKID(r=8, n_markov=40, decimation=1).fit(
        Episode(t=eps[0].t, U=eps[0].U, Y=eps[0].Y), y_ref=y_ref).model_
    U_test = np.random.default_rng(3).standard_normal((M, 100))
    assert np.allclose(model.simulate(U_test), ref.simulate(U_test), rtol=0, atol=1e-10)


def test_lopinf_on_streamed_coordinates(tmp_path):
    lopinf = pytest.importorskip('soft_rom.learners.lopinf')
    eps, q_ref, y_ref = system_episodes()
    ts = training_set(tmp_path, eps, q_ref, y_ref)
    red = reduce_streaming(ts, r=6, n_coords=20)
    model = fit_reduced_model(red, 'lopinf', 6)
    ref = lopinf.LOpInf(r=6).fit(eps, q_ref=q_ref, y_ref=y_ref).model_
    for name in ('K', 'C', 'B', 'E'):
        a, b = getattr(model, name), getattr(ref, name)
        assert np.linalg.norm(a - b) <= 1e-6 * np.linalg.norm(b)

