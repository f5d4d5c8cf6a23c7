"""The controller node under rclpy: bad messages never stop it or make it command NaN."""

from __future__ import annotations

import math
import signal
import time

from _eel_rom import modal_rom
from _ros import client_fixture, no_noise, NodeProcess, require_rclpy
import numpy as np
import pytest

require_rclpy()

from builtin_interfaces.msg import Time  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import Pose, PoseArray  # noqa: E402
from sensor_msgs.msg import FluidPressure, JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402

client = client_fixture('controller_test_client')


def _poses(points: np.ndarray, t: float) -> PoseArray:
    msg = PoseArray()
    sec = int(t)
    msg.header.stamp = Time(sec=sec, nanosec=int(round((t - sec) * 1e9)))
    for x, y, z in points:
        p = Pose()
        p.position.x, p.position.y, p.position.z = float(x), float(y), float(z)
        msg.poses.append(p)
    return msg


def _rest(model) -> np.ndarray:
    """The model's rest centerline as (points, xyz)."""
    return np.stack([model.y_ref[:20], np.zeros(20), model.y_ref[20:]], axis=1)


def _diagnostics(client) -> list[dict[str, str]]:
    """Every ``/diagnostics`` status from now on, as its values and ``msg`` (its message)."""
    diags: list[dict[str, str]] = []
    client.node.create_subscription(
        DiagnosticArray, '/diagnostics',
        lambda m: diags.extend({kv.key: kv.value for kv in s.values} | {'msg': s.message}
                               for s in m.status), 100)
    return diags


@pytest.fixture(scope='module')
def model_path(tmp_path_factory):
    return modal_rom(4).save(tmp_path_factory.mktemp('m') / 'eel_modal_r4.npz')


def test_bad_messages_are_dropped_and_commands_stay_safe(tmp_path, model_path, client) -> None:
    model = modal_rom(4)
    rest = _rest(model)
    node = NodeProcess(tmp_path, {'model_path': str(model_path), 'reference': '',
                                  'reference_topic': '/t/ref', 'measured_topic': '/t/meas',
                                  'state_topic': '/t/state', 'stale_after_s': 0.3},
                       name='ctl', exe='controller')
    try:
        commands: list[tuple[int, float]] = []
        for i in range(6):
            client.node.create_subscription(
                FluidPressure, f'/soft_robot/pressure/chamber_{i + 1}',
                lambda m, i=i: commands.append((i, m.fluid_pressure)), 100)
        diags = _diagnostics(client)
        shapes: list[PoseArray] = []
        client.node.create_subscription(PoseArray, '/ctl/reference', shapes.append, 100)
        pub_meas = client.node.create_publisher(PoseArray, '/t/meas', 100)
        pub_ref = client.node.create_publisher(PoseArray, '/t/ref', 100)
        pub_state = client.node.create_publisher(JointState, '/t/state', 100)
        assert client.spin_until(lambda: len(commands) >= 12, 60), node.log()
        # diagnostics come at 1 Hz (and at once on a change of status, before we listened)
        assert client.spin_until(lambda: any(d['status'] == 'missing' for d in diags), 5)
        now = client.node.get_clock().now().nanoseconds * 1e-9
        pub_meas.publish(_poses(rest[:19], now))                          # wrong size
        bad = rest.copy()
        bad[3, 2] = np.nan
        pub_meas.publish(_poses(bad, now))                                # NaN
        pub_ref.publish(_poses(rest[:10], now + 1))                       # wrong size
        pub_ref.publish(_poses(bad, now + 1))                             # NaN
        pub_ref.publish(_poses(rest, now - 5.0))                          # in the past
        pub_state.publish(JointState(position=[1.0, 2.0]))               # wrong size
        pub_state.publish(JointState(position=[float('nan')] * model.n_states))

        def counters_seen() -> bool:
            d = diags[-1] if diags else {}
            return (int(d.get('measurements_dropped', 0)) >= 2
                    and int(d.get('references_refused', 0)) >= 3
                    and int(d.get('states_dropped', 0)) >= 2)
        assert client.spin_until(counters_seen, 30), (diags[-1:], node.log())
        # then good data: it controls
        target = rest.copy()
        target[10:, 2] += 0.005
        for k in range(60):
            t = client.node.get_clock().now().nanoseconds * 1e-9
            pub_meas.publish(_poses(rest, t))
            st = JointState(position=[0.0] * model.n_states)
            st.header.stamp = Time(sec=int(t), nanosec=int((t - int(t)) * 1e9))
            pub_state.publish(st)
            if k % 10 == 0:
                pub_ref.publish(_poses(target, t + 0.5))
            client.spin_for(0.02)
        assert any(d['status'] == 'ok' for d in diags[-20:]), diags[-3:]
        ticks = [float(d['tick_ms']) for d in diags[-20:]]     # the previous whole tick
        assert all(math.isfinite(v) and v > 0 for v in ticks), diags[-3:]
        longest = [float(d['tick_max_ms']) for d in diags[-20:]]   # since the last message
        assert all(a >= b > 0 for a, b in zip(longest, ticks)), diags[-3:]
        # ~/reference (30 Hz while subscribed): the reference topic's shape, 20 points
        assert len(shapes) >= 10 and len(shapes[-1].poses) == 20
        got = np.array([[p.position.x, p.position.y, p.position.z] for p in shapes[-1].poses])
        assert np.allclose(got, target, atol=1e-9)
        # silence: the state goes stale and the command is held
        assert client.spin_until(lambda: diags and diags[-1]['status'] == 'stale', 10)
        assert node.proc.poll() is None
        values = np.array([v for _i, v in commands])
        assert np.all(np.isfinite(values))
        assert np.all(values >= -50e3) and np.all(values <= 50e3)
        assert node.stop(signal.SIGINT) == 0
        assert not no_noise(node.log()), node.log()
    finally:
        node.kill()


def test_array_mode_publishes_one_scaled_float64multiarray(tmp_path, model_path,
                                                           client) -> None:
    """``input_mode: array``: all chambers in one message, as the predictor reads them.

    Written as ``(u - input_offset) / input_scale``, so the predictor reads back ``u``.
    """
    model = modal_rom(4)
    rest = _rest(model)
    node = NodeProcess(tmp_path, {'model_path': str(model_path), 'reference': '',
                                  'reference_topic': '/a/ref', 'measured_topic': '/a/meas',
                                  'state_topic': '', 'input_mode': 'array',
                                  'array_topic': '/a/pressures', 'input_scale': 1000.0},
                       name='ctl_array', exe='controller')
    try:
        arrays: list[np.ndarray] = []
        chambers: list[float] = []
        client.node.create_subscription(Float64MultiArray, '/a/pressures',
                                        lambda m: arrays.append(np.array(m.data)), 100)
        for i in range(6):
            client.node.create_subscription(
                FluidPressure, f'/soft_robot/pressure/chamber_{i + 1}',
                lambda m: chambers.append(m.fluid_pressure), 100)
        pub_meas = client.node.create_publisher(PoseArray, '/a/meas', 100)
        pub_ref = client.node.create_publisher(PoseArray, '/a/ref', 100)
        assert client.spin_until(lambda: len(arrays) >= 5, 60), node.log()    # it is up
        target = rest.copy()
        target[10:, 2] += 0.01                                   # bend the tail up 10 mm
        for k in range(80):
            t = client.node.get_clock().now().nanoseconds * 1e-9
            pub_meas.publish(_poses(rest, t))
            if k % 10 == 0:
                pub_ref.publish(_poses(target, t + 0.5))
            client.spin_for(0.02)
        values = np.stack(arrays)
        assert values.shape[1] == 6 and np.all(np.isfinite(values))
        # kPa on the wire: within the model's training range (+-50 kPa), and moving
        assert np.all(np.abs(values) <= 50.0 + 1e-9)
        assert np.abs(values[-1]).max() > 0.5
        assert chambers == []
        assert node.stop(signal.SIGINT) == 0
        assert not no_noise(node.log()), node.log()
    finally:
        node.kill()


@pytest.mark.parametrize('params, message', [
    ({'input_mode': 'bus'}, "input_mode 'bus' is not one of per_chamber, array"),
    ({'diagnostics_rate_hz': 0.0}, 'diagnostics_rate_hz must be between 0.01 and 100; got 0.0'),
    ({'rate_weight': 'abc'}, 'parameter rate_weight must be of type DOUBLE; got STRING abc'),
    ({'stale_after_s': -1.0}, 'stale_after must be a positive number of seconds; got -1.0'),
    ({'reference_duration_s': -5.0}, 'reference_duration_s must be finite and > 0; got -5.0'),
    ({'model_path': ''}, 'model_path is empty (give -p model_path:=FILE)'),
    ({'reference': 'wave:f=200'}, 'at or above the Nyquist rate (50 Hz) of the 10 ms control'),
])
def test_bad_parameter_is_one_line_and_exit_1(tmp_path, model_path, params, message) -> None:
    node = NodeProcess(tmp_path, {'model_path': str(model_path), **params},
                       name='ctl_bad', exe='controller')
    try:
        assert node.wait(60) == 1
        log = node.log()
        assert message in log, log
        assert 'Traceback' not in log
    finally:
        node.kill()


def test_an_untrusted_model_and_a_target_out_of_reach_are_logged_once(tmp_path, client
                                                                      ) -> None:
    """The node's own log lines; the library's warnings are not printed beside them."""
    from soft_rom.models import SecondOrderModel
    m = modal_rom(4)
    # a skew part in the damping: stable, but not trusted ('C is not symmetric')
    C = m.C.copy()
    C[0, 1] += 0.5 * np.abs(C).max()
    C[1, 0] -= 0.5 * np.abs(C).max()
    bad = SecondOrderModel(m.K, C, m.B, m.E, dt=m.dt, y_ref=m.y_ref,
                           output_names=m.output_names, input_units=['Pa'] * 6,
                           output_units=['m'] * 40, metadata=m.metadata)
    assert bad.trust_issues() == ['C is not symmetric']
    sys_ = bad.discretize(0.01)
    G = sys_.C @ np.linalg.solve(np.eye(sys_.A.shape[0]) - sys_.A, sys_.B) + sys_.D
    Y = np.repeat(m.y_ref[:, None], 3, axis=1)
    Y[:, 1:] += (G @ (200e3 * np.array([1.0, -1.0] * 3)))[:, None]   # 4 x the +-50 kPa
    np.savez(tmp_path / 'far.npz', t=np.array([0.0, 0.05, 1.0]), Y=Y)
    node = NodeProcess(tmp_path, {'model_path': str(bad.save(tmp_path / 'bad.npz')),
                                  'reference': str(tmp_path / 'far.npz')},
                       name='ctl_untrusted', exe='controller')
    try:
        assert client.spin_until(lambda: 'out of reach' in node.log(), 60), node.log()
        assert node.stop(signal.SIGINT) == 0
        log = node.log()
        assert log.count('not trusted') == 1 and log.count('out of reach') == 1, log
        assert 'Warning:' not in log and 'warnings.warn' not in log, log
    finally:
        node.kill()


@pytest.mark.parametrize('exe', ['controller', 'plant'])
def test_a_bad_command_line_is_one_line_and_exit_1(tmp_path, exe) -> None:
    node = NodeProcess(tmp_path, {}, name=f'{exe}_badargs', exe=exe,
                       extra_args=('-p', 'model_path'))        # no := value
    try:
        assert node.wait(60) == 1
        log = node.log()
        assert 'bad command line (--ros-args)' in log and 'Traceback' not in log, log
    finally:
        node.kill()


def test_plant_refuses_input_topics_of_the_wrong_length(tmp_path) -> None:
    # one topic for six chambers: five would stay at 0 Pa and every lockstep point time out
    node = NodeProcess(tmp_path, {'input_topics': ['/soft_robot/pressure/chamber_1']},
                       name='plant_topics', exe='plant')
    try:
        assert node.wait(60) == 1
        log = node.log()
        assert 'input_topics needs 6 topics (one per chamber); got 1' in log, log
        assert 'Traceback' not in log
    finally:
        node.kill()


def test_a_mistyped_parameter_is_named(tmp_path, model_path, client) -> None:
    node = NodeProcess(tmp_path, {'model_path': str(model_path), 'horizn': 0.5},
                       name='ctl_typo', exe='controller')
    try:
        assert client.spin_until(lambda: 'horizn' in node.log(), 60), node.log()
        assert 'parameter(s) horizn given but not declared by this node' in node.log()
        assert node.stop(signal.SIGINT) == 0
    finally:
        node.kill()


@pytest.mark.parametrize('exe', ['controller', 'predictor'])
def test_waiting_for_a_sim_clock_is_said(tmp_path, model_path, client, exe) -> None:
    # use_sim_time and no /clock: the timers wait, nothing is published; the log says why
    node = NodeProcess(tmp_path, {'model_path': str(model_path), 'use_sim_time': True},
                       name=f'{exe}_noclock', exe=exe)
    try:
        assert client.spin_until(lambda: 'no /clock has come in 5 s' in node.log(), 60), \
            node.log()
        assert node.stop(signal.SIGINT) == 0
    finally:
        node.kill()


def test_a_best_effort_motion_capture_reaches_the_controller(tmp_path, model_path,
                                                             client) -> None:
    # many mocap drivers publish best effort: a reliable reader never matched them
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    model = modal_rom(4)
    rest = _rest(model)
    node = NodeProcess(tmp_path, {'model_path': str(model_path), 'measured_topic': '/t/mocap',
                                  'state_topic': ''}, name='ctl_mocap', exe='controller')
    try:
        diags = _diagnostics(client)
        pub = client.node.create_publisher(
            PoseArray, '/t/mocap', QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))

        def measured() -> bool:
            pub.publish(_poses(rest, client.node.get_clock().now().nanoseconds * 1e-9))
            return any(int(d.get('measurements', 0)) > 0 for d in diags)

        assert client.spin_until(measured, 60), (diags[-1:], node.log())
        assert node.stop(signal.SIGINT) == 0
    finally:
        node.kill()


def test_plant_stops_at_once_while_it_waits_for_commands(tmp_path, client) -> None:
    # a controller is there but silent: the plant waits at its first lockstep point (up to
    # command_timeout_s); SIGTERM ends that wait (it waited the 30 s out), quietly
    pubs = [client.node.create_publisher(FluidPressure, f'/soft_robot/pressure/chamber_{i}',
                                         100) for i in range(1, 7)]
    clock: list[float] = []
    from rosgraph_msgs.msg import Clock
    client.node.create_subscription(Clock, '/clock', lambda m: clock.append(m.clock.nanosec),
                                    100)
    node = NodeProcess(tmp_path, {'command_timeout_s': 30.0}, name='plant_wait', exe='plant')
    try:
        assert client.spin_until(lambda: len(clock) >= 5, 60), node.log()
        client.spin_for(0.5)
        start = time.monotonic()
        assert node.stop(signal.SIGTERM, timeout=20) == 0
        assert time.monotonic() - start < 5.0, node.log()
        assert 'no command for' not in node.log() and not no_noise(node.log()), node.log()
    finally:
        node.kill()
        for pub in pubs:
            client.node.destroy_publisher(pub)


def test_measurements_in_another_frame_are_dropped_and_unstamped_ones_taken(
        tmp_path, model_path, client) -> None:
    model = modal_rom(4)
    rest = _rest(model)
    node = NodeProcess(tmp_path, {'model_path': str(model_path), 'measured_topic': '/t/m2',
                                  'state_topic': ''}, name='ctl_frames', exe='controller')
    try:
        diags = _diagnostics(client)
        pub = client.node.create_publisher(PoseArray, '/t/m2', 100)

        def sent(frame: str, stamped: bool, key: str, least: int = 1) -> bool:
            msg = _poses(rest, client.node.get_clock().now().nanoseconds * 1e-9 if stamped
                         else 0.0)
            msg.header.frame_id = frame
            pub.publish(msg)
            client.spin_for(0.05)
            return any(int(d.get(key, 0)) >= least for d in diags[-3:])

        # a motion-capture frame against the node's world: dropped, said
        assert client.spin_until(lambda: sent('mocap', True, 'measurements_dropped'), 60)
        assert all(d.get('measurements', '0') == '0' for d in diags), diags[-1]
        assert "measurement dropped: frame_id 'mocap' is not this node's" in node.log()
        # no stamp, in the node's frame: each taken at its arrival (not only the first, at 0)
        assert client.spin_until(lambda: sent('world', False, 'measurements', 5), 30), \
            diags[-1]
        assert node.stop(signal.SIGINT) == 0
    finally:
        node.kill()


def test_a_second_sender_or_commander_on_its_topics_is_warned(tmp_path, model_path,
                                                              client) -> None:
    # the predictor counted the publishers on its inputs; the controller did not: a second
    # commander on its pressure topics (fighting it) or a second measured centerline sender
    # left it OK
    model = modal_rom(4)
    rest = _rest(model)
    node = NodeProcess(tmp_path, {'model_path': str(model_path), 'measured_topic': '/t/m3',
                                  'reference': '', 'reference_topic': '/t/ref3',
                                  'state_topic': '', 'diagnostics_rate_hz': 5.0},
                       name='ctl_graph', exe='controller')
    try:
        got: list[tuple[int, dict[str, str]]] = []
        client.node.create_subscription(
            DiagnosticArray, '/diagnostics',
            lambda m: got.extend((s.level[0] if isinstance(s.level, bytes) else s.level,
                                  {kv.key: kv.value for kv in s.values} | {'msg': s.message})
                                 for s in m.status if s.name.endswith('ctl_graph: control')),
            100)
        pub_meas = client.node.create_publisher(PoseArray, '/t/m3', 100)
        pub_ref = client.node.create_publisher(PoseArray, '/t/ref3', 100)
        target = rest.copy()
        target[10:, 2] += 0.002
        extra: list = []

        def controlling(want: str, seconds: float = 0.3) -> bool:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                t = client.node.get_clock().now().nanoseconds * 1e-9
                pub_meas.publish(_poses(rest, t))
                pub_ref.publish(_poses(target, t + 0.5))
                client.spin_for(0.02)
            return bool(got) and got[-1][1]['status'] == 'ok' and want in got[-1][1]['msg']

        assert client.spin_until(lambda: controlling('ok'), 60), (got[-1:], node.log())
        level, values = got[-1]
        assert level == 0 and values['msg'] == 'ok', got[-1]
        assert values['measured_publishers'] == '1' and values['command_publishers'] == '1'
        assert values['reference_publishers'] == '1', values
        # a second commander on chamber 3 and a second sender of the measured centerline
        extra.append(client.node.create_publisher(FluidPressure,
                                                  '/soft_robot/pressure/chamber_3', 10))
        extra.append(client.node.create_publisher(PoseArray, '/t/m3', 10))
        assert client.spin_until(lambda: controlling('second commander'), 30), got[-1:]
        level, values = got[-1]
        assert level == 1 and values['status'] == 'ok', got[-1]
        assert ('1 other publisher(s) on /soft_robot/pressure/chamber_3, which this node '
                'commands (a second commander fighting it?)') in values['msg']
        assert '2 publishers on /t/m3 (a second sender?)' in values['msg'], values['msg']
        assert values['command_publishers'] == '2' and values['measured_publishers'] == '2'
        for pub in extra:                           # gone: OK again
            client.node.destroy_publisher(pub)
        assert client.spin_until(lambda: controlling('ok') and got[-1][1]['msg'] == 'ok', 30), \
            got[-1:]
        assert got[-1][0] == 0
        assert node.stop(signal.SIGINT) == 0
    finally:
        node.kill()


def test_the_last_dropped_measurement_stays_in_the_diagnostics(tmp_path, model_path,
                                                               client) -> None:
    # a held command's reason overwrote last_problem at every tick, so why a measurement was
    # dropped showed only in the log; last_dropped keeps it
    model = modal_rom(4)
    rest = _rest(model)
    node = NodeProcess(tmp_path, {'model_path': str(model_path), 'measured_topic': '/t/m4',
                                  'state_topic': '', 'reference': ''},
                       name='ctl_dropped', exe='controller')
    try:
        diags = _diagnostics(client)
        pub = client.node.create_publisher(PoseArray, '/t/m4', 100)
        bad = rest.copy()
        bad[3, 2] = np.nan

        def dropped() -> bool:
            pub.publish(_poses(bad, client.node.get_clock().now().nanoseconds * 1e-9))
            client.spin_for(0.05)
            return any(int(d.get('measurements_dropped', 0)) > 0 for d in diags)

        assert client.spin_until(dropped, 60), (diags[-1:], node.log())
        client.spin_for(1.5)                        # more reports, every tick held since
        last = diags[-1]
        assert last['status'] != 'ok' and int(last['held']) > 0, last      # held: no reference
        assert 'NaN' not in last['last_problem'], last                     # overwritten
        assert last['last_dropped'] == ('measurement dropped: measurement with 1 NaN/Inf '
                                        'value(s)'), last
        assert node.stop(signal.SIGINT) == 0
    finally:
        node.kill()
