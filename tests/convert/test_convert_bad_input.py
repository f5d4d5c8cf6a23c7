"""Bad input to the converter: each case either stops (nothing written) or continues and reports.

See the table in :mod:`soft_rom.convert`.
"""

from __future__ import annotations

import numpy as np
import pytest

from soft_rom.bags import BagTopics, EpisodeBagWriter
from soft_rom.convert import BagMapping, convert, read_episode
from soft_rom.errors import BagError

K = 12


def _t(j):
    return 0.001 * (j + 1)


def _write(path, storage='mcap', n_nodes=4, hook=None, topics=None, k=K):
    """Simulator-like bag; ``hook(w, j)`` may write sample ``j`` itself (returns True)."""
    with EpisodeBagWriter(path, storage=storage, n_nodes=None, topics=topics) as w:
        for j in range(k):
            if hook is not None and hook(w, j):
                continue
            w.write_pressures(_t(j), np.full(6, float(j)))
            w.write_centerline(_t(j), np.full((20, 3), float(j)))
            if n_nodes:
                w.write_state(_t(j), np.full((n_nodes, 3), float(j)))


def _nothing_left(tmp_path, out):
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith('.')]


# -- cases that stop ----------------------------------------------------------------------
def test_missing_topic_stops(tmp_path):
    bag = tmp_path / 'b'
    _write(bag, topics=BagTopics(centerline='/other/centerline'))
    out = tmp_path / 'o.zarr'
    with pytest.raises(BagError, match=r'output topic /soft_robot/centerline is missing'):
        convert([bag], out, progress=False)
    _nothing_left(tmp_path, out)
    with pytest.raises(BagError, match='no pressure topics'):
        read_episode(_no_pressure_bag(tmp_path))


def _no_pressure_bag(tmp_path):
    bag = tmp_path / 'np'
    with EpisodeBagWriter(bag, storage='mcap') as w:
        w.write_centerline(0.001, np.zeros((20, 3)))
    return bag


def test_wrong_message_type_stops(tmp_path):
    bag = tmp_path / 'b'
    # a Float64MultiArray published on the centerline topic
    _write(bag, n_nodes=4, topics=BagTopics(centerline='/cl', state='/soft_robot/centerline'))
    out = tmp_path / 'o.zarr'
    with pytest.raises(BagError, match=r'/soft_robot/centerline .* carries '
                                       r'std_msgs/msg/Float64MultiArray'):
        convert([bag], out, progress=False)
    _nothing_left(tmp_path, out)


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_truncated_or_corrupt_bag_stops_and_writes_nothing(tmp_path, storage):
    good, bad = tmp_path / 'good', tmp_path / 'bad'
    _write(good, storage)
    _write(bad, storage)
    data = next(p for p in bad.iterdir() if p.suffix in ('.mcap', '.db3'))
    raw = data.read_bytes()
    data.write_bytes(raw[:len(raw) // 2])               # the recorder was killed
    out = tmp_path / 'o.zarr'
    with pytest.raises(BagError, match=r'truncated or corrupt'):
        convert([good, bad], out, progress=False)       # the good bag was converted first
    _nothing_left(tmp_path, out)
    data.write_bytes(b'\x00garbage' * 100)
    with pytest.raises(BagError, match='bad'):
        read_episode(bad)


def test_empty_bag_stops(tmp_path):
    bag = tmp_path / 'empty'
    with EpisodeBagWriter(bag, storage='sqlite3'):
        pass
    with pytest.raises(BagError, match='empty'):
        convert([bag], tmp_path / 'o.zarr', progress=False)
    _nothing_left(tmp_path, tmp_path / 'o.zarr')


def test_missing_bag_path(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_episode(tmp_path / 'nope')


def test_a_folder_of_bags_gives_its_bags_in_natural_order(tmp_path):
    """``convert sim`` takes the bags of the folder ``soft-rom simulate -o sim`` wrote.

    ``sim`` holds ``ep1 … ep10`` and a JSON sidecar beside each: the bags come in natural
    order (ep2 before ep10), the sidecars are left out, and a sidecar given by a glob is
    refused with the advice to give the folder.
    """
    sim = tmp_path / 'sim'
    for name in ('ep10', 'ep2', 'ep1'):
        _write(sim / name, storage='sqlite3' if name == 'ep2' else 'mcap')
        (sim / f'{name}.json').write_text('{}')
    ts, reports = convert([sim], tmp_path / 'o.zarr', progress=False)
    assert ts.episode_names == ['ep1', 'ep2', 'ep10']
    assert [len(r.episodes) for r in reports] == [1, 1, 1]
    with pytest.raises(BagError, match=r'ep1\.json is not a ROS 2 bag .*convert every bag in '
                                       r'.*sim, give that folder'):
        convert([sim / 'ep1', sim / 'ep1.json'], tmp_path / 'p.zarr', progress=False)
    _nothing_left(tmp_path, tmp_path / 'p.zarr')


def test_all_outputs_too_short_stops(tmp_path):
    bag = tmp_path / 'b'

    def short(w, j):
        w.write_pressures(_t(j), np.zeros(6))
        w.write_centerline(_t(j), np.zeros((15, 3)))
        return True
    _write(bag, hook=short)
    mapping = BagMapping.from_dict({'output': {'n_points': 20}})
    with pytest.raises(BagError, match=r'(?s)no usable sample.*fewer than 20 points'):
        convert([bag], tmp_path / 'o.zarr', mapping, progress=False)
    _nothing_left(tmp_path, tmp_path / 'o.zarr')


def test_no_usable_sample_says_why_first(tmp_path):
    """The error leads with the topic and reason that emptied the bag, then the report."""
    bag = tmp_path / 'b'
    _write(bag)
    mapping = BagMapping.from_dict({'output': {'points': [25]}})   # the centerline has 20
    with pytest.raises(BagError) as err:
        convert([bag], tmp_path / 'o.zarr', mapping, progress=False)
    first = str(err.value).split('The whole report')[0]
    assert 'output /soft_robot/centerline: ' in first, first
    assert 'dropped (fewer than 26 points)' in first, first
    _nothing_left(tmp_path, tmp_path / 'o.zarr')


# -- cases that continue and report ---------------------------------------------------------
def test_nan_inf_dropped_and_reported(tmp_path):
    bag = tmp_path / 'b'

    def bad(w, j):
        if j == 3:      # NaN pressure: the previous value is held
            w.write_pressures(_t(j), [np.nan] + [3.0] * 5)
            w.write_centerline(_t(j), np.full((20, 3), 3.0))
            w.write_state(_t(j), np.full((4, 3), 3.0))
            return True
        if j == 5:      # Inf in the output: the sample is dropped
            w.write_pressures(_t(j), np.full(6, 5.0))
            w.write_centerline(_t(j), np.full((20, 3), np.inf))
            w.write_state(_t(j), np.full((4, 3), 5.0))
            return True
        if j == 7:      # NaN in the state: the sample is dropped
            w.write_pressures(_t(j), np.full(6, 7.0))
            w.write_centerline(_t(j), np.full((20, 3), 7.0))
            w.write_state(_t(j), np.full((4, 3), np.nan))
            return True
        return False
    _write(bag, hook=bad)
    ts, (rep,) = convert([bag], tmp_path / 'o.zarr', progress=False)
    ep = ts['b']
    # samples 5 and 7 are dropped; their grid points are interpolated from the neighbours
    # (one lost frame each), exactly here since the values are linear in j
    np.testing.assert_allclose(ep.t, 0.001 * np.arange(K), atol=1e-15)
    np.testing.assert_allclose(ep.Y[0], np.arange(K), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(ep.Q[0]), np.arange(K), rtol=1e-12)
    u0 = [2.0 if j == 3 else j for j in range(K)]       # chamber 1 held at t3
    np.testing.assert_array_equal(ep.U[0], u0)
    np.testing.assert_array_equal(ep.U[1], np.arange(K))
    r = rep.topics
    assert r['/soft_robot/pressure/chamber_1'].dropped == {'NaN/Inf': 1}
    assert r['/soft_robot/pressure/chamber_1'].held_over_gap == 1
    assert 'input /soft_robot/pressure/chamber_1 held over a gap at 1 grid point (longest ' \
        'hold 1 ms)' in rep.summary_line(), rep.summary_line()
    miss = 'no state message within 0.45 output periods'
    assert r['/soft_robot/centerline'].dropped == {'NaN/Inf': 1, miss: 1}
    assert r['/soft_robot/state'].dropped == {
        'NaN/Inf': 1, 'no output message within 0.45 output periods': 1}
    assert r['/soft_robot/centerline'].grid_gap_interpolated == 2
    assert r['/soft_robot/centerline'].grid_exact == K - 2
    assert 'NaN/Inf at stamp 6000000 ns (t = 0.005000 s)' in r['/soft_robot/centerline'].examples
    assert 'NaN/Inf at stamp 4000000 ns (t = 0.003000 s)' in \
        r['/soft_robot/pressure/chamber_1'].examples
    assert ts.metadata('b')['conversion_report']['topics']['/soft_robot/state']['dropped']


def test_inconsistent_length_dropped_and_reported(tmp_path):
    bag = tmp_path / 'b'

    def bad(w, j):
        if j == 4:
            w.write_pressures(_t(j), np.full(6, 4.0))
            w.write_centerline(_t(j), np.full((20, 3), 4.0))
            w.write_state(_t(j), np.full((3, 3), 4.0))   # 3 nodes instead of 4
            return True
        if j == 6:
            w.write_pressures(_t(j), np.full(6, 6.0))
            w.write_centerline(_t(j), np.full((19, 3), 6.0))   # one point short
            w.write_state(_t(j), np.full((4, 3), 6.0))
            return True
        return False
    _write(bag, hook=bad)
    ep, rep = read_episode(bag, include_state=True)
    np.testing.assert_allclose(ep.Y[5], np.arange(K), rtol=1e-12)   # 4 and 6 interpolated
    assert ep.Q.shape == (12, K)
    assert rep.topics['/soft_robot/state'].dropped['9 values instead of 12'] == 1
    assert rep.topics['/soft_robot/centerline'].dropped['fewer than 20 points'] == 1
    assert any('stamp 5000000 ns' in e for e in rep.topics['/soft_robot/state'].examples)
    assert 'fewer than 20 points' in rep.format() or '19 points' in rep.format()


def test_fewer_points_than_configured_dropped(tmp_path):
    bag = tmp_path / 'b'

    def bad(w, j):
        if j == 0:
            w.write_pressures(_t(j), np.zeros(6))
            w.write_centerline(_t(j), np.zeros((10, 3)))
            return True
        return False
    _write(bag, hook=bad, n_nodes=None)
    ep, rep = read_episode(bag, BagMapping.from_dict({'output': {'points': [0, 19]}}))
    assert ep.n_samples == K - 1 and ep.Y.shape == (4, K - 1)
    assert rep.topics['/soft_robot/centerline'].dropped == {'fewer than 20 points': 1}
    assert rep.topics['/soft_robot/centerline'].examples == [
        'fewer than 20 points at stamp 1000000 ns (t = 0.000000 s)']


def test_duplicated_and_backward_stamps_dropped(tmp_path):
    bag = tmp_path / 'b'

    def bad(w, j):
        if j in (5, 8):
            w.write_pressures(_t(j), np.full(6, float(j)))
            w.write_centerline(_t(j), np.full((20, 3), float(j)))
            # a second centerline message: same stamp (j=5) or stamp from the past (j=8)
            back = _t(j) if j == 5 else _t(2)
            w.write_centerline(back, np.full((20, 3), -1.0), log_time=_t(j) + 0.0002)
            return True
        return False
    _write(bag, hook=bad, n_nodes=None)
    ep, rep = read_episode(bag)
    np.testing.assert_array_equal(ep.Y[0], np.arange(K))
    assert rep.topics['/soft_robot/centerline'].dropped == {'duplicated stamp': 1,
                                                            'stamp going backwards': 1}
    assert rep.topics['/soft_robot/centerline'].read == K + 2
