"""``ros2 run soft_rom controller``: MPC on a ROM as a ROS 2 node, a thin shell.

The core is :class:`soft_rom.control.Controller` (offset-free estimator + MPC), the same the
in-process loop (``soft-rom control``) runs. The node:

* takes the reference as a parameter (``reference``: ``wave:…``, ``step:…``, an ``.npz``,
  ``episode:BAG``; its time 0 is ``reference_t0_s`` on the node's clock, default the first
  control tick) or from a topic
  (``reference_topic``, ``geometry_msgs/PoseArray``: the desired centerline at
  ``header.stamp``; samples are interpolated, the last one held);
* takes the ROM state from the predictor node (``state_topic``, its ``~/state``; the
  predictor runs the model on the commands this node publishes) and corrects the output
  disturbance with the measured centerline (``measured_topic``, best effort by default:
  ``measured_qos``); with ``state_topic: ''``
  it estimates the state itself from the measured centerline, as ``soft-rom control`` does;
* every ``step_s`` (sim time with ``use_sim_time``) publishes the pressure commands on the
  predictor's inputs, configured with the predictor's own parameters (``input_mode``,
  ``input_topics``, ``array_topic``, ``input_scale``, ``input_offset``): one
  ``sensor_msgs/FluidPressure`` per chamber stamped with the control time
  (``per_chamber``), or all chambers in one ``std_msgs/Float64MultiArray`` on
  ``array_topic`` (``array``; no header: the receiver stamps it on arrival), as
  ``(u - input_offset) / input_scale`` so that the predictor reads back ``u``;
* publishes ``/diagnostics`` (status, solve and step time, the previous tick's time and the
  longest since the last message, tracking error, saturation, counters, the last input
  dropped and why, publishers on its topics: :mod:`soft_rom.ros.control_diagnostics`) at
  ``diagnostics_rate_hz`` (default 1 Hz, as the predictor) and at once when the status
  changes, and the reference shape on ``~/reference`` (``PoseArray``) at
  ``reference_rate_hz`` (default 30 Hz) while someone subscribes: both on timers of their
  own, so that the control tick only estimates, solves and publishes the commands;
* on shutdown logs the whole control tick's time (estimate, solve, publish), p50 / p99 /
  max in wall and thread CPU time, and p99 as a fraction of the control step.

Bad input never stops it: a measurement, state or reference of the wrong size, with NaN, or
stamped in the past is dropped and counted; without a fresh state or measurement, or when
the QP is infeasible or fails, the last command is held, clipped into the bounds
(diagnostics WARN with the reason).
"""

from __future__ import annotations

from collections import deque
import math
import signal
import sys
import threading
import time
from typing import Any
import warnings

from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Pose, PoseArray
import numpy as np
from rcl_interfaces.msg import ParameterDescriptor
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import FluidPressure, JointState
from std_msgs.msg import Float64MultiArray

from soft_rom.control import Controller, EstimatorConfig, MPCConfig, parse_reference, Reference
from soft_rom.control.reference import _model_outputs
from soft_rom.errors import ReferenceReachWarning, UntrustedModelWarning
from soft_rom.predictor.conversions import (
    array_to_data,
    ns_to_stamp,
    poses_to_points,
    set_points,
    stamp_to_ns,
)
from soft_rom.ros.control_diagnostics import control_diagnostics
from soft_rom.ros.node_params import (
    init_rclpy,
    rclpy_reason,
    warn_unknown_parameters,
    watch_sim_clock,
)

__all__ = ['ControllerNode', 'main']

DEFAULT_TOPICS = [f'/soft_robot/pressure/chamber_{i}' for i in range(1, 7)]
INPUT_MODES = ('per_chamber', 'array')


class StartupError(Exception):
    """A bad parameter or model at start-up (logged as one line): exit status 1."""


class ControllerNode(Node):
    """Publishes pressure commands that make the measured centerline follow a reference."""

    def __init__(self, node_name: str = 'soft_rom_controller', **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        try:
            core = self._declare_parameters()
        except ParameterException as err:       # a value of the wrong type
            self.get_logger().error(f'cannot start: parameter {rclpy_reason(err)}')
            raise StartupError(rclpy_reason(err)) from None
        self._start_core(core)
        self.t0: float | None = None
        self.samples: list[tuple[float, np.ndarray]] = []
        self._create_entities()
        self.last: Any = None      # (stamp, command) of the last tick, for diagnostics
        self.callback_errors = 0
        # the whole tick (estimate, solve, publish): wall and thread CPU seconds, and the CPU
        # seconds of the estimate and solve alone
        self.ticks: deque[tuple[float, float, float]] = deque(maxlen=100_000)
        self.tick_max = 0.0        # the longest tick (wall s) since the last diagnostics
        self._prepare_reference_message()

    def _declare_parameters(self) -> dict[str, Any]:
        """Declare the (read-only) parameters; returns the settings of the core.

        The topics, the command conversion and the reference frame become attributes.
        """

        def declare(name: str, value: Any, text: str) -> Any:
            return self.declare_parameter(name, value, ParameterDescriptor(
                description=text, read_only=True)).value

        core: dict[str, Any] = {}
        core['model_path'] = str(declare('model_path', '', 'linear model file (.npz)'))
        core['spec'] = str(declare('reference', '',
                                   'built-in reference or .npz (empty: the topic)'))
        self.reference_topic = str(declare('reference_topic', '~/reference_in',
                                           'PoseArray reference samples'))
        self.measured_topic = str(declare('measured_topic', '/soft_robot/centerline',
                                          'measured centerline (PoseArray)'))
        self.measured_qos = str(declare('measured_qos', 'sensor_data', 'QoS of the measured '
                                        'centerline: sensor_data (best effort: takes reliable '
                                        'and best-effort publishers) or reliable'))
        self.state_topic = str(declare('state_topic', '/soft_rom_predictor/state',
                                       "the predictor's ~/state ('' : estimate it here)"))
        self.input_mode = str(declare('input_mode', 'per_chamber',
                                      "the predictor's input_mode: per_chamber or array"))
        self.topics = list(declare('input_topics', DEFAULT_TOPICS, 'pressure command topics'))
        self.array_topic = str(declare('array_topic', '/soft_robot/pressures',
                                       'Float64MultiArray command topic (input_mode array)'))
        self.input_scale = float(declare('input_scale', 1.0, 'published value = (u - '
                                          'input_offset) / input_scale, as the predictor reads'))
        self.input_offset = float(declare('input_offset', 0.0, 'see input_scale'))
        core['step'] = float(declare('step_s', 0.01, 'control step, s'))
        core['horizon'] = float(declare('horizon_s', 0.2, 'prediction horizon, s'))
        core['rate_weight'] = float(declare('rate_weight', MPCConfig.rate_weight,
                                            'weight of input increments'))
        core['noise'] = float(declare('sensor_noise', 5e-4, 'measurement noise std, m'))
        core['sensor_rate'] = float(declare('sensor_rate_hz', 120.0,
                                            'measured centerline rate'))
        core['stale'] = float(declare('stale_after_s', 0.1,
                                      'hold the command beyond this age'))
        core['duration'] = float(declare('reference_duration_s', 60.0,
                                         'length of a built-in one'))
        self.frame_id = str(declare('frame_id', 'world', 'frame of ~/reference and of the '
                                    'measured centerline (another one is dropped)'))
        self.diag_rate = float(declare('diagnostics_rate_hz', 1.0, 'rate of /diagnostics '
                                       '(and at once when the status changes)'))
        self.ref_rate = float(declare('reference_rate_hz', 30.0, 'rate of ~/reference while '
                                      'someone subscribes'))
        self.ref_t0 = float(declare('reference_t0_s', -1.0, "clock time of the reference's "
                                    't = 0 (< 0: the first control tick)'))
        return core

    def _start_core(self, c: dict[str, Any]) -> None:
        """Check the settings, load the model, build the controller and the fixed reference.

        Raises
        ------
        StartupError
            Logged as one line first.
        """
        from soft_rom.models import load_model
        try:
            if self.measured_qos not in ('sensor_data', 'reliable'):
                raise ValueError(f'measured_qos {self.measured_qos!r} is not sensor_data or '
                                 'reliable')
            if self.input_mode not in INPUT_MODES:
                raise ValueError(f'input_mode {self.input_mode!r} is not one of '
                                 f'{", ".join(INPUT_MODES)}')
            for name, rate in (('diagnostics_rate_hz', self.diag_rate),
                               ('reference_rate_hz', self.ref_rate)):
                if not 0.01 <= rate <= 100.0:
                    raise ValueError(f'{name} must be between 0.01 and 100; got {rate!r}')
            if not (math.isfinite(self.input_scale) and self.input_scale != 0
                    and math.isfinite(self.input_offset)):
                raise ValueError(f'input_scale ({self.input_scale!r}) must be finite and not 0 '
                                 f'and input_offset ({self.input_offset!r}) finite')
            if not c['model_path']:
                raise ValueError('model_path is empty (give -p model_path:=FILE)')
            if not (math.isfinite(c['duration']) and c['duration'] > 0):
                raise ValueError(f"reference_duration_s must be finite and > 0; got "
                                 f"{c['duration']!r}")
            self.model = load_model(c['model_path'])
            self.distrust = '; '.join(self.model.trust_issues())
            if self.distrust:
                self.get_logger().warning(f'model not trusted: {self.distrust}; the '
                                          'diagnostics stay at WARN while it controls')
            if self.input_mode == 'per_chamber' and len(self.topics) != self.model.n_inputs:
                raise ValueError(f'the model has {self.model.n_inputs} inputs but input_topics '
                                 f'lists {len(self.topics)} topics')
            external = bool(self.state_topic)
            est = EstimatorConfig(measurement_noise=max(c['noise'], 1e-5),
                                  sensor_rate=c['sensor_rate'],
                                  **({'process_noise': 0.0} if external else {}))
            with warnings.catch_warnings():     # logged above, as the node's own line
                warnings.simplefilter('ignore', UntrustedModelWarning)
                self.core = Controller(self.model, MPCConfig(
                    step=c['step'], horizon=c['horizon'], rate_weight=c['rate_weight']), est,
                    stale_after=c['stale'], external_state=external)
            self.fixed_ref = parse_reference(c['spec'], self.model, duration=c['duration']) \
                if c['spec'] else None
            why = self._logged(self.core.check_reference, self.fixed_ref) \
                if self.fixed_ref is not None else ''
            if why:                             # a wave too fast for the control step
                raise ValueError(why)
        except (OSError, ValueError) as err:
            self.get_logger().error(f'cannot start: {err}')
            raise StartupError(str(err)) from None

    def _logged(self, fn: Any, *args: Any) -> Any:
        """``fn(*args)`` with the warnings it gives (a target out of reach) logged, not printed."""
        with warnings.catch_warnings(record=True) as held:
            warnings.simplefilter('always', ReferenceReachWarning)
            out = fn(*args)
        for w in held:
            self.get_logger().warning(str(w.message), throttle_duration_sec=5.0)
        return out

    def _create_entities(self) -> None:
        """The command and reference publishers, the subscriptions and the control timer."""
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        if self.input_mode == 'array':
            self.pubs = []
            self.pub_array = self.create_publisher(Float64MultiArray, self.array_topic, qos)
            self.array_msg = Float64MultiArray()
        else:
            self.pubs = [self.create_publisher(FluidPressure, t, qos) for t in self.topics]
        self.cmd_msgs = [FluidPressure() for _ in self.pubs]    # reused: a tick builds none
        self.pub_ref = self.create_publisher(PoseArray, '~/reference', 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        # a motion-capture driver often publishes best effort: a reliable reader never
        # matches it; a best-effort one takes both
        measured_qos = qos if self.measured_qos == 'reliable' else QoSProfile(
            depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)
        self.create_subscription(PoseArray, self.measured_topic, self._on_measured,
                                 measured_qos)
        if self.state_topic:
            self.create_subscription(JointState, self.state_topic, self._on_state, qos)
        if self.reference_topic:
            self.create_subscription(PoseArray, self.reference_topic, self._on_reference, qos)
        self.create_timer(self.core.h, self._on_tick)
        self.create_timer(1.0 / self.diag_rate, self._on_diagnostics_timer)
        self.create_timer(1.0 / self.ref_rate, self._publish_reference)

    def _prepare_reference_message(self) -> None:
        """``~/reference`` reused at every publish, and where the model's outputs go in it."""
        n = len([nm for nm in self.model.output_names if nm.startswith('x')])
        self.ref_msg = PoseArray()
        self.ref_msg.header.frame_id = self.frame_id
        self.ref_msg.poses = [Pose() for _ in range(n)]
        self.ref_positions = [p.position for p in self.ref_msg.poses]
        # the model outputs named x<i> / z<i> (i <= n): their rows and (point, coordinate)
        rows, where = [], []
        for row, nm in enumerate(self.model.output_names):
            if nm[:1] in 'xz' and nm[1:].isdigit() and 1 <= int(nm[1:]) <= n:
                rows.append(row)
                where.append((int(nm[1:]) - 1, 'xyz'.index(nm[0])))
        self.ref_rows = np.array(rows, dtype=int)
        self.ref_where = tuple(np.array(where, dtype=int).reshape(-1, 2).T)

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _guard(self, what: str, err: Exception) -> None:
        self.callback_errors += 1
        self.get_logger().warning(f'{what}: {type(err).__name__}: {err} (dropped)',
                                  throttle_duration_sec=5.0)

    def _on_measured(self, msg: PoseArray) -> None:
        try:
            frame = msg.header.frame_id
            why = ''
            if len(msg.poses) * 2 != self.model.n_outputs:
                why = (f'{len(msg.poses)} poses; the model has {self.model.n_outputs // 2} '
                       'centerline points')
            elif frame and frame != self.frame_id:
                why = (f"frame_id {frame!r} is not this node's frame_id {self.frame_id!r} (no "
                       'transform is applied)')
            if why:
                self.core.counters.measurements_dropped += 1
                self.core.refused('measurement dropped', why)
            else:
                # an unstamped message (zero stamp) is taken at its arrival, as the predictor
                stamp_ns = stamp_to_ns(msg.header.stamp) or self.get_clock().now().nanoseconds
                why = self.core.measure(_model_outputs(self.model, poses_to_points(msg.poses)),
                                        stamp_ns * 1e-9)
            if why:
                self.get_logger().warning(f'measurement dropped: {why}',
                                          throttle_duration_sec=5.0)
        except Exception as err:  # noqa: BLE001 - the node never dies on a message
            self._guard('measured centerline', err)

    def _on_state(self, msg: JointState) -> None:
        try:
            why = self.core.set_state(np.asarray(msg.position, dtype=np.float64),
                                      stamp_to_ns(msg.header.stamp) * 1e-9)
            if why:
                self.get_logger().warning(f'state dropped: {why}', throttle_duration_sec=5.0)
        except Exception as err:  # noqa: BLE001
            self._guard('state', err)

    def _on_reference(self, msg: PoseArray) -> None:
        try:
            t = stamp_to_ns(msg.header.stamp) * 1e-9
            n = len(msg.poses)
            y = _model_outputs(self.model, poses_to_points(msg.poses)) \
                if 2 * n == self.model.n_outputs else np.zeros(n * 2)
            now = self._now()
            why = ''
            if y.size != self.model.n_outputs:
                why = f'{n} points; the model has {self.model.n_outputs // 2}'
            elif not np.all(np.isfinite(y)):
                why = 'NaN/Inf in the reference'
            elif t < now - self.core.h:
                why = f'stamped {now - t:.3f} s in the past'
            if why:
                self.core.counters.references_refused += 1
                self.core.refused('reference sample refused', why)
                self.get_logger().warning(f'reference sample refused: {why}',
                                          throttle_duration_sec=5.0)
                return
            self.samples = [s for s in self.samples if s[0] < t and s[0] >= now - 1.0]
            self.samples.append((t, y))
            ts = np.array([s[0] for s in self.samples])
            self._logged(self.core.set_reference, Reference(
                t=ts, Y=np.stack([s[1] for s in self.samples], axis=1), label='topic'))
        except Exception as err:  # noqa: BLE001
            self._guard('reference', err)

    def _on_tick(self) -> None:
        """Estimate, solve and publish the commands (and diagnostics if the status changed)."""
        w0, c0 = time.perf_counter(), time.thread_time()
        c_core = math.nan
        changed = False
        try:
            now = self._now()
            if self.t0 is None:
                self.t0 = now if self.ref_t0 < 0 else self.ref_t0
                if self.fixed_ref is not None:
                    f = self.fixed_ref
                    self.core.set_reference(Reference(t=f.t + self.t0, Y=f.Y, label=f.label))
            cmd = self.core.step(now)
            c_core = time.thread_time() - c0
            stamp = _time_msg(now)
            wire = (cmd.u - self.input_offset) / self.input_scale
            if self.input_mode == 'array':
                self.array_msg.data = array_to_data(wire)
                self.pub_array.publish(self.array_msg)
            for pub, msg, value in zip(self.pubs, self.cmd_msgs, wire.tolist()):
                msg.header.stamp = stamp
                msg.fluid_pressure = value
                pub.publish(msg)
            changed = self.last is None or self.last[1].status != cmd.status
            self.last = (stamp, cmd)
        except Exception as err:  # noqa: BLE001
            self._guard('control step', err)
        wall = time.perf_counter() - w0
        self.ticks.append((wall, time.thread_time() - c0, c_core))
        self.tick_max = max(self.tick_max, wall)
        if changed:
            self._on_diagnostics_timer()

    def _publish_reference(self) -> None:
        """``~/reference`` at the node's clock time, while someone subscribes."""
        ref = self.core.reference
        if ref is None or self.pub_ref.get_subscription_count() == 0:
            return
        try:
            now = self._now()
            y = ref.at([now])[:, 0]
            pts = np.zeros((len(self.ref_positions), 3))
            pts[self.ref_where] = y[self.ref_rows]
            self.ref_msg.header.stamp = _time_msg(now)
            set_points(self.ref_positions, pts)
            self.pub_ref.publish(self.ref_msg)
        except Exception as err:  # noqa: BLE001
            self._guard('reference publish', err)

    def _on_diagnostics_timer(self) -> None:
        """``/diagnostics`` for the last tick (its timer, or a tick whose status changed)."""
        if self.last is not None:
            try:
                self._diagnostics(*self.last)
            except Exception as err:  # noqa: BLE001
                self._guard('diagnostics', err)

    def tick_summary(self) -> str:
        """One line: the whole control tick's time, p50 / p99 / max, wall and CPU."""
        if not self.ticks:
            return 'no control tick ran'
        wall, cpu, core = (np.array(v) * 1e3 for v in zip(*self.ticks))
        w50, w99, c50, c99 = (float(np.percentile(a, q)) for a in (wall, cpu)
                              for q in (50, 99))
        k50, k99 = (float(np.nanpercentile(core, q)) if np.isfinite(core).any() else math.nan
                    for q in (50, 99))
        period = self.core.h * 1e3
        return (f'{len(wall)} control ticks (estimate, solve, publish): p50/p99/max '
                f'{w50:.3f}/{w99:.3f}/{wall.max():.3f} ms wall, CPU p50/p99 {c50:.3f}/'
                f'{c99:.3f} ms (estimate + solve {k50:.3f}/{k99:.3f}); p99 = '
                f'{100 * w99 / period:.1f} % (wall), {100 * c99 / period:.1f} % (CPU) of the '
                f'{period:g} ms step')

    def _diagnostics(self, stamp: TimeMsg, cmd: Any) -> None:
        self.pub_diag.publish(control_diagnostics(self, stamp, cmd))


def _time_msg(t: float) -> TimeMsg:
    """A ROS time message for ``t`` seconds on the node's clock."""
    sec, nsec = ns_to_stamp(int(round(t * 1e9)))
    return TimeMsg(sec=sec, nanosec=nsec)


def main(args: list[str] | None = None) -> int:
    """Run the node until SIGINT/SIGTERM; exit status 0 (1: bad model or parameter)."""
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT,
                                                                       signal.SIGTERM)}
    refused = init_rclpy(args)
    if refused is not None:
        for s, h in previous.items():
            signal.signal(s, h)
        print(f'soft_rom controller: bad command line (--ros-args): {refused}',
              file=sys.stderr)
        return 1
    node = None
    code = 0
    executor = SingleThreadedExecutor()
    try:
        node = ControllerNode()
        warn_unknown_parameters(node)
        watch_sim_clock(node)
        executor.add_node(node)
        while not stop.is_set() and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
    except StartupError:
        code = 1
    except KeyboardInterrupt:
        pass
    finally:
        executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.get_logger().info(node.tick_summary())
            node.destroy_node()
        rclpy.try_shutdown()
        for s, h in previous.items():
            signal.signal(s, h)
    return code


if __name__ == '__main__':  # pragma: no cover
    sys.exit(main())
