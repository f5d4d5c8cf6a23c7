"""Tests of soft_rom.convert: round trips, time alignment, alternative types, mapping options."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from soft_rom.bags import BagTopics, EpisodeBagWriter
from soft_rom.convert import BagMapping, convert, load_mapping, read_episode
from soft_rom.dataset import TrainingSet
from soft_rom.errors import ConfigError

CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'bag_mapping.yaml'


def _sim_bag(path, storage='mcap', k=40, n_nodes=9, seed=0, t0=0.001, **kw):
    """A bag as the simulator writes it; returns the source arrays."""
    rng = np.random.default_rng(seed)
    t = t0 + 0.001 * np.arange(k)
    P = rng.normal(size=(k, 6)) * 3e4
    C = rng.normal(size=(k, 20, 3))
    X = rng.normal(size=(k, n_nodes, 3)) if n_nodes else None
    with EpisodeBagWriter(path, storage=storage, n_chambers=6, n_nodes=n_nodes, **kw) as w:
        for j in range(k):
            w.write(t[j], P[j], C[j], None if X is None else X[j])
    return t, P, C, X


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_round_trip_bit_exact(tmp_path, storage):
    bag = tmp_path / 'ep1'
    t, P, C, X = _sim_bag(bag, storage)
    ts, reports = convert([bag], tmp_path / 'train.zarr', progress=False)
    assert ts.episode_names == ['ep1']
    assert ts.input_names == [f'p{i}' for i in range(1, 7)] and ts.input_units == ['Pa'] * 6
    assert ts.output_names[:2] == ['x1', 'x2'] and ts.output_names[20] == 'z1'
    assert len(ts.output_names) == 40 and ts.output_units == ['m'] * 40
    ep = ts['ep1']
    np.testing.assert_allclose(ep.t, t - t[0], rtol=0, atol=1e-15)     # from its own start
    assert ts.t0_ns('ep1') == 1_000_000 and ep.t[0] == 0.0
    np.testing.assert_array_equal(ep.U, P.T)                           # bit-exact
    np.testing.assert_array_equal(ep.Y[:20], C[:, :, 0].T)
    np.testing.assert_array_equal(ep.Y[20:], C[:, :, 2].T)
    np.testing.assert_array_equal(np.asarray(ep.Q[...]), X.reshape(len(t), -1).T)
    np.testing.assert_array_equal(ts.q_ref, X[0].reshape(-1))
    np.testing.assert_array_equal(ts.y_ref, ep.Y[:, 0])
    rep = reports[0]
    assert rep.storage == storage and rep.n_samples == len(t)
    assert all(not r.dropped for r in rep.topics.values())
    assert rep.topics['/soft_robot/state'].used == len(t)
    meta = ts.metadata('ep1')
    assert meta['source_bag'] == str(bag.resolve())
    assert meta['conversion_report']['topics']['/soft_robot/centerline']['read'] == len(t)
    assert ts.provenance['bags'] == [str(bag.resolve())]
    # read_episode gives the same arrays in memory
    ep2, _ = read_episode(bag, include_state=True)
    np.testing.assert_array_equal(ep2.U, ep.U)
    np.testing.assert_array_equal(ep2.Q, np.asarray(ep.Q[...]))
    assert ep2.metadata['output_names'] == ts.output_names


def test_inputs_on_other_rate_with_jitter_are_held(tmp_path):
    rng = np.random.default_rng(3)
    bag = tmp_path / 'jit'
    t_out = 0.010 + 0.001 * np.arange(200)
    t_in = 0.0095 + np.cumsum(rng.uniform(0.002, 0.005, size=80))    # ~290 Hz, jittered
    t_in = np.concatenate([[0.0095], t_in])
    t_in = t_in[t_in < t_out[-1] + 0.01]
    P = rng.normal(size=(t_in.size, 6))
    events = [(ti, 'p', j) for j, ti in enumerate(t_in)] + [(to, 'c', j)
                                                          for j, to in enumerate(t_out)]
    events.sort(key=lambda e: (e[0] + (0.0007 if e[1] == 'p' else 0.0), e[1]))
    C = rng.normal(size=(t_out.size, 20, 3))
    with EpisodeBagWriter(bag, storage='mcap', pressure_mode='array') as w:
        for ti, kind, j in events:
            if kind == 'p':   # array without header: timed by log time
                w.write_pressures(ti, P[j])
            else:             # header stamp t, logged 0.3 ms later (recorder latency)
                w.write_centerline(ti, C[j], log_time=ti + 0.0003)
    ep, rep = read_episode(bag)
    idx = np.searchsorted(t_in, t_out + 1e-12, side='right') - 1
    np.testing.assert_array_equal(ep.U, P[idx].T)
    np.testing.assert_array_equal(ep.Y[:20], C[:, :, 0].T)
    r_in = rep.topics['/soft_robot/pressures']
    assert r_in.read == t_in.size and not r_in.dropped
    assert 0.002 < r_in.period_s < 0.005 and r_in.jitter_s > 1e-4
    assert 0.002 < r_in.max_hold_s < 0.005
    assert rep.topics['/soft_robot/centerline'].period_s == pytest.approx(0.001, abs=1e-9)


@pytest.mark.parametrize('state_type', ['float32', 'pointcloud2'])
def test_float32_and_pointcloud_state_unstamped_float32_inputs(tmp_path, state_type):
    bag = tmp_path / 'sofa'
    t, P, C, X = _sim_bag(bag, 'sqlite3', k=25, state_type=state_type, pressure_mode='array',
                          pressure_array_type='float32')
    ts, rep = convert([bag], tmp_path / 'o.zarr', progress=False)
    ep = ts['sofa']
    assert rep[0].topics['/soft_robot/pressures'].msgtype == 'std_msgs/msg/Float32MultiArray'
    np.testing.assert_array_equal(ep.U, P.T.astype(np.float32).astype(np.float64))
    want = X.astype(np.float32).astype(np.float64).reshape(len(t), -1).T
    np.testing.assert_array_equal(np.asarray(ep.Q[...]), want)
    assert ts.q_array('sofa').dtype == np.float64


def test_mapping_selection_scale_offset_and_order(tmp_path):
    bag = tmp_path / 'm'
    t, P, C, X = _sim_bag(bag, 'mcap', k=12, n_nodes=None, pressure_mode='array')
    mapping = BagMapping.from_dict({
        'inputs': {'topic': '/soft_robot/pressures', 'slice': [2, 5], 'names': ['a', 'b', 'c'],
                   'units': 'kPa', 'scale': [1e-3, 1e-3, 2e-3], 'offset': -101.325},
        'output': {'points': [0, 9, 19], 'components': ['x', 'y', 'z'],
                   'order': 'point_major'},
    })
    ep, rep = read_episode(bag, mapping)
    scale = np.array([1e-3, 1e-3, 2e-3])[:, None]
    np.testing.assert_allclose(ep.U, scale * P[:, 2:5].T - 101.325, rtol=1e-15, atol=0)
    assert ep.metadata['input_names'] == ['a', 'b', 'c']
    assert ep.metadata['input_units'] == ['kPa'] * 3
    assert ep.metadata['output_names'][:4] == ['x1', 'y1', 'z1', 'x10']
    np.testing.assert_array_equal(ep.Y, C[:, [0, 9, 19], :].reshape(len(t), 9).T)
    assert ep.Q is None


def test_split_gap_and_resampling(tmp_path):
    bag = tmp_path / 'g'
    t = np.concatenate([0.001 * np.arange(1, 31), 1.0 + 0.002 * np.arange(20)])
    lin = lambda tt: np.stack([tt * (i + 1) for i in range(60)]).reshape(20, 3)  # noqa: E731
    with EpisodeBagWriter(bag, storage='mcap', n_nodes=4) as w:
        for tj in t:
            w.write(tj, np.full(6, tj), lin(tj), np.full((4, 3), 2.0 * tj))
    ts, rep = convert([bag], tmp_path / 'o.zarr', BagMapping(split_gap=0.1, dt=0.0005),
                      progress=False)
    assert ts.episode_names == ['g', 'g_2']
    a, b = ts['g'], ts['g_2']
    np.testing.assert_allclose(np.diff(a.t), 0.0005, atol=1e-12)
    np.testing.assert_allclose(np.diff(b.t), 0.0005, atol=1e-12)
    assert a.n_samples == 59 and b.n_samples == 77
    assert ts.t0_ns('g') == 1_000_000 and ts.t0_ns('g_2') == 1_000_000_000
    for ep in (a, b):     # Y and Q linear in time: interpolation is exact
        t_abs = ep.t + ep.metadata['t0_ns'] * 1e-9
        np.testing.assert_allclose(ep.Y[0], t_abs, rtol=1e-12)
        np.testing.assert_allclose(np.asarray(ep.Q[...])[2], 2 * t_abs, rtol=1e-12)
        src = t[np.searchsorted(t, t_abs + 1e-12, side='right') - 1]
        np.testing.assert_allclose(ep.U[0], src, rtol=1e-12)   # inputs held, not interpolated


def test_config_file_is_the_default_and_mapping_errors():
    assert load_mapping(CONFIG) == BagMapping() == load_mapping(None)
    for bad in ({'inputs': {'topics': 3}}, {'output': {'components': ['w']}},
                {'time': {'dt': -1}}, {'outputs': {}}, {'output': {'colour': 1}},
                {'inputs': {'topic': '/p', 'slice': [1]}}, {'time': {'stamps': 'x'}}):
        with pytest.raises(ConfigError):
            BagMapping.from_dict(bad)


def test_custom_topics_multiple_bags_and_no_state(tmp_path):
    topics = BagTopics(pressure_template='/pump/ch{i}', centerline='/mocap/cl')
    bags = []
    for i in range(2):
        bags.append(tmp_path / f'run{i}')
        _sim_bag(bags[-1], 'mcap', k=10, n_nodes=3, seed=i, topics=topics)
    mapping = BagMapping.from_dict({
        'inputs': {'topics': [f'/pump/ch{i}' for i in range(1, 7)]},
        'output': {'topic': '/mocap/cl'}, 'state': {'include': False}})
    ts, _ = convert(bags, tmp_path / 'o.zarr', mapping, progress=False)
    assert ts.episode_names == ['run0', 'run1'] and ts.q_ref is None
    assert all(ep.Q is None for ep in ts.episodes())
    assert isinstance(TrainingSet.open(tmp_path / 'o.zarr'), TrainingSet)


def test_short_pieces_between_long_gaps_are_dropped_so_every_learner_fits(tmp_path):
    bag = tmp_path / 'gappy'
    # 100 samples, a 50 ms hole, 10 samples, another hole, 60 samples (1 kHz)
    t = np.concatenate([0.001 * np.arange(100), 0.15 + 0.001 * np.arange(10),
                        0.3 + 0.001 * np.arange(60)])
    with EpisodeBagWriter(bag, storage='mcap', n_nodes=None) as w:
        for tj in t:
            w.write(tj + 0.001, np.full(6, tj), np.full((20, 3), tj))
    ts, (rep,) = convert([bag], tmp_path / 'o.zarr', progress=False)
    assert ts.episode_names == ['gappy', 'gappy_2']
    assert [ts[n].n_samples for n in ts.episode_names] == [100, 60]
    out = rep.topics['/soft_robot/centerline']
    assert out.splits == 2
    assert out.dropped == {'piece shorter than 32 grid points (between long gaps)': 10}
