"""``soft-rom replay``: the node's topics written offline, equal to the model's simulation."""

from __future__ import annotations

from collections import Counter
import json

from _bags import N_POINTS, small_episode, small_model, write_input_bag
import numpy as np
import pytest

from soft_rom.bags.replay_io import read_messages, replay_to_bag
from soft_rom.data import Episode
from soft_rom.errors import BagError
from soft_rom.models import file_sha256, SecondOrderModel
from soft_rom.predictor import Predictor, PredictorConfig
from soft_rom.predictor.conversions import data_to_array, outputs_to_points, poses_to_points

NODE = '/soft_rom_predictor'
_model, _episode = small_model, small_episode


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_replay_bag_has_node_topics_and_exact_predictions(tmp_path, storage: str) -> None:
    model = _model()
    path = model.save(tmp_path / 'm.npz')
    ep = _episode(model)
    out = tmp_path / 'out'
    res = replay_to_bag(Predictor(path), ep, out, storage=storage, publish_every=4,
                        centerline_rate_hz=0.0,
                        diagnostics_period=0.05)
    assert res.summary['relative_error'] <= 1e-12
    msgs = list(read_messages(out))
    count = Counter(topic for topic, _, _ in msgs)
    k_pub = len(range(0, ep.n_samples, 4))
    assert count[f'{NODE}/centerline'] == k_pub
    assert count[f'{NODE}/output'] == k_pub
    assert count[f'{NODE}/centerline_marker'] == 2 * k_pub     # predicted + measured
    assert count[f'{NODE}/error'] == k_pub
    assert count[f'{NODE}/model_info'] == 1
    assert count['/diagnostics'] == 3                           # t = 2.0, 2.05, 2.1
    outputs = np.array([data_to_array(m.data) for tp, _, m in msgs if tp == f'{NODE}/output'])
    np.testing.assert_allclose(outputs.T, ep.Y[:, ::4], rtol=0, atol=1e-12)
    first = next(m for tp, _, m in msgs if tp == f'{NODE}/centerline')
    assert first.header.frame_id == 'world'
    assert first.header.stamp.sec == 2 and first.header.stamp.nanosec == 0
    np.testing.assert_allclose(poses_to_points(first.poses),
                               outputs_to_points(ep.Y[:, 0], 'xz'), atol=1e-12)
    markers = [m for tp, _, m in msgs if tp == f'{NODE}/centerline_marker']
    assert {m.ns for m in markers} == {'predicted', 'measured'}
    assert all(m.type == 4 and len(m.points) == N_POINTS for m in markers)
    info = json.loads(next(m.data for tp, _, m in msgs if tp == f'{NODE}/model_info'))
    assert info['r'] == 4 and info['method'] == 'lopinf'
    assert info['sha256'] == file_sha256(path)
    diags = [m.status[0] for tp, _, m in msgs if tp == '/diagnostics']
    keys = {kv.key for kv in diags[0].values}
    assert {'error_deviation', 'nonfinite', 'backwards', 'wrong_length'} <= keys
    rate = float(dict((kv.key, kv.value) for kv in diags[1].values)['input_rate_hz'])
    assert rate == pytest.approx(1000.0, rel=0.03)                # one input per 1 ms
    errors = [m.data for tp, _, m in msgs if tp == f'{NODE}/error']
    assert max(errors) <= 1e-10


def test_replay_refuses_existing_output(tmp_path) -> None:
    model = _model()
    out = tmp_path / 'out'
    out.mkdir()
    with pytest.raises(FileExistsError):
        replay_to_bag(Predictor(model), _episode(model), out)
    with pytest.raises(BagError):
        replay_to_bag(Predictor(model), _episode(model), tmp_path / 'x', storage='rosbag1')


def test_input_bag_round_trip(tmp_path) -> None:
    model = _model()
    ep = _episode(model, k=20)
    bag = write_input_bag(tmp_path / 'in', ep, storage='sqlite3')
    count = Counter(tp for tp, _, _ in read_messages(bag))
    assert count['/soft_robot/pressure/chamber_1'] == 20
    assert count['/soft_robot/centerline'] == 20
    pressures = [m.fluid_pressure for tp, _, m in read_messages(
        bag, ['/soft_robot/pressure/chamber_2'])]
    np.testing.assert_array_equal(pressures, ep.U[1])


def test_cli_replay_end_to_end(tmp_path, capsys) -> None:
    convert = pytest.importorskip('soft_rom.convert')
    if not hasattr(convert, 'read_episode'):
        pytest.skip('soft_rom.convert.read_episode not available yet')
    from soft_rom.cli import main

    model = _model()
    path = model.save(tmp_path / 'm.npz')
    ep = _episode(model)
    bag = write_input_bag(tmp_path / 'in', ep, storage='mcap')
    out = tmp_path / 'pred'
    summary = tmp_path / 's.json'
    code = main(['replay', str(path), str(bag), '-o', str(out), '--publish-rate', '0',
                 '--summary-json', str(summary), '--components', 'xz'])
    assert code == 0
    text = capsys.readouterr().out
    assert 'relative deviation error' in text
    data = json.loads(summary.read_text())
    assert data['samples'] == ep.n_samples
    assert data['relative_error'] <= 1e-9
    outputs = np.array([data_to_array(m.data)
                        for _, _, m in read_messages(out, [f'{NODE}/output'])])
    np.testing.assert_allclose(outputs.T, ep.Y, atol=1e-9)


def test_kalman_option_reaches_the_core(tmp_path) -> None:
    model = _model()
    res = replay_to_bag(Predictor(model, PredictorConfig(kalman=True)), _episode(model),
                        tmp_path / 'k', storage='sqlite3')
    assert res.summary['config']['kalman'] is True
    assert res.summary['relative_error'] <= 1e-9       # exact model: nothing to correct


def test_cli_replay_with_params_file_and_kalman_comparison(tmp_path, capsys) -> None:
    convert = pytest.importorskip('soft_rom.convert')
    if not hasattr(convert, 'read_episode'):
        pytest.skip('soft_rom.convert.read_episode not available yet')
    from soft_rom.cli import main

    true = _model()
    wrong = SecondOrderModel(true.K * 1.3, true.C, true.B * 1.2, true.E, dt=true.dt,
                             y_ref=true.y_ref)
    path = wrong.save(tmp_path / 'wrong.npz')
    bag = write_input_bag(tmp_path / 'in', _episode(true, k=300), storage='sqlite3')
    params = tmp_path / 'p.yaml'
    params.write_text('soft_rom_predictor:\n  ros__parameters:\n    publish_rate_hz: 100.0\n'
                      '    measurement_noise: 1.0e-8\n')
    summary = tmp_path / 's.json'
    code = main(['replay', str(path), str(bag), '-o', str(tmp_path / 'pred'), '--config',
                 str(params), '--kalman', '--compare', '--summary-json', str(summary)])
    assert code == 0
    assert 'Kalman' in capsys.readouterr().out
    data = json.loads(summary.read_text())
    assert data['config']['kalman'] is True and data['config']['measurement_noise'] == 1e-8
    assert data['compare']['kalman'] <= 0.5 * data['compare']['open_loop']
    count = Counter(tp for tp, _, _ in read_messages(tmp_path / 'pred'))
    assert count[f'{NODE}/output'] == 30                     # 100 Hz from 1 kHz
    assert count[f'{NODE}/centerline'] == 10                 # 30 Hz default: every 33 steps
    assert main(['replay', str(tmp_path / 'nope.npz'), str(bag), '-o',
                 str(tmp_path / 'x')]) == 2


def test_cdr_templates_equal_direct_serialization() -> None:
    from soft_rom.bags import prediction_writer as rio

    rng = np.random.default_rng(3)
    with_writer = rio.PredictionBagWriter.__new__(rio.PredictionBagWriter)
    with_writer.frame_id, with_writer._templates = 'world', {}
    with_writer.topics = {'centerline': (None, 'geometry_msgs/msg/PoseArray'),
                          'marker': (None, 'visualization_msgs/msg/Marker'),
                          'output': (None, 'std_msgs/msg/Float64MultiArray')}
    for n in (1, 7, 20):
        for t in (0.0, 12.345678901, 1.7e9 + 0.5):
            pts = rng.standard_normal((n, 3))
            direct = rio._TS.serialize_cdr(rio._pose_array(t, 'world', pts),
                                           'geometry_msgs/msg/PoseArray')
            assert with_writer._template('centerline', n).render(t, pts) == bytes(direct)
            ns, mid, rgba, width = rio._MARKERS['measured']
            direct = rio._TS.serialize_cdr(rio._marker(t, 'world', pts, ns, mid, rgba, width),
                                           'visualization_msgs/msg/Marker')
            tpl = with_writer._template('measured', n).render(t, pts)
            # the texture header keeps the template's zero stamp; everything else is equal
            msg = rio._TS.deserialize_cdr(tpl, 'visualization_msgs/msg/Marker')
            ref = rio._TS.deserialize_cdr(bytes(direct), 'visualization_msgs/msg/Marker')
            assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (
                ref.header.stamp.sec, ref.header.stamp.nanosec)
            assert [(p.x, p.y, p.z) for p in msg.points] == [(p.x, p.y, p.z)
                                                              for p in ref.points]
            assert (msg.ns, msg.id, msg.type, msg.scale.x) == (ns, mid, 4, width)
            y = rng.standard_normal(2 * n)
            direct = rio._TS.serialize_cdr(rio._float64_array(y, 'outputs'),
                                           'std_msgs/msg/Float64MultiArray')
            assert with_writer._template('output', 2 * n).render(t, y.reshape(-1, 1)) == bytes(
                direct)


@pytest.mark.parametrize('stepping', ['event', 'fixed', 'input'])
def test_stream_replay_feeds_messages_like_the_node(tmp_path, stepping: str) -> None:
    from soft_rom.bags.replay_io import replay_stream_to_bag

    model = _model()
    ep = _episode(model, k=100)
    topics = [f'/soft_robot/pressure/chamber_{i + 1}' for i in range(3)]
    bag = write_input_bag(tmp_path / 'in', ep, storage='mcap', chamber_topics=topics)
    out = tmp_path / 'pred'
    summary = replay_stream_to_bag(Predictor(model, PredictorConfig(stepping=stepping)), bag,
                                   out, input_topics=topics, publish_rate_hz=250.0,
                                   diagnostics_period=0.05)
    assert summary['messages'] == {'inputs': 300, 'measured': 100, 'published': 25}
    assert summary['relative_error'] <= 1e-12
    assert summary['counters']['late'] == 0 and summary['counters']['backwards'] == 0
    got = [(t, data_to_array(m.data)) for _, t, m in read_messages(out, [f'{NODE}/output'])]
    assert len(got) == 25
    for t, y in got:                    # every 4th step, stamped with its model time
        j = int(round((t - ep.t[0]) / model.dt))
        assert j % 4 == 0
        np.testing.assert_allclose(y, ep.Y[:, j], atol=1e-12)
    # centerline and markers at their own rate (30 Hz default: every 33 steps of 1 ms)
    count = Counter(tp for tp, _, _ in read_messages(out))
    assert count[f'{NODE}/centerline'] == 4


def test_stream_replay_across_a_restarted_sensor_clock_resets_and_stays_exact(tmp_path) -> None:
    # the robot restarts mid-bag: its stamps go back 3 s (the recorder's log time runs on)
    # and its body starts again from rest; the node's core resets once (clock_reset) and
    # predicts the second run from rest at the new stamps, exactly as before the restart
    from soft_rom.bags.replay_io import replay_stream_to_bag

    model, k = _model(), 100
    rng = np.random.default_rng(3)
    U = np.repeat(rng.standard_normal((model.n_inputs, 2 * k // 10)), 10, axis=1)
    Y = np.hstack([model.simulate(U[:, :k]), model.simulate(U[:, k:])])
    ep = Episode(t=2.0 + np.arange(2 * k) * model.dt, U=U, Y=Y, name='ep')
    topics = [f'/soft_robot/pressure/chamber_{i + 1}' for i in range(3)]
    bag = write_input_bag(tmp_path / 'in', ep, chamber_topics=topics, t0_ns=10 * 10**9,
                          restamp=lambda j, ns: ns - (3 * 10**9 if j >= k else 0))
    out = tmp_path / 'pred'
    summary = replay_stream_to_bag(Predictor(model), bag, out, input_topics=topics,
                                   publish_rate_hz=0.0)
    assert summary['counters']['clock_reset'] == 1, summary['counters']
    assert summary['relative_error'] <= 1e-12, summary
    got = [(t, data_to_array(m.data)) for _, t, m in read_messages(out, [f'{NODE}/output'])]
    # every step published once, at its stamp: 12.000-12.099 s, then 9.100-9.199 s
    runs = {round((t - 12.0) * 1e3) if t >= 12.0 else round((t - 9.0) * 1e3) for t, _ in got}
    assert len(got) == 2 * k and runs == set(range(2 * k)), sorted(t for t, _ in got)
    for t, y in got:
        j = round((t - 12.0) * 1e3) if t >= 12.0 else round((t - 9.0) * 1e3)
        np.testing.assert_allclose(y, Y[:, j], atol=1e-12)


def test_cli_replay_stream(tmp_path, capsys) -> None:
    from soft_rom.cli import main

    model = _model()
    path = model.save(tmp_path / 'm.npz')
    ep = _episode(model, k=60)
    bag = write_input_bag(tmp_path / 'in', ep, storage='sqlite3', per_chamber=False)
    params = tmp_path / 'p.yaml'
    params.write_text("soft_rom_predictor:\n  ros__parameters:\n    input_mode: 'array'\n"
                      "    publish_rate_hz: 0.0\n")
    summary = tmp_path / 's.json'
    assert main(['replay', str(path), str(bag), '-o', str(tmp_path / 'pred'), '--stream',
                 '--config', str(params), '--summary-json', str(summary)]) == 0
    assert 'relative deviation error' in capsys.readouterr().out
    data = json.loads(summary.read_text())
    assert data['messages']['inputs'] == 60 and data['messages']['measured'] == 60
    assert data['relative_error'] <= 1e-12


def test_bags_do_not_import_the_ros_package() -> None:
    import ast
    from pathlib import Path

    import soft_rom.bags

    for path in Path(soft_rom.bags.__file__).parent.glob('*.py'):
        tree = ast.parse(path.read_text(encoding='utf-8'))
        names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
        names += [n.module or '' for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
        assert not [n for n in names if n.startswith('soft_rom.ros')], path.name


def test_replay_stamps_at_the_recordings_epoch_start(tmp_path) -> None:
    model = _model()
    ep = _episode(model, k=50)
    t0_ns = 1_700_000_000_123_456_789
    ep = Episode(t=ep.t - ep.t[0], U=ep.U, Y=ep.Y, name='ep', metadata={'t0_ns': t0_ns})
    res = replay_to_bag(Predictor(model), ep, tmp_path / 'o', storage='mcap')
    assert res.summary['relative_error'] <= 1e-12
    stamps = []
    for _, _, m in read_messages(tmp_path / 'o', [f'{NODE}/centerline']):
        stamps.append(m.header.stamp.sec * 10 ** 9 + m.header.stamp.nanosec)
    assert stamps[0] == t0_ns and stamps[1] == t0_ns + 33 * 1_000_000    # exact int ns


def test_stream_replay_of_topics_the_bag_lacks_reads_nothing(tmp_path) -> None:
    """An empty topic selection is not "every topic" (rosbags reads every message for none).

    The stream replay of topics the bag does not have feeds no message.
    """
    from soft_rom.bags.replay_io import read_messages_ns, replay_stream_to_bag

    model = _model()
    ep = _episode(model, k=60)
    bag = write_input_bag(tmp_path / 'in', ep, storage='sqlite3')
    assert list(read_messages_ns(bag, ['/not/in/the/bag'])) == []
    assert len(list(read_messages_ns(bag))) == sum(1 for _ in read_messages_ns(
        bag, list({tp for tp, _, _ in read_messages_ns(bag)})))
    summary = replay_stream_to_bag(Predictor(model), bag, tmp_path / 'pred',
                                   input_topics=[f'/rig/valve{i}' for i in range(3)],
                                   measured_topic='/mocap/spine')
    assert summary['messages'] == {'inputs': 0, 'measured': 0, 'published': 0}
    with pytest.raises(FileNotFoundError, match='does not exist'):
        list(read_messages_ns(tmp_path / 'missing'))


def test_cli_replay_keeps_every_input_when_the_outputs_are_slower(tmp_path, capsys) -> None:
    """A camera at 100 Hz beside pressures at 1 kHz: every input reaches the prediction.

    Found by an audit: the converted grid was the outputs' (10 ms), so 9 of 10 input samples
    were lost (30 samples replayed); the replay now converts on the model's step.
    """
    from soft_rom.cli import main

    model = small_model()
    rng = np.random.default_rng(3)
    k = 300
    U = rng.standard_normal((model.n_inputs, k))            # a new input every 1 ms step
    Y = model.simulate(U)
    ep = Episode(t=2.0 + np.arange(k) * model.dt, U=U, Y=Y, name='ep')
    bag = write_input_bag(tmp_path / 'in', ep, storage='mcap', output_every=10)
    path = model.save(tmp_path / 'm.npz')
    out = tmp_path / 'pred'
    assert main(['replay', str(path), str(bag), '-o', str(out), '--publish-rate', '0',
                 '--json', str(tmp_path / 's.json'), '--components', 'xz', '--quiet']) == 0
    data = json.loads((tmp_path / 's.json').read_text())
    assert data['samples'] >= k - 10, data['samples']
    pred = np.array([data_to_array(m.data) for _, _, m in read_messages(out, [f'{NODE}/output'])])
    n = pred.shape[0]
    np.testing.assert_allclose(pred.T, Y[:, :n], atol=1e-9)
