"""The predictor node's parameters (``soft_rom/ros/node_params.py``), as a user sets them.

Start-up: a bad value is one error line naming the parameter, exit status 1, no traceback.
Run time: ``input_min`` and ``input_max`` are set one at a time by plain SetParameters (what
``ros2 param set`` sends), take effect, and ``~/model_info`` follows the envelopes in force;
every refusal is a WARN line with the reason.
"""

from __future__ import annotations

import signal

from _ros import Client, client_fixture, no_noise, NodeProcess, require_rclpy
import pytest

require_rclpy()

from sensor_msgs.msg import FluidPressure  # noqa: E402
from test_ros_node import model, MS, Outputs, params, pressure, RELIABLE, T0_NS, TOPICS  # noqa: E402

client = client_fixture('params_client')


# (-p arguments after the params file, the parameter the one error line must name)
BAD_START = {
    'type': (['-p', 'rate_hz:=abc'], 'rate_hz'),
    'range_double': (['-p', 'rate_hz:=-5.0'], 'rate_hz'),
    'range_int': (['-p', 'qos_depth:=0'], 'qos_depth'),
    'range_rate': (['-p', 'diagnostics_rate_hz:=0.0'], 'diagnostics_rate_hz'),
    'empty_list': (['-p', 'input_topics:=[]'], 'input_topics'),
    'choice': (['-p', 'executor:=fast'], 'executor'),
    'rclpy_own': (['-p', 'use_sim_time:=abc'], 'use_sim_time'),
    'no_value': (['-p', 'model_path:='], 'model_path'),
    'order': (['-p', 'warn_threshold:=0.9', '-p', 'error_threshold:=0.3'], 'warn_threshold'),
}


@pytest.mark.parametrize('case', sorted(BAD_START))
def test_bad_startup_parameter_exits_1_with_one_line(tmp_path, case) -> None:
    args, name = BAD_START[case]
    path = model().save(tmp_path / 'm.npz')
    # wait_for_model waits for a model only: a bad parameter exits all the same
    values = params(path, wait_for_model=True)
    if case == 'empty_list':
        del values['input_topics']          # the params file's value would win over []
    node = NodeProcess(tmp_path, values, extra_args=tuple(args))
    try:
        assert node.wait(30) == 1
        log = node.log()
        errors = [line for line in log.splitlines() if '[ERROR]' in line]
        assert len(errors) == 1, log
        assert name in errors[0] and 'exiting with status 1' in errors[0], log
        assert 'cannot load model_path' not in log
        assert 'Traceback' not in log and not no_noise(log), log
    finally:
        node.kill()


def _set(client: Client, fqn: str, **values) -> list:
    return [(r.successful, r.reason) for r in client.set_parameters(fqn, **values)]


def test_bounds_one_at_a_time_take_effect_and_model_info_follows(client, tmp_path) -> None:
    node = NodeProcess(tmp_path, params(model().save(tmp_path / 'm.npz')))
    try:
        out = Outputs(client, node.fqn)
        pubs = [client.node.create_publisher(FluidPressure, tp, RELIABLE) for tp in TOPICS]
        assert client.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs)
                                 and bool(out.infos), timeout=20.0)
        assert out.infos[-1]['envelope']['input_min'] is None      # none recorded in the file

        def envelope_is(lo, hi) -> bool:
            env = out.infos[-1]['envelope']
            return env['input_min'] == lo and env['input_max'] == hi

        # input_min alone, then input_max alone (one value for every input): plain requests
        assert _set(client, node.fqn, input_min=[-1.0, -1.0, -1.0]) == [(True, '')]
        assert client.spin_until(lambda: envelope_is([-1.0] * 3, None), timeout=5.0)
        assert _set(client, node.fqn, input_max=[2.0]) == [(True, '')]
        assert client.spin_until(lambda: envelope_is([-1.0] * 3, [2.0] * 3), timeout=5.0)
        assert out.infos[-1]['envelope']['input_source'] == 'configured'
        # both in one SetParameters request (rclpy applies them one at a time)
        assert _set(client, node.fqn, input_min=[-3.0], input_max=[1.0, 1.0, 1.0]) == [
            (True, ''), (True, '')]
        assert client.spin_until(lambda: envelope_is([-3.0] * 3, [1.0] * 3), timeout=5.0)
        # a value outside it is clipped and counted
        for j in range(3):
            for i, pub in enumerate(pubs):
                pub.publish(pressure(5.0 if i == 0 else 0.5, T0_NS + j * MS))
        assert client.spin_until(lambda: int(out.status(': prediction').get(
            'input_clipped', 0)) >= 3, timeout=10.0), out.status(': prediction')
        # a real conflict is refused with the reason; the envelope in force stays
        n_infos = len(out.infos)
        (ok, why), = _set(client, node.fqn, input_min=[4.0])
        assert not ok and 'input_min must not exceed input_max' in why, why
        # the output bound follows output_envelope_factor; an unchanged info is not resent
        bound = out.infos[-1]['envelope']['output_bound']
        assert _set(client, node.fqn, output_envelope_factor=7.0) == [(True, '')]
        assert client.spin_until(lambda: out.infos[-1]['envelope']['output_bound'] != bound,
                                 timeout=5.0)
        assert len(out.infos) == n_infos + 1
        # the thresholds in force are part of the info: a change is sent, the same value not
        assert _set(client, node.fqn, warn_threshold=0.2) == [(True, '')]
        assert client.spin_until(lambda: out.infos[-1]['monitor']['warn_threshold'] == 0.2,
                                 timeout=5.0)
        n_infos = len(out.infos)
        assert _set(client, node.fqn, warn_threshold=0.2) == [(True, '')]
        client.spin_for(0.3)
        assert len(out.infos) == n_infos
        # back to the defaults, one at a time: the model file's (none here)
        assert _set(client, node.fqn, input_min=[0.0]) == [(True, '')]
        assert _set(client, node.fqn, input_max=[0.0]) == [(True, '')]
        assert client.spin_until(lambda: envelope_is(None, None), timeout=5.0)
        # refusals rclpy makes itself, before the node's own checks: logged at WARN too
        assert not _set(client, node.fqn, use_sim_time='yes')[0][0]
        assert not _set(client, node.fqn, no_such_parameter=1.0)[0][0]
        assert node.proc.poll() is None
        assert node.stop(signal.SIGINT) == 0
        log = node.log()
        warns = [line for line in log.splitlines() if '[WARN]' in line and 'refused' in line]
        assert len(warns) == 3, log
        assert 'input_min must not exceed input_max' in warns[0]
        assert 'use_sim_time must be of type BOOL' in warns[1]
        assert 'no_such_parameter is not a parameter of this node' in warns[2]
        assert not no_noise(log), log
    finally:
        node.kill()
