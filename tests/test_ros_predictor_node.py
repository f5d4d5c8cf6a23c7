"""The rclpy predictor node, spun in-process (skipped where ROS 2 is not installed).

Pressures are published on per-chamber topics with header stamps; the centerlines the
node publishes are compared with ``replay`` of the same episode through the core.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
import time

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import PoseArray  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import FluidPressure  # noqa: E402
from std_msgs.msg import String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from soft_rom.data import Episode  # noqa: E402
from soft_rom.models import SecondOrderModel  # noqa: E402
from soft_rom.predictor import Predictor, PredictorConfig, replay_episode  # noqa: E402
from soft_rom.predictor.conversions import (  # noqa: E402
    outputs_to_points,
    poses_to_points,
    sec_to_stamp,
    stamp_to_sec,
)
from soft_rom.ros.predictor_node import PredictorNode  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TOPICS = ['/test/chamber_1', '/test/chamber_2', '/test/chamber_3']
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


def _model() -> SecondOrderModel:
    rng = np.random.default_rng(11)
    r, m, p = 4, 3, 10
    M = rng.standard_normal((r, r))
    K = (M @ M.T / r + 4.0 * np.eye(r)) * 100.0
    return SecondOrderModel(K, 0.5 * np.eye(r) + 0.01 * K, rng.standard_normal((r, m)),
                            0.01 * rng.standard_normal((p, r)), dt=1e-3,
                            y_ref=np.linspace(0.0, 1.0, p))


def _episode(model: SecondOrderModel, k: int = 60, t0: float = 100.0) -> Episode:
    rng = np.random.default_rng(12)
    U = np.repeat(rng.standard_normal((3, k // 6)), 6, axis=1)
    return Episode(t=t0 + np.arange(k) * model.dt, U=U, Y=model.simulate(U))


@pytest.fixture
def ctx():
    context = Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)


def _spin_until(executor, cond, timeout: float = 5.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        executor.spin_once(timeout_sec=0.01)
    return cond()


def _node(ctx, path, **params) -> PredictorNode:
    values = {'model_path': str(path), 'input_topics': TOPICS, 'input_qos': 'reliable',
              'qos_depth': 1000, 'stepping': 'input', 'publish_rate_hz': 0.0,
              'measured_topic': '/test/centerline'}
    values.update(params)
    return PredictorNode(context=ctx, parameter_overrides=[
        Parameter(k, value=v) for k, v in values.items()])


def _pressure(value: float, t: float) -> FluidPressure:
    msg = FluidPressure()
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec_to_stamp(t)
    msg.fluid_pressure = float(value)
    return msg


def test_node_centerline_equals_replay(ctx, tmp_path) -> None:
    model = _model()
    path = model.save(tmp_path / 'm.npz')
    ep = _episode(model)
    ref = replay_episode(Predictor(model, PredictorConfig(stepping='input')), ep,
                         measured=False)
    node = _node(ctx, path)
    helper = rclpy.create_node('helper', context=ctx)
    pubs = [helper.create_publisher(FluidPressure, tp, RELIABLE) for tp in TOPICS]
    got: list[tuple[float, np.ndarray]] = []
    helper.create_subscription(
        PoseArray, '/soft_rom_predictor/centerline',
        lambda msg: got.append((stamp_to_sec(msg.header.stamp), poses_to_points(msg.poses))),
        RELIABLE)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(helper)
    try:
        assert _spin_until(ex, lambda: all(p.get_subscription_count() > 0 for p in pubs))
        for j in range(ep.n_samples):
            for i, pub in enumerate(pubs):
                pub.publish(_pressure(ep.U[i, j], ep.t[j]))
            assert _spin_until(ex, lambda j=j: node.predictor.counters['inputs'] == 3 * (j + 1))
            ex.spin_once(timeout_sec=0.002)       # let the timer publish
        assert _spin_until(ex, lambda: len(got) >= 5)
        matched = 0
        for stamp, pts in got:
            j = int(round((stamp - ep.t[0]) / model.dt))
            assert 0 <= j < ep.n_samples
            np.testing.assert_allclose(pts, outputs_to_points(ref.Y[:, j], 'xz'), atol=1e-9)
            matched += 1
        assert matched >= 5
        np.testing.assert_allclose(node.predictor.output(), ref.Y[:, -1], atol=1e-12)
        assert node.predictor.counters['late'] == 0
    finally:
        ex.shutdown()
        node.destroy_node()
        helper.destroy_node()


def test_node_survives_bad_input_refuses_bad_model_and_resets(ctx, tmp_path) -> None:
    model = _model()
    path = model.save(tmp_path / 'm.npz')
    bad = tmp_path / 'bad.npz'
    bad.write_bytes(b'garbage')
    node = _node(ctx, path, stepping='fixed')
    helper = rclpy.create_node('helper2', context=ctx)
    pub = helper.create_publisher(FluidPressure, TOPICS[0], RELIABLE)
    infos: list[str] = []
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    helper.create_subscription(String, '/soft_rom_predictor/model_info',
                               lambda msg: infos.append(msg.data), latched)
    client = helper.create_client(Trigger, '/soft_rom_predictor/reset')
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(helper)
    try:
        # latched model info reaches a late subscriber
        assert _spin_until(ex, lambda: bool(infos))
        info = json.loads(infos[-1])
        assert info['r'] == 4 and info['method'] == 'lopinf' and len(info['sha256']) == 64
        # a NaN pressure is dropped and counted; the node keeps running
        assert _spin_until(ex, lambda: pub.get_subscription_count() > 0)
        now = node.get_clock().now().nanoseconds * 1e-9
        pub.publish(_pressure(math.nan, now))
        assert _spin_until(ex, lambda: node.predictor.counters['nonfinite'] == 1)
        pub.publish(_pressure(2.0, now + 0.01))
        assert _spin_until(ex, lambda: node.predictor.u[0] == 2.0)
        # a bad model file is refused with the reason; the running model stays
        running = node.predictor.model
        result = node.set_parameters([Parameter('model_path', value=str(bad))])[0]
        assert not result.successful and 'unchanged' in result.reason
        assert node.predictor.model is running
        # read-only parameters cannot change at run time
        assert not node.set_parameters([Parameter('input_mode', value='array')])[0].successful
        # a threshold changes without touching the state
        assert node.set_parameters([Parameter('warn_threshold', value=0.05)])[0].successful
        assert node.predictor.config.warn_threshold == 0.05
        # a valid model reloads (and is announced again)
        other = SecondOrderModel(running.K * 2, running.C, running.B, running.E, dt=1e-3,
                                 y_ref=running.y_ref).save(tmp_path / 'other.npz')
        n_infos = len(infos)
        assert node.set_parameters([Parameter('model_path', value=str(other))])[0].successful
        assert node.predictor.model is not running
        assert _spin_until(ex, lambda: len(infos) > n_infos)
        # reset service (inputs at zero first, so the state stays at the reference)
        pub.publish(_pressure(0.0, now + 0.02))
        assert _spin_until(ex, lambda: node.predictor.u[0] == 0.0)
        assert client.wait_for_service(timeout_sec=5.0)
        future = client.call_async(Trigger.Request())
        ex.spin_until_future_complete(future, timeout_sec=5.0)
        assert future.result().success
        assert np.all(node.predictor.x == 0)
    finally:
        ex.shutdown()
        node.destroy_node()
        helper.destroy_node()


def test_missing_model_at_startup(ctx, tmp_path) -> None:
    node = _node(ctx, tmp_path / 'missing.npz')
    try:
        assert node.predictor is None
        assert 'missing.npz' in node.startup_error
    finally:
        node.destroy_node()
    waiting = _node(ctx, tmp_path / 'missing.npz', wait_for_model=True)
    try:
        assert waiting.predictor is None
        path = _model().save(tmp_path / 'm.npz')
        assert waiting.set_parameters([Parameter('model_path', value=str(path))])[0].successful
        assert waiting.predictor is not None and waiting.startup_error is None
    finally:
        waiting.destroy_node()


def test_params_file_applies_under_another_node_name(ctx, tmp_path) -> None:
    # the launch file's node_name argument renames the node; config/predictor.yaml must still
    # apply (rcl ignores a section keyed by another node name)
    text = (ROOT / 'config' / 'predictor.yaml').read_text(encoding='utf-8')
    assert 'publish_rate_hz: 50.0' in text
    params = tmp_path / 'p.yaml'
    params.write_text(text.replace('publish_rate_hz: 50.0', 'publish_rate_hz: 7.0'),
                      encoding='utf-8')
    node = PredictorNode(context=ctx, cli_args=['--ros-args', '-r', '__node:=renamed',
                                                '--params-file', str(params)])
    try:
        assert node.get_name() == 'renamed'
        assert node.get_parameter('publish_rate_hz').value == 7.0
    finally:
        node.destroy_node()
