"""Reduce once, then fit: the streaming reducer against the in-memory one, same learners."""

from __future__ import annotations

from _scale_data import M, system_episodes, training_set
from _systems import spring_chain_episodes
import numpy as np
import pytest

from soft_rom.data import Episode
from soft_rom.learners import DMDc, ERAOKID, LOpInf
from soft_rom.pipeline import fit_models, open_training_data
from soft_rom.reduce import InMemoryPOD, StreamingReducer


def _fit(ts, learner, r, reducer, **kw):
    return fit_models(open_training_data(ts, **kw), learner, (r,), reducer)[0].model


@pytest.mark.parametrize('pod_method', ['randomized', 'gram'])
def test_streamed_dmdc_equals_in_memory_dmdc(tmp_path, pod_method):
    eps, q_ref, y_ref = system_episodes(noise=1e-9)
    ts = training_set(tmp_path, eps, q_ref, y_ref)
    U_test = np.random.default_rng(7).standard_normal((M, 200))
    for r, p in ((8, None), (6, 8)):
        ref = DMDc(r=r, p=p).fit(eps, q_ref=q_ref, y_ref=y_ref).model_
        model = _fit(ts, DMDc(p=p), r, StreamingReducer(method=pod_method, n_coords=20))
        Y1, Y2 = ref.simulate(U_test), model.simulate(U_test)
        dev = np.linalg.norm(Y1 - y_ref[:, None])
        assert np.linalg.norm(Y1 - Y2) / dev < 1e-10
        assert np.allclose(np.sort_complex(np.linalg.eigvals(model.A)),
                           np.sort_complex(np.linalg.eigvals(ref.A)), atol=1e-10)
        assert model.metadata['scale']['pod_method'] == pod_method
        assert model.output_names == ts.output_names


def test_t_max_stays_lazy_and_matches_sliced_fit(tmp_path):
    eps, q_ref, y_ref = system_episodes(ks=(200, 180))
    ts = training_set(tmp_path, eps, q_ref, y_ref)
    td = open_training_data(ts, t_max=1.2)
    assert [ep.n_samples for ep in td.episodes] == [120, 120]
    assert not isinstance(td.episodes[0].Q, np.ndarray)
    model = _fit(ts, DMDc(), 8, StreamingReducer(method='randomized', n_coords=20), t_max=1.2)
    ref = DMDc(r=8).fit([ep.slice(0, 120) for ep in eps], q_ref=q_ref, y_ref=y_ref).model_
    U_test = np.random.default_rng(2).standard_normal((M, 100))
    Y1 = ref.simulate(U_test)
    assert np.linalg.norm(Y1 - model.simulate(U_test)) / np.linalg.norm(
        Y1 - y_ref[:, None]) < 1e-10


def test_era_needs_no_snapshots_and_equals_direct_fit(tmp_path):
    eps, q_ref, y_ref = system_episodes(ks=(400,))
    ts = training_set(tmp_path, eps, q_ref, y_ref)
    model = _fit(ts, ERAOKID(n_markov=40, decimation=1), 8, StreamingReducer())
    assert 'scale' not in model.metadata          # nothing was streamed
    ref = ERAOKID(r=8, n_markov=40, decimation=1).fit(
        Episode(t=eps[0].t, U=eps[0].U, Y=eps[0].Y), y_ref=y_ref).model_
    U_test = np.random.default_rng(3).standard_normal((M, 100))
    assert np.allclose(model.simulate(U_test), ref.simulate(U_test), rtol=0, atol=1e-10)


@pytest.mark.parametrize('learner', [
    LOpInf(), LOpInf(mass='learned', min_damping_ratio=0.0),
    LOpInf(forces='cubic', cubic_options={'reg': 1e-3, 'eps4': 1e-2})],
    ids=['linear', 'mass', 'cubic'])
def test_streamed_lopinf_equals_in_memory(tmp_path, learner):
    # The exact (Gram) streamed POD gives the in-memory coordinates to rounding: every
    # LOpInf variant then fits the same model on either (a mechanical system: a chain of
    # springs and dampers, 30 DOF, driven at two nodes).
    eps = spring_chain_episodes(n_dof=30, m=2, p=4, k=600, dt=1e-2, seed=3, stiffness=50.0,
                                drive_nodes=(10, 20), input_gain=1.0, amplitude=1.0, hold=20,
                                q_span=1.0)
    q_ref, y_ref = eps[0].Q[:, 0], eps[0].Y[:, 0]
    ts = training_set(tmp_path, eps, q_ref, y_ref)
    r = 4 if learner.forces == 'cubic' else 6
    mem = _fit(ts, learner, r, InMemoryPOD())
    streamed = _fit(ts, learner, r, StreamingReducer(method='gram'))
    assert streamed.metadata['scale']['pod_method'] == 'gram'
    Y1, Y2 = mem.simulate(eps[1].U), streamed.simulate(eps[1].U)
    assert np.linalg.norm(Y1 - Y2) <= 1e-10 * np.linalg.norm(Y1 - y_ref[:, None])


def test_refinement_runs_on_streamed_coordinates(tmp_path):
    # The output-error refinement is a nonlinear least-squares search: on streamed
    # coordinates it runs as in memory and reaches the same training error (its minimizer
    # is not unique to rounding on these exact data, so the operators are not compared).
    from soft_rom.evaluation import evaluate
    eps, q_ref, y_ref = system_episodes(noise=1e-6)
    ts = training_set(tmp_path, eps, q_ref, y_ref)
    errs = []
    for reducer in (InMemoryPOD(), StreamingReducer(method='randomized', n_coords=20)):
        model = _fit(ts, LOpInf(refine='output-error'), 6, reducer)
        assert model.metadata['diagnostics']['refinement']['criterion'] == 'output-error'
        assert model.stability_margin() > 0
        errs.append(evaluate(model, eps).get()['relative_deviation_error'])
    assert errs[1] <= 1.1 * errs[0] + 1e-6


@pytest.mark.parametrize('method', ['lopinf', 'dmdc', 'era'])
def test_a_streamed_study_streams_its_held_out_refits_too(tmp_path, monkeypatch, method):
    # The paper-scale study 2 (cfg.streaming) records each model's held-out error by
    # refitting it on each training episode left out (ERA/OKID: on the first 80 % of its
    # one episode). Those refits loaded the snapshots into memory (24 GB at resolution 4,
    # killed by the kernel): they must stream as the fit does, and ERA/OKID read no state.
    from soft_rom.basis import POD
    from soft_rom.dataset import StoredArray
    from soft_rom.study.config import StudyConfig
    from soft_rom.study.fits import _record_held_out, sweep

    eps = spring_chain_episodes(n_dof=30, m=2, p=4, k=300, dt=1e-2, seed=5, stiffness=50.0,
                                drive_nodes=(10, 20), input_gain=1.0, amplitude=1.0, hold=20,
                                q_span=1.0)
    eps = [Episode(t=e.t, U=e.U, Y=e.Y, Q=e.Q, name=f'ep{i + 1}') for i, e in enumerate(eps)]
    ts = training_set(tmp_path, eps, eps[0].Q[:, 0], eps[0].Y[:, 0], chunks=(16, 32))
    stored = [ts[e.name] for e in eps[:2]]
    assert isinstance(stored[0].Q, StoredArray)             # lazy, as at paper scale

    def in_memory_svd(*args, **kw):
        raise AssertionError('the snapshots were loaded for an in-memory SVD')

    monkeypatch.setattr(POD, 'fit', in_memory_svd)
    era = {'n_markov': 40, 'decimation': 1}
    cfg = StudyConfig(streaming=True, r_cubic=(), era_options=era)
    chosen = {'r': 4, 'episode': 'ep1'} if method == 'era' else {'r': 4}
    train = stored[:1] if method == 'era' else stored
    model = sweep(method, [4], train, ts, streaming=True, era_options=era)[4]
    if method == 'era':
        read = StoredArray.__getitem__

        def one_column_at_most(self, key):          # a reference state, not the snapshots
            got = read(self, key)
            assert got.ndim < 2 or got.shape[1] <= 1, f'ERA/OKID read the states {key}'
            return got
        monkeypatch.setattr(StoredArray, '__getitem__', one_column_at_most)
    _record_held_out(method, model, chosen, stored, ts, cfg)
    held = model.metadata['held_out']                       # recorded, by streamed refits
    assert held['samples'] > 0 and 0 < held['deviation_error'] < 1


def test_study_1_training_head_keeps_a_stored_q_on_disk(tmp_path):
    # Study 1 fits on the head of Ep 1. Episode.time_slice read a stored Q into memory
    # (3 GB at resolution 4, peak RSS 4.17 GB for a stage whose fits stream): _head keeps
    # it on disk and gives the same samples.
    from soft_rom.reduce import ColumnWindow
    from soft_rom.study.fits import _head

    eps, q_ref, y_ref = system_episodes(ks=(200,))
    ts = training_set(tmp_path, eps, q_ref, y_ref, chunks=(16, 32))
    stored = ts[ts.episode_names[0]]
    head, want = _head(stored, 1.2), eps[0].time_slice(None, 1.2)
    assert isinstance(head.Q, ColumnWindow) and head.Q.shape == want.Q.shape
    for key in ('t', 'U', 'Y'):
        np.testing.assert_array_equal(getattr(head, key), getattr(want, key))
    np.testing.assert_array_equal(head.Q[:, 0:head.n_samples], want.Q)
    in_memory = eps[0]                              # an array is sliced as before
    np.testing.assert_array_equal(_head(in_memory, 1.2).Q, want.Q)
