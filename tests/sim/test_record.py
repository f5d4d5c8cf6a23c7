"""Recording episodes: bags read back by rosbags' AnyReader equal the simulation bit for bit."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from soft_rom.cli import main
from soft_rom.sim import EelModel, random_pressures
from soft_rom.sim.record import record_episode

AnyReader = pytest.importorskip('rosbags.highlevel').AnyReader
typesys = pytest.importorskip('rosbags.typesys')


def _read(path: Path) -> dict[str, list]:
    store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    out: dict[str, list] = {}
    with AnyReader([path], default_typestore=store) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, ts, raw in reader.messages():
            out.setdefault(conn.topic, []).append((ts, reader.deserialize(raw, conn.msgtype)))
    out['__types__'] = [types]
    return out


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_bag_round_trip_is_bit_exact(tmp_path: Path, storage: str) -> None:
    model = EelModel()
    k = 25
    side = record_episode(model, 2, tmp_path / 'ep2', seed=5, storage=storage, n_steps=k,
                          state=True)
    U = random_pressures(k, 1e-3, seed=5, episode=2, amplitude=50e3)
    ref = model.simulate(U, k, store_states=True)
    bag = _read(tmp_path / 'ep2')
    types = bag.pop('__types__')[0]
    assert types['/soft_robot/centerline'] == 'geometry_msgs/msg/PoseArray'
    assert types['/soft_robot/state'] == 'std_msgs/msg/Float64MultiArray'
    for c in range(6):
        topic = f'/soft_robot/pressure/chamber_{c + 1}'
        assert types[topic] == 'sensor_msgs/msg/FluidPressure'
        msgs = bag[topic]
        assert len(msgs) == k
        for j, (ts, msg) in enumerate(msgs):
            stamp = msg.header.stamp.sec * 10 ** 9 + msg.header.stamp.nanosec
            assert stamp == ts == round(ref.t[j] * 1e9)
            assert msg.fluid_pressure == U[c, j]          # bit-exact float64
    cl = bag['/soft_robot/centerline']
    assert len(cl) == k
    for j, (_, msg) in enumerate(cl):
        assert msg.header.frame_id == 'world'
        pts = np.array([[p.position.x, p.position.y, p.position.z] for p in msg.poses])
        np.testing.assert_array_equal(pts, ref.centerline[:, :, j])
    st = bag['/soft_robot/state']
    assert len(st) == k
    for j, (_, msg) in enumerate(st):
        assert [d.label for d in msg.layout.dim] == ['nodes', 'xyz']
        assert msg.layout.dim[0].size == model.n_nodes
        np.testing.assert_array_equal(np.asarray(msg.data).reshape(-1, 3), ref.states[:, :, j])
    assert side['n_dof'] == model.n_dof and side['storage'] == storage
    saved = json.loads((tmp_path / 'ep2.json').read_text())
    assert saved['seed'] == 5 and saved['episode'] == 2
    assert saved['simulator']['young_soft'] == model.config.young_soft


def test_cli_simulate_writes_one_bag_per_episode(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / 'bags'
    rc = main(['simulate', '--out', str(out), '--episodes', '2', '--steps', '5',
               '--storage', 'sqlite3', '--no-state', '--no-progress', '--seed', '3'])
    assert rc == 0
    text = capsys.readouterr().out
    assert '5,145 DOF' in text and '2 bag(s)' in text
    for e in (1, 2):
        assert (out / f'ep{e}' / 'metadata.yaml').exists()
        side = json.loads((out / f'ep{e}.json').read_text())
        assert side['episode'] == e and side['seed'] == 3 and not side['state_written']
        bag = _read(out / f'ep{e}')
        assert '/soft_robot/state' not in bag
        assert len(bag['/soft_robot/centerline']) == 5
    # an existing bag is not overwritten silently
    rc = main(['simulate', '--out', str(out), '--episodes', '1', '--steps', '5',
               '--no-state', '--no-progress'])
    assert rc == 2
