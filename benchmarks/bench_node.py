"""The predictor node under real rclpy at 1 kHz, against a bare rclpy echo node.

Run: ``.venv/bin/python benchmarks/bench_node.py [--seconds 4] [--modes array,per_chamber]``
(needs rclpy: a sourced Jazzy or the ros extra).

Four processes: the installed ``predictor`` (event stepping, reliable QoS); beside it, on
the same inputs at the same time (so under the same load), a bare rclpy echo node (this
file, ``--role echo``: subscribe -> publish the
same message, with the node's executor; with per-chamber input it subscribes to all six
topics, as the node does, and echoes the last chamber, one message per step as the node's
output) as the floor of what rclpy can do on this machine; a publisher (``--role
publisher``: six ``FluidPressure`` topics at 1 kHz stamped on a 1 ms grid, or one
``Float64MultiArray`` at 1 kHz); and this process, which subscribes to the node's
``~/output_stamped`` and the echoes and measures.

Printed, per input mode (``array``, ``per_chamber``): % of inputs applied at their stamp /
late / lost (from the node's counters); latency publish -> first ``~/output`` that includes
the input (p50 / p99 / max) for the node and for the echo node; node CPU % of one core and
RSS, idle and under input; the largest difference between the published outputs and
``model.simulate`` of the inputs sent (un-stamped arrays are placed on the sender's sequence
by the node, one step each; if that was resynchronised, the inputs as the node held them are
read off the outputs greedily -- an upper bound, since a wrong guess also counts).
"""

# ruff: noqa: E402  (thread settings must precede the numpy import)
from __future__ import annotations

import os

for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(50 + os.getpid() % 50))

import argparse
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
import yaml

MS = 1_000_000
M_IN, R, P = 6, 16, 40
TOPICS = [f'/bench/chamber_{i}' for i in range(1, M_IN + 1)]
ARRAY = '/bench/pressures'
ECHO = '/bench_echo'


def _model():
    from soft_rom.models import SecondOrderModel

    rng = np.random.default_rng(0)
    M = rng.standard_normal((R, R))
    K = (M @ M.T / R + 4.0 * np.eye(R)) * 100.0
    return SecondOrderModel(K, 0.5 * np.eye(R) + 0.01 * K, rng.standard_normal((R, M_IN)),
                            0.01 * rng.standard_normal((P, R)), dt=1e-3,
                            y_ref=rng.standard_normal(P))


def _inputs(k: int) -> np.ndarray:
    rng = np.random.default_rng(1)
    return np.repeat(rng.uniform(0.0, 1.0, (M_IN, k // 20 + 1)), 20, axis=1)[:, :k]


def _qos():
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                      reliability=ReliabilityPolicy.RELIABLE)


# -- roles run in their own processes ---------------------------------------------------------
def role_publisher(mode: str, seconds: float, out: str, expect: int) -> None:
    """Publish the inputs at 1 kHz once ``expect`` subscribers matched; save publish times."""
    import rclpy
    from sensor_msgs.msg import FluidPressure
    from std_msgs.msg import Float64MultiArray

    rclpy.init()
    node = rclpy.create_node('bench_publisher')
    qos = _qos()
    if mode == 'per_chamber':
        pubs = [node.create_publisher(FluidPressure, tp, qos) for tp in TOPICS]
    else:
        pubs = [node.create_publisher(Float64MultiArray, ARRAY, qos)]
    end = time.monotonic() + 30
    while any(p.get_subscription_count() < expect for p in pubs) and time.monotonic() < end:
        time.sleep(0.01)
    time.sleep(0.5)
    k = int(seconds * 1000)
    U = _inputs(k)
    sent = np.zeros(k, dtype=np.int64)
    t0 = (time.time_ns() // MS + 20) * MS         # the stamp grid, on the wall clock
    msgs = [FluidPressure() for _ in TOPICS] if mode == 'per_chamber' else None
    arr = Float64MultiArray()
    start = time.monotonic_ns()
    for j in range(k):
        due = start + j * MS
        while True:
            left = due - time.monotonic_ns()
            if left <= 0:
                break
            time.sleep(left * 1e-9 if left > 200_000 else 0)
        if msgs is not None:
            sec, nsec = divmod(t0 + j * MS, 1_000_000_000)
            for i, (pub, msg) in enumerate(zip(pubs, msgs)):
                msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nsec
                msg.fluid_pressure = float(U[i, j])
                pub.publish(msg)
        else:
            arr.data = U[:, j].tolist()
            pubs[0].publish(arr)
        sent[j] = time.time_ns()
    np.savez(out, sent=sent, t0=t0, U=U)
    time.sleep(0.5)
    node.destroy_node()
    rclpy.try_shutdown()


def role_echo(mode: str, executor: str) -> None:
    """A bare rclpy node: every input message published again, unchanged."""
    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions
    from sensor_msgs.msg import FluidPressure
    from std_msgs.msg import Float64MultiArray

    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node('bench_echo')
    qos = _qos()
    if mode == 'per_chamber':
        # the node's input load (all six topics), the node's output rate (one per step)
        pub = node.create_publisher(FluidPressure, ECHO + TOPICS[-1], qos)
        for tp in TOPICS[:-1]:
            node.create_subscription(FluidPressure, tp, lambda msg: None, qos)
        node.create_subscription(FluidPressure, TOPICS[-1], pub.publish, qos)
    else:
        pub = node.create_publisher(Float64MultiArray, ECHO + ARRAY, qos)
        node.create_subscription(Float64MultiArray, ARRAY, pub.publish, qos)
    if executor == 'events':
        from rclpy.experimental import EventsExecutor

        ex = EventsExecutor()
    else:
        ex = SingleThreadedExecutor()
    ex.add_node(node)
    stop = threading.Event()        # as the predictor: a flag, checked every 0.1 s
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


# -- measuring process ------------------------------------------------------------------------
class Sampler(threading.Thread):
    """CPU time (ticks) and RSS of a process, every 50 ms, with wall-clock stamps."""

    def __init__(self, pid: int) -> None:
        super().__init__(daemon=True)
        self.pid = pid
        self.samples: list[tuple[int, float, int]] = []
        self.stop = threading.Event()
        self.hz = os.sysconf('SC_CLK_TCK')

    def read(self) -> tuple[int, float, int] | None:
        try:
            stat = Path(f'/proc/{self.pid}/stat').read_text().rsplit(')', 1)[1].split()
            rss = next(int(line.split()[1]) for line in
                       Path(f'/proc/{self.pid}/status').read_text().splitlines()
                       if line.startswith('VmRSS'))
        except (OSError, StopIteration):
            return None
        return time.time_ns(), (int(stat[11]) + int(stat[12])) / self.hz, rss

    def run(self) -> None:
        while not self.stop.is_set():
            s = self.read()
            if s is not None:
                self.samples.append(s)
            time.sleep(0.05)

    def cpu(self, t_from: int, t_to: int) -> tuple[float, float]:
        """CPU % of one core and the largest RSS (MB) between two wall times."""
        win = [s for s in self.samples if t_from <= s[0] <= t_to]
        if len(win) < 2:
            return float('nan'), float('nan')
        (a, ca, _), (b, cb, _) = win[0], win[-1]
        return 100.0 * (cb - ca) / ((b - a) * 1e-9), max(s[2] for s in win) / 1024.0


def _spawn(args: list[str], log: Path) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED='1', RCUTILS_COLORIZED_OUTPUT='0')
    return subprocess.Popen(args, stdout=log.open('wb'), stderr=subprocess.STDOUT, env=env)


def _pct(x: np.ndarray, q: float) -> float:
    return float(np.percentile(x, q)) if x.size else float('nan')


def _lat(x: np.ndarray) -> str:
    if not x.size:
        return 'n/a'
    return (f'p50 {_pct(x, 50) / 1e6:7.3f}  p99 {_pct(x, 99) / 1e6:7.3f}  '
            f'max {x.max() / 1e6:7.3f} ms')


def run_mode(mode: str, seconds: float, idle: float, work: Path,
             executor: str = 'events') -> dict:
    """Node phase then echo phase for one input mode; the figures."""
    from diagnostic_msgs.msg import DiagnosticArray
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import FluidPressure, JointState
    from std_msgs.msg import Float64MultiArray

    model = _model()
    path = model.save(work / 'model.npz')
    label = mode
    params = {'model_path': str(path), 'input_mode': mode, 'input_topics': TOPICS,
              'array_topic': ARRAY, 'input_qos': 'reliable', 'qos_depth': 1000,
              'measured_topic': '', 'diagnostics_rate_hz': 2.0, 'publish_rate_hz': 0.0,
              'executor': executor}
    pfile = work / f'{label}.yaml'
    pfile.write_text(yaml.safe_dump({'/**': {'ros__parameters': params}}), encoding='utf-8')
    exe = str(Path(sys.executable).parent / 'predictor')
    me = [sys.executable, str(Path(__file__).resolve())]
    n_topics = M_IN if mode == 'per_chamber' else 1

    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    sub = rclpy.create_node('bench_measure', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(sub)
    qos = _qos()
    got: list[tuple[int, int, np.ndarray]] = []      # (arrival, model time, outputs)
    diags: list[DiagnosticArray] = []
    sub.create_subscription(JointState, '/bench_predictor/output_stamped',
                            lambda m: got.append((time.time_ns(), m.header.stamp.sec
                                                  * 1_000_000_000 + m.header.stamp.nanosec,
                                                  np.array(m.position))), qos)
    sub.create_subscription(DiagnosticArray, '/diagnostics', diags.append, 10)
    echoed: list[tuple[int, int]] = []                 # (arrival, stamp or index)
    if mode == 'per_chamber':
        sub.create_subscription(FluidPressure, ECHO + TOPICS[-1], lambda m: echoed.append(
            (time.time_ns(), m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)),
            qos)
    else:
        sub.create_subscription(Float64MultiArray, ECHO + ARRAY,
                                lambda m: echoed.append((time.time_ns(), 0)), qos)

    def spin_while(cond, timeout: float) -> None:
        end = time.monotonic() + timeout
        while cond() and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.01)

    def subscribed(topics: list[str], n: int) -> bool:
        return all(sub.count_subscribers(tp) >= n for tp in topics)

    out: dict = {'mode': label}
    inputs = TOPICS if mode == 'per_chamber' else [ARRAY]
    # ---- the predictor node and the echo node, side by side on the same inputs
    node = _spawn([exe, '--ros-args', '-r', '__node:=bench_predictor', '--params-file',
                   str(pfile)], work / f'node_{label}.log')
    echo = _spawn(me + ['--role', 'echo', '--mode', mode, '--executor', executor],
                  work / f'echo_{label}.log')
    sampler, echo_sampler = Sampler(node.pid), Sampler(echo.pid)
    sampler.start()
    echo_sampler.start()
    spin_while(lambda: not subscribed(inputs, 2), 30)
    spin_while(lambda: sub.count_publishers('/bench_predictor/output_stamped') < 1, 10)
    t_idle = time.time_ns()
    spin_while(lambda: True, idle)
    out['idle_cpu'], out['idle_rss'] = sampler.cpu(t_idle, time.time_ns())
    pub_file = work / f'sent_{label}.npz'
    pub = _spawn(me + ['--role', 'publisher', '--mode', mode, '--seconds', str(seconds),
                       '--out', str(pub_file), '--expect', '2'], work / f'pub_{label}.log')
    spin_while(lambda: pub.poll() is None, seconds + 60)
    spin_while(lambda: True, 1.0)
    n_diag = len(diags)
    spin_while(lambda: len(diags) < n_diag + 2, 5)
    sent = np.load(pub_file)
    s_ns, t0, U = sent['sent'], int(sent['t0']), sent['U']
    out['busy_cpu'], out['busy_rss'] = sampler.cpu(int(s_ns[0]), int(s_ns[-1]))
    out['echo_cpu'], out['echo_rss'] = echo_sampler.cpu(int(s_ns[0]), int(s_ns[-1]))
    node.send_signal(signal.SIGINT)
    echo.send_signal(signal.SIGINT)
    out['exit'] = node.wait(20)
    echo.wait(20)
    sampler.stop.set()
    echo_sampler.stop.set()
    status = {kv.key: kv.value for st in diags[-1].status if st.name.endswith(': prediction')
              for kv in st.values}
    k = U.shape[1]
    n_sent = k * n_topics
    n_in, n_late = int(status.get('inputs', 0)), int(status.get('late', 0))
    dropped = sum(int(status.get(c, 0)) for c in ('wrong_length', 'nonfinite', 'bad_time',
                                                     'backwards', 'input_out_of_envelope'))
    out['at_stamp'] = 100.0 * (n_in - n_late - dropped) / n_sent
    out['late'] = 100.0 * n_late / n_sent
    out['lost'] = 100.0 * (n_sent - n_in) / n_sent
    out['outputs'] = len(got)
    arrival = np.array([g[0] for g in got], dtype=np.int64)
    times = np.array([g[1] for g in got], dtype=np.int64)
    steps = np.unique(times)
    sequenced = mode == 'array' and steps.size == k and np.all(np.diff(steps) == MS)
    if mode == 'per_chamber' or sequenced:
        Y = model.simulate(U)
        if sequenced:       # one array per step, from the first one on
            t0 = int(steps[0])
        j = (times - t0) // MS
        ok = (j >= 0) & (j < k) & ((times - t0) % MS == 0)
        out['max_diff'] = max(float(np.max(np.abs(got[i][2] - Y[:, j[i]])))
                              for i in np.flatnonzero(ok)) if ok.any() else float('nan')
        first = {}
        for a, jj in zip(arrival[ok], j[ok]):
            first.setdefault(int(jj), int(a))
        lat = np.array([first[jj] - s_ns[jj] for jj in range(k) if jj in first])
    else:   # not one step per array (resynchronised): the inputs as the outputs show them
        out['max_diff'] = _array_diff(model, U, times, [g[2] for g in got])
        # the i-th step published <-> the i-th array sent (approximate after a resync)
        order = np.argsort(times, kind='stable')
        a_sorted = arrival[order]
        lat = np.array([a - s for a, s in zip(a_sorted, s_ns)])
    out['node_lat'] = lat
    if mode == 'per_chamber':
        first = {}
        for a, st in echoed:
            first.setdefault((st - t0) // MS, a)
        elat = np.array([first[jj] - s_ns[jj] for jj in range(k) if jj in first])
    else:
        elat = np.array([a - s for (a, _), s in zip(echoed, s_ns)])
    out['echo_lat'] = elat
    out['echo_lost'] = 100.0 * (k - len(elat)) / k
    ex.shutdown()
    sub.destroy_node()
    rclpy.try_shutdown(context=ctx)
    return out


def _array_diff(model, U: np.ndarray, times: np.ndarray, ys: list[np.ndarray]) -> float:
    """Largest |output - model run with the inputs as the node held them| (array mode).

    Un-stamped arrays take the node's reception time, so the step each input started at is
    not known to the sender; the output has no direct term (``y = E q``), so the input held
    at step n shows in the output of step n + 1. Each step's input is chosen among the
    one held before and the next two sent (inputs in order), by the exact model step
    ``x <- A_h x + B_h u`` the node runs; the figure is the worst remaining difference.
    """
    order = np.argsort(times, kind='stable')
    t = times[order]
    if t.size < 2 or np.any(np.diff(t) != MS):
        return float('nan')          # a step missing (or repeated): reported as nan
    Y = [ys[i] for i in order]
    sys_h = model.discretize(1e-3)
    A, B, C, y_ref = sys_h.A, sys_h.B, sys_h.C, model.y_ref
    x = np.zeros(A.shape[0])
    worst = float(np.max(np.abs(C @ x + y_ref - Y[0])))
    j = 0
    for n in range(1, t.size):
        best = None
        for cand in range(j, min(j + 3, U.shape[1])):
            xn = A @ x + B @ U[:, cand]
            d = float(np.max(np.abs(C @ xn + y_ref - Y[n])))
            if best is None or d < best[0]:
                best = (d, cand, xn)
        worst = max(worst, best[0])
        _, j, x = best
    return worst


def main() -> None:
    """Parse the arguments and run the roles or the whole benchmark."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=4.0)
    ap.add_argument('--idle', type=float, default=3.0)
    ap.add_argument('--modes', default='array,per_chamber')
    ap.add_argument('--executor', choices=('events', 'single_threaded'),
                    default='events', help="the node's executor parameter (and the echo's)")
    ap.add_argument('--role', choices=('publisher', 'echo'), default=None)
    ap.add_argument('--mode', default='array')
    ap.add_argument('--out', default='')
    ap.add_argument('--expect', type=int, default=1)
    args = ap.parse_args()
    if args.role == 'publisher':
        return role_publisher(args.mode, args.seconds, args.out, args.expect)
    if args.role == 'echo':
        return role_echo(args.mode, args.executor)
    work = Path(tempfile.mkdtemp(prefix='bench_node_'))
    print(f'bench_node: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}; '
          f'{args.seconds:g} s at 1 kHz per phase; model r={R}, {M_IN} inputs, {P} outputs')
    try:
        for mode in args.modes.split(','):
            r = run_mode(mode, args.seconds, args.idle, work, args.executor)
            what = '6 FluidPressure topics' if mode == 'per_chamber' else '1 Float64MultiArray'
            print(f'\n== {mode}: {what} at 1 kHz, reliable QoS, node executor '
                  f'{args.executor} ==')
            print(f'  inputs applied at stamp {r["at_stamp"]:6.2f} %   late {r["late"]:6.2f} %'
                  f'   lost {r["lost"]:6.2f} %   (outputs received {r["outputs"]})')
            print(f'  latency node   {_lat(r["node_lat"])}')
            print(f'  latency echo   {_lat(r["echo_lat"])}   (echo lost {r["echo_lost"]:.2f} %)')
            ratio = _pct(r['node_lat'], 99) / _pct(r['echo_lat'], 99)
            print(f'  p99 node / echo  {ratio:.2f}   (target <= 2)')
            print(f'  node CPU  idle {r["idle_cpu"]:5.1f} %   under input {r["busy_cpu"]:5.1f} %'
                  f'   (echo node {r["echo_cpu"]:5.1f} %)   RSS {r["busy_rss"]:.0f} MB')
            print(f'  max |output - model.simulate| {r["max_diff"]:.3g}   node exit {r["exit"]}')
    finally:
        if os.environ.get('BENCH_KEEP') is None:
            shutil.rmtree(work, ignore_errors=True)
        else:
            print(f'logs in {work}')


if __name__ == '__main__':
    main()
