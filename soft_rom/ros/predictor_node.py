"""``ros2 run soft_rom predictor``: the ROM predictor node (Jazzy rclpy), a thin shell.

All behaviour lives in :class:`soft_rom.predictor.Predictor`; this node reads parameters
(:mod:`soft_rom.ros.params`, ``config/predictor.yaml``), converts messages
(:mod:`soft_rom.ros.conversions`), calls the core and publishes:

* ``~/centerline`` (``geometry_msgs/PoseArray``), ``~/centerline_marker``
  (``visualization_msgs/Marker`` LINE_STRIP, ns ``predicted``; ns ``measured`` when a
  measured centerline is known), ``~/output`` (``std_msgs/Float64MultiArray``),
  ``~/error`` (``std_msgs/Float64``, windowed relative error), ``/diagnostics``
  (``diagnostic_msgs/DiagnosticArray``) and, latched (transient local), ``~/model_info``
  (``std_msgs/String``, JSON: method, r, dt, names, units, file sha256).
* Service ``~/reset`` (``std_srvs/Trigger``): back to the initial state.
* Setting ``model_path`` (or a core setting) at run time reloads atomically; a bad file is
  refused with the reason and the running model stays.

Start-up with a missing or bad model: one error message naming the file and the reason;
then the node exits with status 1, or, with ``wait_for_model:=true``, stays up idle
(diagnostics ``ERROR``) until a valid ``model_path`` is set.

Time: input stamps come from ``header.stamp`` (``FluidPressure``) or, for un-stamped
arrays and zero stamps, from the node clock, which follows ``/clock`` when
``use_sim_time`` is true. One timer at the publish rate integrates every whole step due
(``fixed`` stepping) and publishes, so the publish rate is decimated from the integration
rate without a 1 kHz Python timer. A callback never raises: a bad message is dropped and
counted by the core, anything unexpected is logged (throttled) and counted.
"""

from __future__ import annotations

from dataclasses import dataclass
import math
import sys
from typing import Any

from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, Pose, PoseArray
import numpy as np
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import FluidPressure
from std_msgs.msg import Float64, Float64MultiArray, MultiArrayDimension, String
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker

from soft_rom.predictor import Predictor
from soft_rom.predictor.conversions import (
    array_to_data,
    check_components,
    data_to_array,
    health_key_values,
    model_info_json,
    outputs_to_points,
    points_to_outputs,
    poses_to_points,
    sec_to_stamp,
    set_points,
    stamp_to_sec,
)
from soft_rom.predictor.params import NODE_NAME, PARAMS, predictor_config

__all__ = ['PredictorNode', 'main']


@dataclass(frozen=True)
class NodeSettings:
    """The node's read-only parameters, read once at start-up."""

    input_mode: str
    input_topics: tuple[str, ...]
    array_topic: str
    input_scale: float
    input_offset: float
    input_qos: str
    qos_depth: int
    publish_rate_hz: float
    diagnostics_rate_hz: float
    frame_id: str
    output_components: str
    fill_value: float
    measured_topic: str
    wait_for_model: bool


def _descriptor(p: Any) -> ParameterDescriptor:
    text = p.description
    if p.choices:
        text += f' One of: {", ".join(p.choices)}.'
    d = ParameterDescriptor(description=text, read_only=p.read_only)
    if p.choices:
        d.additional_constraints = f'one of {", ".join(p.choices)}'
    if p.range is not None:
        if isinstance(p.default, bool):
            pass
        elif isinstance(p.default, int):
            d.integer_range = [IntegerRange(from_value=int(p.range[0]),
                                            to_value=int(p.range[1]), step=1)]
        elif isinstance(p.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(p.range[0]),
                                                         to_value=float(p.range[1]),
                                                         step=0.0)]
    return d


class PredictorNode(Node):
    """Subscribes to pressures (and a measured centerline), publishes the ROM's prediction.

    Parameters
    ----------
    node_name : str
        Default ``soft_rom_predictor``.
    **kwargs
        Passed to :class:`rclpy.node.Node` (e.g. ``parameter_overrides``, ``namespace``).

    Attributes
    ----------
    predictor : Predictor or None
        The core (``None`` while waiting for a valid model).
    startup_error : str or None
        Why the model could not be loaded at start-up.
    """

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        for p in PARAMS:
            self.declare_parameter(p.name, p.default, _descriptor(p))
        v = self._values()
        self.settings = NodeSettings(
            input_mode=str(v['input_mode']), input_topics=tuple(v['input_topics']),
            array_topic=str(v['array_topic']), input_scale=float(v['input_scale']),
            input_offset=float(v['input_offset']), input_qos=str(v['input_qos']),
            qos_depth=int(v['qos_depth']), publish_rate_hz=float(v['publish_rate_hz']),
            diagnostics_rate_hz=float(v['diagnostics_rate_hz']), frame_id=str(v['frame_id']),
            output_components=str(v['output_components']), fill_value=float(v['fill_value']),
            measured_topic=str(v['measured_topic']), wait_for_model=bool(v['wait_for_model']))
        self.predictor: Predictor | None = None
        self.startup_error: str | None = None
        self.callback_errors = 0
        self._timer = None
        self._measured_pts: np.ndarray | None = None
        self._last_diag = (math.nan, 0, 0)

        # publishers
        self._pub_centerline = self.create_publisher(PoseArray, '~/centerline', 10)
        self._pub_marker = self.create_publisher(Marker, '~/centerline_marker', 10)
        self._pub_output = self.create_publisher(Float64MultiArray, '~/output', 10)
        self._pub_error = self.create_publisher(Float64, '~/error', 10)
        self._pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        latched = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._pub_info = self.create_publisher(String, '~/model_info', latched)
        self.create_service(Trigger, '~/reset', self._on_reset)

        # the model (one clear error if it cannot be loaded)
        path = str(v['model_path'])
        try:
            self._check_settings()
            if not path:
                raise FileNotFoundError('model_path is empty')
            predictor = Predictor(path, predictor_config(v))
            self._check_model(predictor.model)
            self._install(predictor)
        except Exception as err:  # noqa: BLE001 - reported once, clearly
            then = ('waiting for a valid model_path (ros2 param set '
                    f'{self.get_fully_qualified_name()} model_path FILE)'
                    if self.settings.wait_for_model else
                    'exiting with status 1 (wait_for_model:=true to wait instead)')
            self.startup_error = f'cannot load model_path {path!r}: {err}'
            self.get_logger().error(f'{self.startup_error}; {then}.')

        # subscriptions
        qos = self._input_qos()
        if self.settings.input_mode == 'per_chamber':
            for i, topic in enumerate(self.settings.input_topics):
                self.create_subscription(FluidPressure, topic,
                                         lambda msg, i=i: self._on_pressure(i, msg), qos)
        else:
            self.create_subscription(Float64MultiArray, self.settings.array_topic,
                                     self._on_array, qos)
        if self.settings.measured_topic:
            self.create_subscription(PoseArray, self.settings.measured_topic,
                                     self._on_measured, qos)
        self.create_timer(1.0 / self.settings.diagnostics_rate_hz, self._on_diagnostics)
        self.add_on_set_parameters_callback(self._on_set_parameters)

    # -- set-up ----------------------------------------------------------------------------
    def _values(self, changes: list[Parameter] | None = None) -> dict[str, Any]:
        values = {p.name: self.get_parameter(p.name).value for p in PARAMS}
        for param in changes or []:
            values[param.name] = param.value
        return values

    def _input_qos(self) -> QoSProfile:
        best = self.settings.input_qos == 'sensor_data'
        return QoSProfile(depth=self.settings.qos_depth, history=HistoryPolicy.KEEP_LAST,
                          reliability=(ReliabilityPolicy.BEST_EFFORT if best
                                       else ReliabilityPolicy.RELIABLE),
                          durability=DurabilityPolicy.VOLATILE)

    def _check_settings(self) -> None:
        s = self.settings
        if s.input_mode not in ('per_chamber', 'array'):
            raise ValueError(f"input_mode must be 'per_chamber' or 'array'; got {s.input_mode!r}")
        if s.input_qos not in ('sensor_data', 'reliable'):
            raise ValueError(f"input_qos must be 'sensor_data' or 'reliable'; got "
                             f'{s.input_qos!r}')

    def _check_model(self, model: Any) -> None:
        check_components(self.settings.output_components, model.n_outputs)
        if self.settings.input_mode == 'per_chamber' and len(
                self.settings.input_topics) != model.n_inputs:
            raise ValueError(f'the model has {model.n_inputs} inputs '
                             f'({", ".join(model.input_names)}) but input_topics lists '
                             f'{len(self.settings.input_topics)} topics')

    def _install(self, predictor: Predictor) -> None:
        """Make ``predictor`` the running core: message buffers, timer, model info."""
        model = predictor.model
        n = model.n_outputs // len(self.settings.output_components)
        self._pts = np.empty((n, 3))
        self._y = np.empty(model.n_outputs)
        self._pose_msg = PoseArray()
        self._pose_msg.header.frame_id = self.settings.frame_id
        self._pose_msg.poses = [Pose() for _ in range(n)]
        self._positions = [p.position for p in self._pose_msg.poses]
        self._marker = self._make_marker('predicted', 0, (0.1, 0.4, 1.0, 1.0), 0.004, n)
        self._marker_measured = self._make_marker('measured', 1, (1.0, 0.3, 0.1, 1.0), 0.003,
                                                  0)
        self._output_msg = Float64MultiArray()
        self._output_msg.layout.dim = [MultiArrayDimension(
            label='outputs', size=model.n_outputs, stride=model.n_outputs)]
        self._measured_pts = None
        h = predictor.h
        rate = self.settings.publish_rate_hz
        period = h if rate <= 0 else max(1, round(1.0 / (rate * h))) * h
        if self._timer is not None:
            self.destroy_timer(self._timer)
        self.predictor = predictor
        self._timer = self.create_timer(period, self._on_tick)
        self._pub_info.publish(String(data=model_info_json(predictor.info)))
        self.get_logger().info(
            f'running {model.method} model r={model.r} ({model.n_inputs} inputs, '
            f'{model.n_outputs} outputs, dt={model.dt:g} s) from {predictor.info["path"]}; '
            f'step {h:g} s, publishing every {period:g} s'
            + (', Kalman correction on' if predictor.config.kalman else ''))

    def _make_marker(self, ns: str, marker_id: int, rgba: tuple[float, ...], width: float,
                     n: int) -> Marker:
        m = Marker()
        m.header.frame_id = self.settings.frame_id
        m.ns, m.id, m.type, m.action = ns, marker_id, Marker.LINE_STRIP, Marker.ADD
        m.scale.x = width
        m.color.r, m.color.g, m.color.b, m.color.a = rgba
        m.points = [Point() for _ in range(n)]
        return m

    # -- time ------------------------------------------------------------------------------
    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _stamp(self, header_stamp: Any) -> float:
        if header_stamp.sec == 0 and header_stamp.nanosec == 0:
            return self._now()
        return stamp_to_sec(header_stamp)

    @staticmethod
    def _time_msg(t: float) -> TimeMsg:
        sec, nsec = sec_to_stamp(t)
        return TimeMsg(sec=sec, nanosec=nsec)

    def _guard(self, what: str, err: Exception) -> None:
        self.callback_errors += 1
        self.get_logger().warning(f'{what}: {type(err).__name__}: {err} (message dropped)',
                                  throttle_duration_sec=5.0)

    # -- callbacks -------------------------------------------------------------------------
    def _on_pressure(self, index: int, msg: FluidPressure) -> None:
        if self.predictor is None:
            return
        try:
            value = self.settings.input_scale * msg.fluid_pressure + self.settings.input_offset
            self.predictor.set_channel(index, value, self._stamp(msg.header.stamp))
        except Exception as err:  # noqa: BLE001 - the node never dies on a message
            self._guard('pressure', err)

    def _on_array(self, msg: Float64MultiArray) -> None:
        if self.predictor is None:
            return
        try:
            u = data_to_array(msg.data)
            u = self.settings.input_scale * u + self.settings.input_offset
            self.predictor.set_input(u, self._now())
        except Exception as err:  # noqa: BLE001
            self._guard('pressures', err)

    def _on_measured(self, msg: PoseArray) -> None:
        if self.predictor is None:
            return
        try:
            pts = poses_to_points(msg.poses)
            y = points_to_outputs(pts, self.settings.output_components)
            if self.predictor.measure(y, self._stamp(msg.header.stamp)) is not None:
                self._measured_pts = pts
        except Exception as err:  # noqa: BLE001
            self._guard('measured centerline', err)

    def _on_tick(self) -> None:
        pred = self.predictor
        if pred is None:
            return
        try:
            now = self._now()
            if pred.config.stepping == 'fixed':
                pred.advance_to(now)
            if pred.t is None:      # input stepping, no input yet: nothing to predict
                return
            t = pred.t
            y = pred.output(self._y)
            outputs_to_points(y, self.settings.output_components, self.settings.fill_value,
                              out=self._pts)
            stamp = self._time_msg(t)
            self._pose_msg.header.stamp = stamp
            set_points(self._positions, self._pts)
            self._pub_centerline.publish(self._pose_msg)
            self._marker.header.stamp = stamp
            set_points(self._marker.points, self._pts)
            self._pub_marker.publish(self._marker)
            if self._measured_pts is not None:
                mk = self._marker_measured
                if len(mk.points) != len(self._measured_pts):
                    mk.points = [Point() for _ in range(len(self._measured_pts))]
                mk.header.stamp = stamp
                set_points(mk.points, self._measured_pts)
                self._pub_marker.publish(mk)
            self._output_msg.data = array_to_data(y)
            self._pub_output.publish(self._output_msg)
            err = pred.windowed_error()
            if math.isfinite(err):
                self._pub_error.publish(Float64(data=err))
        except Exception as err:  # noqa: BLE001
            self._guard('publish', err)

    def _on_diagnostics(self) -> None:
        msg = DiagnosticArray()
        now = self._now()
        msg.header.stamp = self._time_msg(now)
        status = DiagnosticStatus(name=f'{self.get_name()}: prediction',
                                  hardware_id=self.get_fully_qualified_name())
        pred = self.predictor
        if pred is None:
            status.level = DiagnosticStatus.ERROR
            status.message = f'no model: {self.startup_error}'
        else:
            health = pred.health(now)
            status.level = bytes([int(health.level)])
            status.message = health.message
            values = health_key_values(health)
            t0, n_in, n_meas = self._last_diag
            n_in_now, n_meas_now = pred.counters['inputs'], pred.counters['measurements']
            if math.isfinite(t0) and now > t0:
                values.append(('input_rate_hz', f'{(n_in_now - n_in) / (now - t0):.4g}'))
                values.append(('measured_rate_hz',
                               f'{(n_meas_now - n_meas) / (now - t0):.4g}'))
            self._last_diag = (now, n_in_now, n_meas_now)
            values.append(('callback_errors', str(self.callback_errors)))
            status.values = [KeyValue(key=k, value=v) for k, v in values]
        msg.status = [status]
        self._pub_diag.publish(msg)

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        if self.predictor is None:
            response.success = False
            response.message = f'no model loaded: {self.startup_error}'
            return response
        self.predictor.reset()
        self._measured_pts = None
        response.success = True
        response.message = (f'reset to the {self.predictor.config.initial_state} state')
        return response

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        names = {p.name for p in params}
        core = {p.name for p in PARAMS if not p.read_only} - {'model_path'}
        if not names & (core | {'model_path'}):
            return SetParametersResult(successful=True)
        values = self._values(params)
        try:
            config = predictor_config(values)
            if self.predictor is None and 'model_path' not in names:
                return SetParametersResult(successful=True)     # used when a model loads
            if 'model_path' in names:
                path = str(values['model_path'])
                if not path:
                    if self.predictor is None:
                        return SetParametersResult(successful=True)
                    raise ValueError('model_path is empty')
                if self.predictor is None:
                    candidate = Predictor(path, config)
                    self._check_model(candidate.model)
                else:   # atomic: inputs held, running model kept on any failure
                    self.predictor.reload(path, config, validate=self._check_model)
                    candidate = self.predictor
                self._install(candidate)
                self.startup_error = None
            else:
                self.predictor.set_config(config)
        except Exception as err:  # noqa: BLE001 - refused, running model stays
            why = str(err).rstrip('.')
            reason = f'{type(err).__name__}: {why}; the running model is unchanged'
            self.get_logger().error(f'parameter change refused: {reason}')
            return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)


def main(args: list[str] | None = None) -> int:
    """Entry point of ``ros2 run soft_rom predictor``; returns the exit status."""
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = PredictorNode()
        if node.startup_error is not None and not node.settings.wait_for_model:
            code = 1
        else:
            rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':  # pragma: no cover
    sys.exit(main())
