"""Bags as the outside world writes them (rosbags): clocks that jump, doubled topics, frames.

The bags are made the way the outside world makes them (``rosbags.rosbag2.Writer``), with
known values: chamber ``i`` reads ``1000 i + 100 t`` Pa at its stamp ``t`` (s from the start),
and the centerline's point ``k`` is at ``x = 0.01 k + 0.001 t``, ``z = 0.002 k t``.
"""

from __future__ import annotations

import copy
from pathlib import Path

from _bags import one_line_error
import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

from soft_rom.cli import main
from soft_rom.dataset import TrainingSet

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
T0 = 1_700_000_000_000_000_000
NP = 5
CH2 = '/soft_robot/pressure/chamber_2'


def _header(ns: int) -> object:
    stamp = T['builtin_interfaces/msg/Time'](sec=ns // 10**9, nanosec=ns % 10**9)
    return T['std_msgs/msg/Header'](stamp=stamp, frame_id='world')


def _fp(ns: int, v: float) -> object:
    return T['sensor_msgs/msg/FluidPressure'](header=_header(ns), fluid_pressure=v, variance=0.0)


def _centerline(ns: int, frame: str = 'world', dx: float = 0.0,
                true_ns: int | None = None) -> object:
    """Stamped ``ns``; the positions of the time ``true_ns`` (default ``ns``)."""
    t = ((ns if true_ns is None else true_ns) - T0) * 1e-9
    P, Pt = T['geometry_msgs/msg/Pose'], T['geometry_msgs/msg/Point']
    Q = T['geometry_msgs/msg/Quaternion']
    header = _header(ns)
    header.frame_id = frame
    return T['geometry_msgs/msg/PoseArray'](header=header, poses=[
        P(position=Pt(x=0.01 * k + 0.001 * t + dx, y=0.0, z=0.002 * k * t),
          orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0)) for k in range(NP)])


def _messages(dur: float, in_hz: int = 1000) -> list[tuple[int, str, str, object]]:
    """``(log_ns, topic, type, msg)``: 3 chambers at ``in_hz``, the centerline at 100 Hz."""
    msgs = []
    for i in (1, 2, 3):
        for j in range(int(dur * in_hz)):
            s = T0 + j * 10**9 // in_hz
            msgs.append((s + 200_000, f'/soft_robot/pressure/chamber_{i}',
                         'sensor_msgs/msg/FluidPressure', _fp(s, 1000.0 * i + 100.0 * j / in_hz)))
    for j in range(int(dur * 100)):
        s = T0 + j * 10**7
        msgs.append((s + 200_000, '/soft_robot/centerline', 'geometry_msgs/msg/PoseArray',
                     _centerline(s)))
    return msgs


def _write(path: Path, msgs: list[tuple[int, str, str, object]]) -> Path:
    w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    w.open()
    conns: dict[str, object] = {}
    for log_ns, topic, msgtype, msg in sorted(msgs, key=lambda m: m[0]):
        if topic not in conns:
            conns[topic] = w.add_connection(topic, msgtype, typestore=TS)
        w.write(conns[topic], log_ns, TS.serialize_cdr(msg, msgtype))
    w.close()
    return path


def _stamp(msg: object) -> int:
    st = msg.header.stamp  # type: ignore[attr-defined]
    return int(st.sec) * 10**9 + int(st.nanosec)


def _restamp(msgs, topic: str, after_ns: int, new) -> list:
    """Messages of ``topic`` stamped ``after_ns`` or later get the stamp ``new(stamp)``."""
    out = []
    for log_ns, tp, ty, msg in msgs:
        s = _stamp(msg)
        if tp == topic and s - T0 >= after_ns:
            msg = copy.deepcopy(msg)
            s = new(s)
            msg.header.stamp.sec, msg.header.stamp.nanosec = s // 10**9, s % 10**9
        out.append((log_ns, tp, ty, msg))
    return out


def _check_exact(out: Path) -> list[int]:
    """Every episode's U and Y equal the known values at its grid times; the lengths."""
    ts = TrainingSet.open(out)
    lengths = []
    for name in ts.episode_names:
        ep = ts[name]
        t = np.asarray(ep.t) + (ts.t0_ns(name) - T0) * 1e-9
        U = np.asarray(ep.U)
        want_u = np.array([1000.0 * i + 100.0 * t for i in (1, 2, 3)])
        np.testing.assert_allclose(U, want_u, atol=1e-6)
        x = 0.01 * np.arange(NP)[:, None] + 0.001 * t
        z = 0.002 * np.arange(NP)[:, None] * t
        np.testing.assert_allclose(np.asarray(ep.Y), np.vstack([x, z]), atol=1e-12)
        lengths.append(U.shape[1])
    return lengths


@pytest.mark.parametrize('new', [
    lambda s: s - T0 - 500_000_000,                   # restarted from zero
    lambda s: s - T0 - 500_000_000 + 1000 * 10**9,    # restarted on a boot clock
    lambda s: s + 3600 * 10**9,                       # set an hour ahead
], ids=['zero', 'boot', 'ahead'])
def test_a_chamber_whose_clock_restarts_mid_bag_is_refused(tmp_path, capsys, new):
    # chamber 2's clock jumps at 0.5 s; its later stamps were followed after 8 messages and
    # appended out of order to its timeline, so the zero-order hold searched an unsorted
    # array: chamber 2 read 2099.9 Pa from 0.02 s on (the whole episode wrong, exit 0)
    bag = _write(tmp_path / 'restart', _restamp(_messages(1.0), CH2, 500_000_000, new))
    out = tmp_path / 'out.zarr'
    assert main(['convert', str(bag), '-o', str(out), '--quiet']) == 2
    one_line_error(capsys, CH2, 'jumped', 'stamps: log')
    assert not out.exists()


@pytest.mark.parametrize('back_ms', [300, 20])
def test_a_chamber_clock_set_back_under_a_second_is_refused(tmp_path, capsys, back_ms):
    # an NTP-style step: chamber 2's clock goes back 0.3 s (or 20 ms) at 0.5 s, within the
    # 1 s stamp-to-log limit; its stamps before the newest were dropped, and once they passed
    # it again the chamber was followed shifted by the step to the end (30 Pa off, exit 0)
    bag = _write(tmp_path / 'back', _restamp(_messages(1.0), CH2, 500_000_000,
                                              lambda s: s - back_ms * 10**6))
    out = tmp_path / 'out.zarr'
    assert main(['convert', str(bag), '-o', str(out), '--quiet']) == 2
    one_line_error(capsys, CH2, 'stepped back by', 'stamps: log')
    assert not out.exists()


def test_messages_out_of_order_are_not_a_clock_step(tmp_path):
    # a few pressures delivered late (each after the next 5 of its topic) are dropped alone
    msgs = _messages(1.0)
    late = {(CH2, j) for j in range(100, 900, 100)}
    moved = [(log + (6 * 10**6 if (tp, (_stamp(m) - T0) // 10**6) in late else 0), tp, ty, m)
             for log, tp, ty, m in msgs]
    bag = _write(tmp_path / 'late', moved)
    out = tmp_path / 'out.zarr'
    assert main(['convert', str(bag), '-o', str(out), '--quiet']) == 0
    ts = TrainingSet.open(out)
    ep = ts[ts.episode_names[0]]
    t = np.asarray(ep.t) + (ts.t0_ns(ts.episode_names[0]) - T0) * 1e-9
    err = np.abs(np.asarray(ep.U)[1] - (2000.0 + 100.0 * t))
    assert np.sum(err > 1e-6) == len(late) and np.max(err) < 0.1 + 1e-6   # one 1 ms hold each


def test_one_stamp_glitched_ahead_is_not_a_clock_step(tmp_path):
    # one chamber-2 message stamped 50 ms ahead (its value of then): the 49 after it come
    # before it and are dropped and held, as before; the bag still converts
    bag = _write(tmp_path / 'glitch', _restamp(_messages(1.0), CH2, 500_000_000,
                                                lambda s: s + 50 * 10**6 if s - T0 < 500_500_000
                                                else s))
    out = tmp_path / 'out.zarr'
    assert main(['convert', str(bag), '-o', str(out), '--quiet']) == 0


def test_a_jump_of_the_recorders_clock_alone_is_still_followed(tmp_path):
    # the recorder's clock steps 5 s ahead at 3 s; the stamps stay continuous, so the
    # values after it are still right (8 outputs dropped before following: two pieces)
    msgs = [(log + (5 * 10**9 if _stamp(m) - T0 >= 3 * 10**9 else 0), tp, ty, m)
            for log, tp, ty, m in _messages(5.0, in_hz=100)]
    bag = _write(tmp_path / 'logjump', msgs)
    out = tmp_path / 'out.zarr'
    assert main(['convert', str(bag), '-o', str(out), '--quiet']) == 0
    assert sum(_check_exact(out)) > 450


@pytest.mark.parametrize('twice', [[CH2], [CH2, '/soft_robot/centerline']])
def test_a_topic_recorded_twice_converts_to_the_same_values(tmp_path, twice):
    # every message of the topic is in the bag twice (a merged or doubly recorded bag): the
    # probe saw half its stamps "not advancing" and refused the bag, advising log time,
    # whose times stand still just the same
    msgs = _messages(1.0)
    bag = _write(tmp_path / 'twice', msgs + [m for m in msgs if m[1] in twice])
    out = tmp_path / 'out.zarr'
    assert main(['convert', str(bag), '-o', str(out), '--quiet']) == 0
    assert _check_exact(out) == [100]
    report = TrainingSet.open(out).metadata('twice')['conversion_report']
    assert 'duplicated stamp' in str(report['topics'][CH2]['dropped'])


@pytest.mark.parametrize('fast', [True, False], ids=['cdr', 'generic'])
def test_centerline_in_another_frame_mid_bag_is_dropped_not_mixed(tmp_path, monkeypatch, fast):
    # the tracker's centerline switches from 'world' to 'camera' (1 m apart in x) at 0.5 s:
    # the frame was never read, so the second half went into Y 1 m off, exit 0
    if not fast:
        monkeypatch.setattr('soft_rom.bags.reader.FAST', {})
    msgs = [(log, tp, ty, _centerline(_stamp(m), 'camera', 1.0)
             if tp == '/soft_robot/centerline' and _stamp(m) - T0 >= 500_000_000 else m)
            for log, tp, ty, m in _messages(1.0)]
    bag = _write(tmp_path / 'frames', msgs)
    out = tmp_path / 'out.zarr'
    assert main(['convert', str(bag), '-o', str(out), '--quiet']) == 0
    assert _check_exact(out) == [50]
    dropped = TrainingSet.open(out).metadata('frames')['conversion_report']['topics'][
        '/soft_robot/centerline']['dropped']
    assert "frame_id 'camera' instead of 'world'" in str(dropped), dropped


def test_centerline_in_one_other_frame_throughout_converts(tmp_path):
    msgs = [(log, tp, ty, _centerline(_stamp(m), 'mocap') if tp == '/soft_robot/centerline'
             else m) for log, tp, ty, m in _messages(1.0)]
    out = tmp_path / 'out.zarr'
    assert main(['convert', str(_write(tmp_path / 'b', msgs)), '-o', str(out), '--quiet']) == 0
    assert _check_exact(out) == [100]



def test_a_camera_clock_seconds_off_is_said_and_log_time_realigns_it(tmp_path, capsys):
    # the tracker's machine is 2 s ahead (stamps = true time + 2 s, logged on time): samples
    # paired inputs with outputs 2 s apart, exit 0, said only as 'inputs held over a gap'
    msgs = [(log, tp, ty, _centerline(_stamp(m) + 2 * 10**9, true_ns=_stamp(m)))
            if tp == '/soft_robot/centerline' else (log, tp, ty, m)
            for log, tp, ty, m in _messages(3.0, in_hz=100)]
    bag = _write(tmp_path / 'apart', msgs)
    out = tmp_path / 'out.zarr'
    assert main(['convert', str(bag), '-o', str(out), '--quiet']) == 0
    err = capsys.readouterr().err
    assert '/soft_robot/centerline are +2 s from' in err and 'stamps: log' in err, err
    assert len(err.strip().splitlines()) == 1, err
    notes = TrainingSet.open(out).metadata('apart')['conversion_report']['notes']
    assert any('+2 s' in n for n in notes), notes
    mapping = tmp_path / 'log.yaml'
    mapping.write_text('time:\n  stamps: log\n')
    out2 = tmp_path / 'log.zarr'
    assert main(['convert', str(bag), '-o', str(out2), '--quiet', '--mapping', str(mapping)]) == 0
    assert capsys.readouterr().err == ''
    ts = TrainingSet.open(out2)
    ep = ts[ts.episode_names[0]]
    true = np.asarray(ep.t) + (ts.t0_ns(ts.episode_names[0]) - T0) * 1e-9 - 2e-4  # log latency
    assert ep.U.shape[1] == 300
    np.testing.assert_allclose(np.asarray(ep.U)[1], 2000.0 + 100.0 * true, atol=1e-6)
    np.testing.assert_allclose(np.asarray(ep.Y)[1], 0.01 + 0.001 * true, atol=1e-9)
