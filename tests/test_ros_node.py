"""The installed ``predictor`` in its own process, driven by a plain rclpy client.

What a user does: publish pressures (per chamber, or one array), hostile messages, call
``~/reset``, set ``model_path`` at run time, start it wrong, press Ctrl-C.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
import signal
import threading
import time

from _ros import Client, client_fixture, no_noise, NodeProcess, Pauser, require_rclpy
import numpy as np
import pytest

require_rclpy()

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import Pose, PoseArray  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import FluidPressure, JointState  # noqa: E402
from std_msgs.msg import Float64MultiArray, String  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from soft_rom.data import Episode  # noqa: E402
from soft_rom.models import DiscreteModel, SecondOrderModel  # noqa: E402
from soft_rom.predictor import Predictor, PredictorConfig, replay_episode  # noqa: E402
from soft_rom.predictor.conversions import ns_to_stamp, stamp_to_ns  # noqa: E402

TOPICS = ['/t/chamber_1', '/t/chamber_2', '/t/chamber_3']
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
T0_NS = 1_700_000_000_123_000_000      # epoch-like stamps (int ns)
MS = 1_000_000


def model(seed: int = 11, scale: float = 1.0) -> SecondOrderModel:
    """A stable 3-input, 10-output second-order ROM at dt = 1 ms."""
    rng = np.random.default_rng(seed)
    r, m, p = 4, 3, 10
    M = rng.standard_normal((r, r))
    K = (M @ M.T / r + 4.0 * np.eye(r)) * 100.0 * scale
    return SecondOrderModel(K, 0.5 * np.eye(r) + 0.01 * K, rng.standard_normal((r, m)),
                            0.01 * rng.standard_normal((p, r)), dt=1e-3,
                            y_ref=np.linspace(0.0, 1.0, p))


def episode(m: SecondOrderModel, k: int = 200) -> Episode:
    """Piecewise-constant random pressures at the model's rate (time from 0)."""
    rng = np.random.default_rng(12)
    U = np.repeat(rng.standard_normal((3, k // 5 + 1)), 5, axis=1)[:, :k]
    return Episode(t=np.arange(k) * m.dt, U=U, Y=m.simulate(U))


def pressure(value: float, t_ns: int) -> FluidPressure:
    """A FluidPressure stamped ``t_ns`` (0: a zero stamp)."""
    msg = FluidPressure()
    msg.header.stamp.sec, msg.header.stamp.nanosec = ns_to_stamp(t_ns)
    msg.fluid_pressure = float(value)
    return msg


def params(path: Path | str, **extra) -> dict:
    """Node parameters for these tests (reliable QoS, every step published)."""
    values = {'model_path': str(path), 'input_topics': TOPICS, 'input_qos': 'reliable',
              'qos_depth': 1000, 'publish_rate_hz': 0.0,
              'measured_topic': '/t/centerline', 'array_topic': '/t/pressures',
              'diagnostics_rate_hz': 5.0}
    values.update(extra)
    return values


class Outputs:
    """Collects ``~/output_stamped`` (model time -> outputs) and ``~/output`` of a node."""

    def __init__(self, client: Client, fqn: str) -> None:
        self.stamped: dict[int, np.ndarray] = {}
        self.times: list[int] = []
        self.plain: list[np.ndarray] = []
        self.infos: list[dict] = []
        self.diagnostics: list[DiagnosticArray] = []
        self.centerlines: list[int] = []
        n = client.node
        n.create_subscription(PoseArray, f'{fqn}/centerline',
                              lambda m: self.centerlines.append(stamp_to_ns(m.header.stamp)),
                              RELIABLE)
        n.create_subscription(JointState, f'{fqn}/output_stamped', self._on_stamped, RELIABLE)
        n.create_subscription(Float64MultiArray, f'{fqn}/output',
                              lambda m: self.plain.append(np.array(m.data)), RELIABLE)
        n.create_subscription(String, f'{fqn}/model_info',
                              lambda m: self.infos.append(json.loads(m.data)), LATCHED)
        n.create_subscription(DiagnosticArray, '/diagnostics', self.diagnostics.append, 10)

    def _on_stamped(self, msg: JointState) -> None:
        t_ns = stamp_to_ns(msg.header.stamp)
        self.stamped[t_ns] = np.array(msg.position)
        self.times.append(t_ns)

    def status(self, suffix: str) -> dict:
        """The newest diagnostic status whose name ends with ``suffix``: level, message, values."""
        for arr in reversed(self.diagnostics):
            for st in arr.status:
                if st.name.endswith(suffix):
                    return {'level': st.level[0] if isinstance(st.level, bytes) else st.level,
                            'message': st.message, 'name': st.name,
                            'hardware_id': st.hardware_id,
                            **{kv.key: kv.value for kv in st.values}}
        return {}


client = client_fixture()


def _publishers(client: Client, topics=TOPICS, kind=FluidPressure) -> list:
    return [client.node.create_publisher(kind, tp, RELIABLE) for tp in topics]


def _connected(client: Client, pubs: list, out: Outputs | None = None) -> None:
    assert client.spin_until(lambda: all(p.get_subscription_count() > 0 for p in pubs),
                             timeout=20.0), 'the node did not subscribe'
    if out is not None:
        assert client.spin_until(lambda: bool(out.infos), timeout=10.0), 'no model_info'


@pytest.mark.parametrize('executor', ['events', 'single_threaded'])
def test_per_chamber_input_at_full_rate_equals_replay(client, tmp_path, executor) -> None:
    m = model()
    ep = episode(m)
    ref = replay_episode(Predictor(m, PredictorConfig()), ep, measured=False, t0_ns=T0_NS)
    # The burst puts 200 ms of stamps on the wire in a few ms, far faster than real time, and
    # the executor may drain one topic's queue well ahead of another's. The stamp-time caps
    # for real-time streams (max_lag_s 0.1 s, input_timeout_s 0.5 s: a topic that many
    # stamps behind is lagging or dead) would then step on with held inputs under load, so
    # they are lifted here: this test checks that every step is taken once, at its stamp.
    node = NodeProcess(tmp_path, params(m.save(tmp_path / 'm.npz'), executor=executor,
                                        max_lag_s=30.0, input_timeout_s=30.0))
    try:
        out = Outputs(client, node.fqn)
        pubs = _publishers(client)
        _connected(client, pubs, out)
        for j in range(ep.n_samples):      # as fast as rclpy publishes, no waiting
            for i, pub in enumerate(pubs):
                pub.publish(pressure(ep.U[i, j], T0_NS + j * MS))
        last = T0_NS + (ep.n_samples - 1) * MS
        assert client.spin_until(lambda: last in out.stamped, timeout=20.0), len(out.stamped)
        want = {T0_NS + j * MS: ref.Y[:, j] for j in range(ep.n_samples)}
        assert set(out.stamped) == set(want)          # every step, none twice
        assert len(out.times) == ep.n_samples
        worst = max(np.max(np.abs(y - want[t])) for t, y in out.stamped.items())
        assert worst <= 1e-12 * max(1.0, np.max(np.abs(ref.Y)))
        assert client.spin_until(lambda: len(out.plain) == ep.n_samples, timeout=5.0)
        # the centerline (and markers) at their own rate: 30 Hz of model time, not 1 kHz
        span = (ep.n_samples - 1) * 1e-3
        assert 0.8 * 30 * span <= len(out.centerlines) <= 30 * span + 2, len(out.centerlines)
        assert min(np.diff(out.centerlines)) >= 33 * MS
        assert out.infos[-1]['r'] == 4 and len(out.infos[-1]['sha256']) == 64
        assert node.stop(signal.SIGINT) == 0
        assert not no_noise(node.log()), node.log()
    finally:
        node.kill()


def test_array_input_equals_replay_of_what_arrived(client, tmp_path) -> None:
    rng = np.random.default_rng(3)
    A = np.diag([0.99, 0.95, 0.9, 0.8])
    m = DiscreteModel(A, 0.01 * rng.standard_normal((4, 3)), rng.standard_normal((10, 4)),
                      rng.standard_normal((10, 3)), dt=1e-3,
                      y_ref=np.linspace(0.0, 1.0, 10))          # D != 0: u shows at once
    U = rng.standard_normal((3, 60))
    node = NodeProcess(tmp_path, params(m.save(tmp_path / 'm.npz'), input_mode='array'))
    try:
        out = Outputs(client, node.fqn)
        pub = client.node.create_publisher(Float64MultiArray, '/t/pressures', RELIABLE)
        _connected(client, [pub], out)
        for j in range(U.shape[1]):
            n = len(out.times)
            pub.publish(Float64MultiArray(data=U[:, j].tolist()))
            assert client.spin_until(lambda n=n: len(out.times) > n, timeout=10.0)
            client.spin_for(0.003)
        client.spin_for(0.2)
        # Un-stamped arrays are stamped on arrival (the client cannot see when): check that
        # the outputs are the model run with the inputs in order, each held from some step
        # on until the next, none lost, exact to 1e-12.
        steps = sorted(out.stamped)
        assert steps == [steps[0] + i * MS for i in range(len(steps))], 'a step missing'
        x = np.zeros(4)
        j = 0
        for k in steps:
            for cand in (j, j + 1)[:2 if j + 1 < U.shape[1] else 1]:
                y = m.C @ x + m.D @ U[:, cand] + m.y_ref
                if np.max(np.abs(y - out.stamped[k])) <= 1e-12:
                    j = cand
                    break
            else:
                raise AssertionError(f'step {(k - steps[0]) // MS}: no input explains it')
            x = m.A @ x + m.B @ U[:, j]
        assert j == U.shape[1] - 1, f'only {j + 1} of {U.shape[1]} inputs applied'
    finally:
        node.kill()


def test_arrays_all_dropped_show_on_their_topic(client, tmp_path) -> None:
    # arrays of the wrong length: the topic says they arrive and are dropped, not "no
    # messages yet" (an audit saw STALE 'nothing received' while 2,499 were dropped)
    node = NodeProcess(tmp_path, params(model().save(tmp_path / 'm.npz'), input_mode='array'))
    try:
        out = Outputs(client, node.fqn)
        pub = client.node.create_publisher(Float64MultiArray, '/t/pressures', RELIABLE)
        _connected(client, [pub], out)

        def warned() -> bool:
            pub.publish(Float64MultiArray(data=[1.0] * 5))
            return out.status(': input /t/pressures').get('message', '').startswith('none taken')

        assert client.spin_until(warned, timeout=20.0), out.status(': input /t/pressures')
        st = out.status(': input /t/pressures')
        assert st['level'] == 1 and 'dropped or clipped since the last report' in st['message']
        assert int(st['dropped']) >= 1 and st['received'] == '0', st
        assert node.stop(signal.SIGINT) == 0
    finally:
        node.kill()


def test_array_burst_one_step_each_equals_simulate(client, tmp_path) -> None:
    # un-stamped arrays are placed on the sender's sequence: a burst (as after an executor
    # stall) still gives one model step per array, in order
    m = model()
    ep = episode(m, k=60)
    node = NodeProcess(tmp_path, params(m.save(tmp_path / 'm.npz'), input_mode='array'))
    try:
        out = Outputs(client, node.fqn)
        pub = client.node.create_publisher(Float64MultiArray, '/t/pressures', RELIABLE)
        _connected(client, [pub], out)
        for j in range(ep.n_samples):                  # a burst: no waiting at all
            pub.publish(Float64MultiArray(data=ep.U[:, j].tolist()))
        assert client.spin_until(lambda: len(out.stamped) >= ep.n_samples, timeout=20.0), (
            len(out.stamped), out.status(': prediction'))
        client.spin_for(0.1)
        steps = sorted(out.stamped)
        assert steps == [steps[0] + j * MS for j in range(ep.n_samples)]
        Y = np.array([out.stamped[t] for t in steps]).T
        np.testing.assert_allclose(Y, ep.Y, rtol=0, atol=1e-12)      # each array one step
    finally:
        node.kill()


def test_hostile_messages_reset_and_diagnostics(client, tmp_path) -> None:
    m = model()
    node = NodeProcess(tmp_path, params(m.save(tmp_path / 'm.npz'), hardware_id='eel_1'))
    try:
        out = Outputs(client, node.fqn)
        pubs = _publishers(client)
        arr = client.node.create_publisher(Float64MultiArray, '/t/pressures', RELIABLE)
        meas = client.node.create_publisher(PoseArray, '/t/centerline', RELIABLE)
        _connected(client, pubs + [meas], out)
        t = T0_NS
        for j in range(20):
            for pub in pubs:
                pub.publish(pressure(1.0, t + j * MS))
        hostile = [math.nan, math.inf, -math.inf, 1e308, -1e308]
        for value in hostile:
            pubs[0].publish(pressure(value, t + 19 * MS + MS // 2))
        pubs[1].publish(pressure(1.0, t - 500 * MS))             # stamp going backwards
        arr.publish(Float64MultiArray(data=[1.0] * 7))      # wrong topic for this mode
        bad_pose = PoseArray(poses=[Pose()] * 3)            # wrong number of points
        meas.publish(bad_pose)
        nan_pose = PoseArray(poses=[Pose()] * 5)
        nan_pose.poses[0].position.x = math.nan
        meas.publish(nan_pose)
        for j in range(20, 40):                              # and it keeps working
            for pub in pubs:
                pub.publish(pressure(0.5, t + j * MS))
        last = t + 39 * MS
        assert client.spin_until(lambda: last in out.stamped, timeout=20.0)
        assert np.all(np.isfinite(out.stamped[last]))
        assert np.max(np.abs(out.stamped[last] - m.y_ref)) < 10.0
        assert node.proc.poll() is None
        # per-input diagnostics: stable names, rate and stamp age, the hardware id. The
        # diagnostics are a snapshot at the timer's tick, which may fall amid the last
        # batch: wait for one taken after every message was received.
        def reported() -> bool:
            return (int(out.status(': prediction').get('nonfinite', 0)) >= 3
                    and all(int(out.status(f': input {tp}').get('received', 0)) >= 40
                            for tp in TOPICS))

        assert client.spin_until(reported, timeout=10.0), [
            out.status(': prediction'), *(out.status(f': input {tp}') for tp in TOPICS)]
        pred = out.status(': prediction')
        assert pred['hardware_id'] == 'eel_1'
        assert int(pred['nonfinite']) >= 3
        for topic in TOPICS:
            st = out.status(f': input {topic}')
            assert st['hardware_id'] == 'eel_1', st
            assert int(st['received']) >= 40
            assert 'rate_hz' in st and 'stamp_age_s' in st
        measured = out.status(': measured /t/centerline')
        # both arrived, both dropped (3 points; NaN): said on the topic, not "OK 30 Hz"
        assert measured['received'] == '2' and measured['dropped'] == '2', measured
        pubs[2].publish(pressure(1.0, 0))     # a zero stamp: taken at node time
        assert client.spin_until(lambda: len(out.stamped) > 40, timeout=10.0)
        # ~/reset
        res = client.call(Trigger, f'{node.fqn}/reset', Trigger.Request())
        assert res.success, res.message
        assert node.proc.poll() is None
        assert node.stop(signal.SIGINT) == 0
        assert not no_noise(node.log()), node.log()
    finally:
        node.kill()


def test_reload_missing_corrupt_valid_and_runtime_parameters(client, tmp_path) -> None:
    m = model()
    path = m.save(tmp_path / 'm.npz')
    corrupt = tmp_path / 'corrupt.npz'
    corrupt.write_bytes(path.read_bytes()[:200])
    other = model(seed=5).save(tmp_path / 'other.npz')
    node = NodeProcess(tmp_path, params(path))
    try:
        out = Outputs(client, node.fqn)
        pubs = _publishers(client)
        _connected(client, pubs, out)
        sha = out.infos[-1]['sha256']
        for bad in (tmp_path / 'missing.npz', corrupt):
            res = client.set_parameters(node.fqn, model_path=str(bad))[0]
            assert not res.successful and 'unchanged' in res.reason, res.reason
            assert bad.name in res.reason
        res = client.set_parameters(node.fqn, model_path=str(other))[0]
        assert res.successful, res.reason
        assert client.spin_until(lambda: out.infos[-1]['sha256'] != sha, timeout=10.0)
        # an integer for a double, at run time; read-only and out-of-range refused (WARN)
        assert client.set_parameters(node.fqn, input_timeout_s=2)[0].successful
        ro = client.set_parameters(node.fqn, input_mode='array')[0]
        assert not ro.successful
        rng = client.set_parameters(node.fqn, warn_threshold=500.0)[0]
        assert not rng.successful
        assert client.set_parameters(node.fqn, error_threshold=0.3)[0].successful
        bad_order = client.set_parameters(node.fqn, warn_threshold=0.9)[0]   # > error 0.3
        assert not bad_order.successful and 'unchanged' in bad_order.reason
        # still running the reloaded model
        for pub in pubs:
            pub.publish(pressure(1.0, T0_NS))
        assert client.spin_until(lambda: T0_NS in out.stamped, timeout=10.0)
        assert node.stop(signal.SIGTERM) == 0
        log = node.log()
        warns = [line for line in log.splitlines() if '[WARN]' in line and 'refused' in line]
        assert len(warns) >= 5, log          # missing, corrupt, read-only, range, order
        assert any('input_mode is read-only' in w for w in warns)
        assert any('warn_threshold' in w and 'outside' in w for w in warns)
        assert not no_noise(log), log
    finally:
        node.kill()


@pytest.mark.parametrize('case', ['missing', 'corrupt', 'empty', 'bad_mode', 'topics'])
def test_startup_failure_exits_1_with_one_line(tmp_path, case) -> None:
    path = model().save(tmp_path / 'm.npz')
    corrupt = tmp_path / 'c.npz'
    corrupt.write_bytes(b'PK\x03\x04 not a zip')
    values = {'missing': params(tmp_path / 'nope.npz'), 'corrupt': params(corrupt),
              'empty': params(''), 'bad_mode': params(path, input_mode='both'),
              'topics': params(path, input_topics=TOPICS[:2])}[case]
    node = NodeProcess(tmp_path, values)
    try:
        assert node.wait(30) == 1
        log = node.log()
        errors = [line for line in log.splitlines() if '[ERROR]' in line]
        assert len(errors) == 1 and 'exiting with status 1' in errors[0], log
        assert 'Traceback' not in log
    finally:
        node.kill()


def test_wait_for_model_then_load_and_integer_overrides(client, tmp_path) -> None:
    path = model().save(tmp_path / 'm.npz')
    # an integer written for a double parameter (and an integer array for a double array)
    # is accepted at start-up, and at run time
    node = NodeProcess(tmp_path, params(tmp_path / 'later.npz', wait_for_model=True,
                                        rate_hz=1000, centerline_rate_hz=10,
                                        input_max=[100000]))
    try:
        out = Outputs(client, node.fqn)
        assert client.spin_until(lambda: 'no model' in out.status(': prediction').get(
            'message', ''), timeout=20.0)
        assert out.status(': prediction')['level'] == 2
        assert client.set_parameters(node.fqn, model_path=str(path))[0].successful
        assert client.spin_until(lambda: bool(out.infos), timeout=10.0)
        assert client.set_parameters(node.fqn, input_max=[200000])[0].successful
        assert 'INTEGER_ARRAY' not in node.log(), node.log()
        assert node.stop(signal.SIGINT) == 0
    finally:
        node.kill()


def _flood(pubs, stop: threading.Event) -> None:
    t = time.time_ns()
    while not stop.is_set():
        t += MS
        for pub in pubs:
            pub.publish(pressure(0.1, t))
        time.sleep(0.0005)


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
@pytest.mark.parametrize('stepping,executor', [('event', 'events'),
                                               ('fixed', 'single_threaded')])
def test_signal_under_load_exits_0_quietly(client, tmp_path, sig, stepping, executor) -> None:
    m = model()
    node = NodeProcess(tmp_path, params(m.save(tmp_path / 'm.npz'), stepping=stepping,
                                        centerline_rate_hz=0.0, executor=executor))
    stop = threading.Event()
    try:
        out = Outputs(client, node.fqn)
        pubs = _publishers(client)
        _connected(client, pubs, out)
        flood = threading.Thread(target=_flood, args=(pubs, stop), daemon=True)
        flood.start()
        assert client.spin_until(lambda: len(out.plain) > 50, timeout=10.0)
        assert node.stop(sig) == 0
        stop.set()
        flood.join(5)
        log = node.log()
        assert not no_noise(log), log
    finally:
        stop.set()
        node.kill()


# -- a node that pauses: SIGSTOP for 60 ms and 150 ms during a 1 kHz stream ---------------
PAUSES = {300: 0.060, 800: 0.150}          # at the array / sample index: seconds stopped


def _stream(node: NodeProcess, k: int, send) -> str:
    """Send ``send(j)`` for j < k at 1 kHz of wall time; stop the node as :data:`PAUSES` says.

    The pauses are timed by a :class:`Pauser` of their own on the stream's schedule (array
    ``j`` is due ``j`` ms after the start), not by this loop. A sender that falls behind (a
    loaded machine) catches up at once, as a real one's queue would. Returns how it went,
    for the assertions' messages: the pauses as they happened, the sender's worst lag.
    """
    pauser = Pauser(node.proc.pid, {j * 1e-3: length for j, length in PAUSES.items()})
    lag = 0.0
    try:
        pauser.start(start := time.monotonic() + 0.01)
        for j in range(k):
            due = start + j * 1e-3
            while (now := time.monotonic()) < due:
                time.sleep(min(due - now, 2e-4))
            lag = max(lag, now - due)
            send(j)
        return (f'node stopped (at, for; s) {pauser.done()}, sender at most '
                f'{lag * 1e3:.0f} ms late')
    finally:
        pauser.kill()


def _counters(client: Client, out: Outputs, k: int) -> dict:
    """The node's prediction diagnostics once it has taken all ``k`` inputs of the stream."""
    assert client.spin_until(lambda: int(out.status(': prediction').get('inputs', 0)) >= k,
                             timeout=30.0), out.status(': prediction')
    client.spin_for(0.5)                         # the next report: every figure settled
    return out.status(': prediction')


def test_pauses_keep_one_step_per_array_equal_to_simulate(client, tmp_path) -> None:
    m = model()
    k = 1200
    ep = episode(m, k=k)
    # ~/output at 50 Hz of model time: the figures the test needs, without asking the test
    # process (the sender) to take 1 kHz of outputs as well
    node = NodeProcess(tmp_path, params(m.save(tmp_path / 'm.npz'), input_mode='array',
                                        publish_rate_hz=50.0))
    try:
        out = Outputs(client, node.fqn)
        pub = client.node.create_publisher(Float64MultiArray, '/t/pressures', RELIABLE)
        _connected(client, [pub], out)
        how = _stream(node, k,
                      lambda j: pub.publish(Float64MultiArray(data=ep.U[:, j].tolist())))
        pred = _counters(client, out, k)
        why = ({c: pred[c] for c in ('inputs', 'steps', 'stamp_resync', 'late')},
               pred['message'], how)                           # one step each
        assert pred['inputs'] == str(k) and pred['steps'] == str(k - 1), why
        assert pred['stamp_resync'] == '0' and pred['late'] == '0', why
        t0 = min(out.stamped)
        assert client.spin_until(lambda: t0 + (k - 1) * MS in out.stamped or max(
            out.stamped) >= t0 + (k - 21) * MS, timeout=10.0)
        assert len(out.stamped) >= 20
        for t, y in out.stamped.items():     # each output is the simulation's at its step
            j = (t - t0) // MS
            assert (t - t0) % MS == 0 and j < k
            np.testing.assert_allclose(y, ep.Y[:, j], rtol=0, atol=1e-9)
        assert node.stop(signal.SIGINT) == 0
    finally:
        node.proc.send_signal(signal.SIGCONT)
        node.kill()


def test_pauses_with_fixed_stepping_publish_every_step(client, tmp_path) -> None:
    m = model()
    k = 1200
    ep = episode(m, k=k)
    node = NodeProcess(tmp_path, params(m.save(tmp_path / 'm.npz'), input_mode='array',
                                        stepping='fixed'))
    try:
        out = Outputs(client, node.fqn)
        pub = client.node.create_publisher(Float64MultiArray, '/t/pressures', RELIABLE)
        _connected(client, [pub], out)
        _stream(node, k, lambda j: pub.publish(Float64MultiArray(data=ep.U[:, j].tolist())))
        pred = _counters(client, out, k)
        # the timer integrates the stalled steps when it runs again: each one is published
        # (and the first output, at the first input, before any step)
        assert int(pred['steps']) >= k - 1, pred
        assert pred['outputs_published'] == str(int(pred['steps']) + 1), pred
        stamps = sorted(out.stamped)
        assert len(stamps) == len(out.times), 'an output published twice'
        assert np.all(np.diff(stamps) % MS == 0)
        assert node.stop(signal.SIGINT) == 0
    finally:
        node.proc.send_signal(signal.SIGCONT)
        node.kill()


def _held_sensor_run(client, folder: Path) -> tuple[dict, dict, list]:
    """One run of the held-sensor scenario below.

    Returns the late counts per topic, the prediction diagnostics and the WARN statuses
    that name late inputs.
    """
    m = model()
    k = 1200
    ep = episode(m, k=k)
    folder.mkdir()
    node = NodeProcess(folder, params(m.save(folder / 'm.npz'), publish_rate_hz=50.0))
    held: list[int] = []
    window = range(800, 1050)                       # PAUSES: the node stops at 800 for 150 ms
    try:
        out = Outputs(client, node.fqn)
        pubs = _publishers(client)
        _connected(client, pubs, out)

        def send(j: int) -> None:
            for i, p in enumerate(pubs[:-1]):
                p.publish(pressure(ep.U[i, j], T0_NS + j * MS))
            if j == window.stop:                    # ... and sends them, in order, 250 ms on
                for h in held:
                    pubs[-1].publish(pressure(ep.U[len(pubs) - 1, h], T0_NS + h * MS))
            if j in window:
                held.append(j)                      # the last sensor holds its samples ...
            else:
                pubs[-1].publish(pressure(ep.U[len(pubs) - 1, j], T0_NS + j * MS))

        _stream(node, k, send)
        pred = _counters(client, out, 3 * k)
        late = {tp: int(out.status(f': input {tp}')['late']) for tp in TOPICS}
        warned = [st for arr in out.diagnostics for st in arr.status
                  if 'arrived after their step was taken' in st.message]
        assert node.stop(signal.SIGINT) == 0
        return late, pred, warned
    finally:
        node.proc.send_signal(signal.SIGCONT)
        node.kill()


def test_a_sensor_held_up_across_a_pause_is_counted_late_and_warned(client, tmp_path) -> None:
    # The node stopped for 150 ms took every input at its own step above. Here the last
    # chamber's sensor is held up across that pause too: it sends nothing for 250 ms, then
    # its held samples in order, beyond max_lag_s (0.1 s) behind the other chambers, which
    # moved the model on. The late ones are counted, on that topic only, and diagnostics WARN.
    # In one CI run another chamber's stream fell more than max_lag_s behind too (795 late
    # on chamber 1, 0 on chamber 2): the node counted what it saw, but that run is not the
    # scenario, so it is run once more and must then hold.
    for attempt in range(2):
        late, pred, warned = _held_sensor_run(client, tmp_path / f'run{attempt}')
        if all(late[tp] == 0 for tp in TOPICS[:-1]):
            break
    assert late[TOPICS[-1]] > 0 and all(late[tp] == 0 for tp in TOPICS[:-1]), late
    assert int(pred['late']) == sum(late.values())
    assert warned, 'no WARN names the late inputs'
    level = warned[0].level
    assert (level[0] if isinstance(level, bytes) else level) == 1          # WARN


@pytest.mark.parametrize('executor', ['events', 'single_threaded'])
def test_a_pause_makes_late_inputs_counted_and_warned(client, tmp_path, executor) -> None:
    m = model()
    k = 1200
    ep = episode(m, k=k)
    node = NodeProcess(tmp_path, params(m.save(tmp_path / 'm.npz'),     # max_lag_s 0.1 s
                                        publish_rate_hz=50.0, executor=executor))
    try:
        out = Outputs(client, node.fqn)
        pubs = _publishers(client)
        _connected(client, pubs, out)

        def send(j: int) -> None:
            for i, p in enumerate(pubs):
                p.publish(pressure(ep.U[i, j], T0_NS + j * MS))

        _stream(node, k, send)
        pred = _counters(client, out, 3 * k)
        late = int(pred['late'])
        assert late == sum(int(out.status(f': input {tp}')['late']) for tp in TOPICS)
        worst = max(np.max(np.abs(y - ep.Y[:, (t - T0_NS) // MS]))
                    for t, y in out.stamped.items())
        warned = [st for arr in out.diagnostics for st in arr.status
                  if 'arrived after their step was taken' in st.message]
        if late == 0:                   # nothing was late: the outputs are the simulation
            assert worst <= 1e-9, worst
        else:                           # the output is off the simulation: never silently
            assert warned, [st.message for arr in out.diagnostics for st in arr.status]
            level = warned[0].level
            assert (level[0] if isinstance(level, bytes) else level) == 1
            assert 'ms behind the model' in warned[0].message
        assert node.stop(signal.SIGINT) == 0
    finally:
        node.proc.send_signal(signal.SIGCONT)
        node.kill()
