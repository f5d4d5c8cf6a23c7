"""Tests of soft_rom.bags: the episode bag writer and the bag reader (both storages)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from soft_rom.bags import BagReader, BagTopics, describe_bag, EpisodeBagWriter, is_bag
from soft_rom.errors import BagError, DimensionError

STORAGES = ('mcap', 'sqlite3')


def _write(path, storage, k=6, n_nodes=5, **kw):
    rng = np.random.default_rng(1)
    t = 0.001 * np.arange(1, k + 1)
    P = rng.normal(size=(k, 6)) * 1e4
    C = rng.normal(size=(k, 20, 3))
    X = rng.normal(size=(k, n_nodes, 3))
    with EpisodeBagWriter(path, storage=storage, n_chambers=6, n_nodes=n_nodes, **kw) as w:
        for j in range(k):
            w.write(t[j], P[j], C[j], X[j])
    return t, P, C, X


@pytest.mark.parametrize('storage', STORAGES)
def test_contract_topics_types_and_values(tmp_path, storage):
    path = tmp_path / 'ep'
    t, P, C, X = _write(path, storage)
    info = describe_bag(path)
    assert info['storage'] == storage
    topics = info['topics']
    for i in range(1, 7):
        assert topics[f'/soft_robot/pressure/chamber_{i}'] == {
            'type': 'sensor_msgs/msg/FluidPressure', 'count': 6,
            'rate_hz': pytest.approx(1000.0, rel=1e-9)}
    assert topics['/soft_robot/centerline']['type'] == 'geometry_msgs/msg/PoseArray'
    assert topics['/soft_robot/state']['type'] == 'std_msgs/msg/Float64MultiArray'
    assert info['duration_s'] == pytest.approx(0.005, abs=1e-12)
    with BagReader(path) as bag:
        msgs = list(bag.messages(['/soft_robot/state', '/soft_robot/centerline',
                                  '/soft_robot/pressure/chamber_3']))
    state = [m for m in msgs if m.topic == '/soft_robot/state']
    cl = [m for m in msgs if m.topic == '/soft_robot/centerline']
    p3 = [m for m in msgs if m.topic.endswith('chamber_3')]
    assert len(state) == len(cl) == len(p3) == 6
    for j in range(6):
        ns = round(t[j] * 1e9)
        assert state[j].stamp_ns is None and state[j].log_ns == ns
        assert state[j].layout == (('nodes', 5), ('xyz', 3))
        np.testing.assert_array_equal(state[j].value.reshape(5, 3), X[j])
        assert cl[j].stamp_ns == ns == cl[j].log_ns
        np.testing.assert_array_equal(cl[j].value, C[j])
        assert p3[j].value[0] == P[j, 2] and p3[j].stamp_ns == ns


@pytest.mark.parametrize('state_type', ['float32', 'pointcloud2'])
def test_alternative_state_and_pressure_array(tmp_path, state_type):
    path = tmp_path / 'ep'
    t, P, C, X = _write(path, 'mcap', state_type=state_type, pressure_mode='array')
    info = describe_bag(path)
    assert '/soft_robot/pressures' in info['topics']
    assert not any('chamber' in k for k in info['topics'])
    with BagReader(path) as bag:
        st = list(bag.messages(['/soft_robot/state']))
        pr = list(bag.messages(['/soft_robot/pressures']))
    assert pr[0].msgtype == 'std_msgs/msg/Float64MultiArray' and pr[0].stamp_ns is None
    np.testing.assert_array_equal(pr[4].value, P[4])
    got = st[3].value.reshape(5, 3)
    np.testing.assert_array_equal(got, X[3].astype(np.float32).astype(np.float64))
    if state_type == 'pointcloud2':
        assert st[3].stamp_ns == round(t[3] * 1e9)


def _open_under(folder: Path) -> list[str]:
    """Files this process holds open under ``folder`` (``/proc/self/fd``: Linux)."""
    held = []
    for fd in Path('/proc/self/fd').iterdir():
        try:
            target = os.readlink(fd)
        except OSError:                 # closed meanwhile (the listing's own descriptor)
            continue
        if target.startswith(str(folder)):
            held.append(target)
    return held


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_failure_mid_write_leaves_no_bag(tmp_path, storage):
    path = tmp_path / 'ep'
    with pytest.raises(RuntimeError, match='boom'):
        with EpisodeBagWriter(path, storage=storage, n_chambers=6) as w:
            w.write(0.001, np.zeros(6), np.zeros((20, 3)))
            raise RuntimeError('boom')
    assert not path.exists()
    assert list(tmp_path.iterdir()) == []
    # and nothing of it left open (rosbags 0.11.0, the oldest allowed, has no
    # Writer.abort: its bag was deleted while still open)
    assert _open_under(tmp_path) == []


def test_bad_arguments_and_existing_path(tmp_path):
    path = tmp_path / 'ep'
    _write(path, 'sqlite3', k=2)
    with pytest.raises(BagError, match='exists already'):
        EpisodeBagWriter(path).open()
    with pytest.raises(BagError, match='storage'):
        EpisodeBagWriter(tmp_path / 'x', storage='bag')
    with EpisodeBagWriter(path, storage='mcap', overwrite=True, n_nodes=3) as w:
        with pytest.raises(DimensionError):
            w.write(0.001, np.zeros(5), np.zeros((20, 3)), np.zeros((3, 3)))
        with pytest.raises(DimensionError):
            w.write(0.001, np.zeros(6), np.zeros((20, 3)), None)
        w.write(0.001, np.zeros(6), np.zeros((20, 3)), np.zeros((3, 3)))
    assert describe_bag(path)['storage'] == 'mcap'
    assert is_bag(path) and not is_bag(tmp_path)


def test_custom_topics(tmp_path):
    topics = BagTopics(pressure_template='/p{i}', centerline='/cl', state='/x')
    with EpisodeBagWriter(tmp_path / 'b', storage='mcap', n_chambers=2, n_nodes=1,
                          topics=topics) as w:
        w.write(1.5, [1.0, 2.0], np.ones((3, 3)), np.ones((1, 3)))
    assert set(describe_bag(tmp_path / 'b')['topics']) == {'/p1', '/p2', '/cl', '/x'}


@pytest.mark.parametrize('frame_id', ['', 'w', 'world', 'abcdefg', 'abcdefgh'])
@pytest.mark.parametrize('n_points', [0, 1, 20])
def test_fast_cdr_parsers_match_rosbags(frame_id, n_points):
    from soft_rom.bags._cdr import _fast_fluid_pressure, _fast_pose_array, raw_frame_id
    from soft_rom.bags.reader import decode
    from soft_rom.bags.writer import typestore
    ts = typestore()
    T = ts.types
    header = T['std_msgs/msg/Header'](
        stamp=T['builtin_interfaces/msg/Time'](sec=1_700_000_000, nanosec=999_999_999),
        frame_id=frame_id)
    fp = T['sensor_msgs/msg/FluidPressure'](header=header, fluid_pressure=-1.25e5, variance=3.0)
    raw = bytes(ts.serialize_cdr(fp, 'sensor_msgs/msg/FluidPressure'))
    ref = decode('sensor_msgs/msg/FluidPressure',
                 ts.deserialize_cdr(raw, 'sensor_msgs/msg/FluidPressure'))
    got = _fast_fluid_pressure(raw)
    assert raw_frame_id(raw) == frame_id
    assert got[0] == ref[0] == 1_700_000_000_999_999_999
    np.testing.assert_array_equal(got[1], ref[1])
    pts = np.random.default_rng(n_points).normal(size=(n_points, 3))
    P, Pt = T['geometry_msgs/msg/Pose'], T['geometry_msgs/msg/Point']
    Q = T['geometry_msgs/msg/Quaternion']
    pa = T['geometry_msgs/msg/PoseArray'](header=header, poses=[
        P(position=Pt(x=a, y=b, z=c), orientation=Q(x=0.1, y=0.2, z=0.3, w=0.9))
        for a, b, c in pts])
    raw = bytes(ts.serialize_cdr(pa, 'geometry_msgs/msg/PoseArray'))
    got = _fast_pose_array(raw)
    assert raw_frame_id(raw) == frame_id
    assert got[0] == ref[0]
    np.testing.assert_array_equal(got[1], pts.reshape(-1, 3))
    assert _fast_pose_array(raw[:-8]) is None          # truncated: generic path decides
    assert _fast_fluid_pressure(b'\x00\x00' + raw[2:]) is None   # big-endian: generic path
