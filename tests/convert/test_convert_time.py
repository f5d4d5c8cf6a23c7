"""One time convention: epoch-stamped bags convert and fit exactly as bags stamped from zero."""

from __future__ import annotations

from pathlib import Path

from _rig import _header, _pose_array, T, T0_NS, write_messages
from _systems import spring_chain_episodes
import numpy as np

from soft_rom.cli import main
from soft_rom.dataset import TrainingSet
from soft_rom.models import load_model

DT_NS = 1_000_000
N_NODES = 4


def _state_bag(path: Path, ep, t0_ns: int, storage: str) -> None:
    """Pressures, centerline and a Float64MultiArray state at 1 kHz, stamps from ``t0_ns``."""
    FP = T['sensor_msgs/msg/FluidPressure']
    Arr = T['std_msgs/msg/Float64MultiArray']
    Dim = T['std_msgs/msg/MultiArrayDimension']
    layout = T['std_msgs/msg/MultiArrayLayout'](
        dim=[Dim(label='nodes', size=N_NODES, stride=3 * N_NODES),
             Dim(label='xyz', size=3, stride=3)], data_offset=0)
    n_pts = ep.Y.shape[0] // 2
    msgs = []
    for j in range(ep.n_samples):
        ns = t0_ns + j * DT_NS
        for i in range(ep.U.shape[0]):
            msgs.append((ns, f'/soft_robot/pressure/chamber_{i + 1}', FP.__msgtype__,
                         FP(header=_header(ns), fluid_pressure=float(ep.U[i, j]),
                            variance=0.0)))
        pts = np.stack([ep.Y[:n_pts, j], np.zeros(n_pts), ep.Y[n_pts:, j]], axis=1)
        msgs.append((ns, '/soft_robot/centerline', 'geometry_msgs/msg/PoseArray',
                     _pose_array(ns, pts)))
        msgs.append((ns, '/soft_robot/state', Arr.__msgtype__,
                     Arr(layout=layout, data=np.ascontiguousarray(ep.Q[:, j]))))
    write_messages(path, msgs, storage)


def test_epoch_stamped_bags_with_state_fit_like_zero_stamped(tmp_path, monkeypatch):
    storage = 'mcap'
    eps = spring_chain_episodes(n_dof=3 * N_NODES, m=2, p=6, k=1500, dt=1e-3, seed=4,
                                stiffness=400.0, drive_nodes=[3, 8], input_gain=1.0,
                                amplitude=1.0, hold=60, q_span=0.3, n_episodes=2)
    monkeypatch.chdir(tmp_path)
    models = {}
    for label, t0 in (('epoch', T0_NS), ('zero', 0)):
        bags = []
        for i, ep in enumerate(eps):
            bags.append(f'{label}{i + 1}')
            _state_bag(Path(bags[-1]), ep, t0 + i * 10 ** 10, storage)
        assert main(['convert', *bags, '-o', f'{label}.zarr', '--quiet']) == 0
        ts = TrainingSet.open(f'{label}.zarr')
        assert ts.t0_ns(f'{label}1') == t0 and ts.n_states == 3 * N_NODES
        for i, ep in enumerate(eps):
            got = ts[f'{label}{i + 1}']
            np.testing.assert_array_equal(got.t, (np.arange(ep.n_samples) * DT_NS) * 1e-9)
            assert got.is_uniform(rtol=1e-12)
            np.testing.assert_array_equal(got.U, ep.U)
            np.testing.assert_array_equal(np.asarray(got.Q[...]), ep.Q)
        assert main(['fit', f'{label}.zarr', '--method', 'lopinf,dmdc,era', '--r', '4',
                     '-o', f'm_{label}', '--no-progress']) == 0
        models[label] = {p.name.split('_', 1)[1]: load_model(p)
                         for p in Path(f'm_{label}').glob('*.npz')}
    assert sorted(models['epoch']) == ['dmdc_r4.npz', 'era_r4.npz', 'lopinf_r4.npz']
    test = eps[1]
    for name, a in models['epoch'].items():
        b = models['zero'][name]
        assert a.dt == b.dt
        assert a.metadata['training']['t0_ns']['epoch1'] == T0_NS
        ya, yb = a.simulate(test.U), b.simulate(test.U)
        scale = np.linalg.norm(yb - b.y_ref[:, None])
        assert np.linalg.norm(ya - yb) <= 1e-10 * scale, name
        for key in a._matrix_names:
            ma, mb = getattr(a, key), getattr(b, key)
            assert np.max(np.abs(ma - mb)) <= 1e-10 * max(np.max(np.abs(mb)), 1e-300), \
                (name, key)
