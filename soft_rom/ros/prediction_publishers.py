"""The predictor node's publishers: what :class:`~soft_rom.predictor.loop.Publish` says, sent.

:class:`PredictionPublishers` is mixed into :class:`~soft_rom.ros.predictor_node.PredictorNode`
(which sets the attributes listed on the class): it creates the node's publishers, sizes the
message objects once per model (reused at every publish, only their data and stamps
change) and publishes outputs, state, centerline, markers, error, diagnostics and the
latched model info. The topics are described in :mod:`soft_rom.ros.predictor_node`.
"""

from __future__ import annotations

from typing import Any

from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Point, Pose, PoseArray
import numpy as np
from rclpy.qos import QoSProfile
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64, Float64MultiArray, MultiArrayDimension, String
from visualization_msgs.msg import Marker

from soft_rom.predictor.conversions import array_to_data, model_info_json, ns_to_stamp, set_points
from soft_rom.predictor.loop import MARKER_STYLES, Publish, RuntimeLoop
from soft_rom.ros.diagnostics import Diagnostics, publisher_counts, TopicMonitor
from soft_rom.ros.node_params import NodeSettings

__all__ = ['PredictionPublishers']


class PredictionPublishers:
    """Publishers and reused messages of the predictor node (mixed into ``PredictorNode``)."""

    # attributes set by PredictorNode
    settings: NodeSettings
    loop: RuntimeLoop | None
    startup_error: str | None
    callback_errors: int
    measured_monitor: TopicMonitor | None
    diagnostics: Diagnostics
    _active: bool
    _latched: QoSProfile
    _info_sent: str | None

    def _create_publishers(self) -> list[Any]:
        """Create the node's publishers (on activation); returns them."""
        pub = self.create_publisher  # type: ignore[attr-defined]
        self._pub_output = pub(Float64MultiArray, '~/output', 100)
        self._pub_output_stamped = pub(JointState, '~/output_stamped', 100)
        self._pub_centerline = pub(PoseArray, '~/centerline', 10)
        self._pub_marker = pub(Marker, '~/centerline_marker', 10)
        self._pub_error = pub(Float64, '~/error', 10)
        self._pub_diag = pub(DiagnosticArray, '/diagnostics', 10)
        self._pub_info = pub(String, '~/model_info', self._latched)
        self._pub_state = pub(JointState, '~/state', 10)
        return [self._pub_output, self._pub_output_stamped, self._pub_centerline,
                self._pub_marker, self._pub_error, self._pub_diag, self._pub_info,
                self._pub_state]

    def _publish_info(self, if_changed: bool = False) -> None:
        """Publish ``~/model_info`` (latched); ``if_changed``: only if it says something new."""
        if not self._active or self.loop is None:
            return
        text = model_info_json(self.loop.predictor.info)
        if if_changed and text == self._info_sent:
            return
        self._info_sent = text
        self._pub_info.publish(String(data=text))

    def _prepare_messages(self) -> None:
        """Message objects reused at every publish (sized for the loaded model)."""
        assert self.loop is not None
        model = self.loop.predictor.model
        n = model.n_outputs // len(self.settings.output_components)
        frame = self.settings.frame_id
        self._pose_msg = PoseArray()
        self._pose_msg.header.frame_id = frame
        self._pose_msg.poses = [Pose() for _ in range(n)]
        self._positions = [p.position for p in self._pose_msg.poses]
        self._marker = self._make_marker('predicted', n)
        self._marker_measured = self._make_marker('measured', 0)
        self._output_msg = Float64MultiArray()
        self._output_msg.layout.dim = [MultiArrayDimension(
            label='outputs', size=model.n_outputs, stride=model.n_outputs)]
        self._stamped_msg = JointState()
        self._stamped_msg.header.frame_id = frame
        self._stamped_msg.name = list(model.output_names)
        self._state_msg = JointState()
        self._state_msg.header.frame_id = frame
        self._state_msg.name = [f'x{i}' for i in range(model.n_states)]

    def _make_marker(self, kind: str, n: int) -> Marker:
        ns, marker_id, rgba, width = MARKER_STYLES[kind]
        m = Marker()
        m.header.frame_id = self.settings.frame_id
        m.ns, m.id, m.type, m.action = ns, marker_id, Marker.LINE_STRIP, Marker.ADD
        m.scale.x = width
        m.color.r, m.color.g, m.color.b, m.color.a = rgba
        m.points = [Point() for _ in range(n)]
        return m

    def _now_ns(self) -> int:
        """The node clock's time in int ns (the bag's ``/clock`` under ``use_sim_time``)."""
        return self.get_clock().now().nanoseconds  # type: ignore[attr-defined]

    def _taken(self, loop: Any) -> None:
        """Tell ``loop`` the node finished taking an input (:meth:`RuntimeLoop.taken`).

        Wall time only: in sim time the node's clock can trail ``/clock`` messages queued
        with the inputs, so a message taken at an unchanged clock did not wait in a queue
        (a 100 Hz controller's arrays were read so, and compressed to one step each).
        """
        clock = self.get_clock()  # type: ignore[attr-defined]
        if not clock.ros_time_is_active:
            loop.taken(clock.now().nanoseconds)

    def _publish(self, pub: Publish) -> None:
        """Publish what the loop says is due."""
        if not self._active:
            return
        out, sm = self._output_msg, self._stamped_msg
        for t_ns, y in pub.outputs:
            out.data = array_to_data(y)
            self._pub_output.publish(out)
            sec, nsec = ns_to_stamp(t_ns)
            sm.header.stamp.sec, sm.header.stamp.nanosec = sec, nsec
            sm.position = out.data
            self._pub_output_stamped.publish(sm)
        if pub.outputs:
            self._publish_state()
        if pub.centerline is not None:
            self._publish_centerline(*pub.centerline, pub.measured_points, pub.error)
        if pub.diagnostics_due:
            self._publish_diagnostics(self._now_ns())

    def _publish_state(self) -> None:
        """``~/state``: the ROM state estimate (deviations) stamped with its model time."""
        loop = self.loop
        t_ns = None if loop is None else loop.predictor.t_ns
        if loop is None or t_ns is None:
            return
        msg = self._state_msg
        msg.header.stamp.sec, msg.header.stamp.nanosec = ns_to_stamp(t_ns)
        msg.position = array_to_data(np.asarray(loop.predictor.x, dtype=np.float64))
        self._pub_state.publish(msg)

    def _publish_centerline(self, t_ns: int, pts: np.ndarray, measured: np.ndarray | None,
                            error: float | None) -> None:
        sec, nsec = ns_to_stamp(t_ns)
        stamp = TimeMsg(sec=sec, nanosec=nsec)
        self._pose_msg.header.stamp = stamp
        set_points(self._positions, pts)
        self._pub_centerline.publish(self._pose_msg)
        self._marker.header.stamp = stamp
        set_points(self._marker.points, pts)
        self._pub_marker.publish(self._marker)
        if measured is not None:
            mk = self._marker_measured
            if len(mk.points) != len(measured):
                mk.points = [Point() for _ in range(len(measured))]
            mk.header.stamp = stamp
            set_points(mk.points, measured)
            self._pub_marker.publish(mk)
        if error is not None:
            self._pub_error.publish(Float64(data=error))

    def _publish_diagnostics(self, now_ns: int) -> None:
        loop = self.loop
        report = None if loop is None else loop.diagnostics(
            now_ns, extra=[('callback_errors', str(self.callback_errors))])
        sec, nsec = ns_to_stamp(now_ns)
        timeout = float(self.settings_value('input_timeout_s'))  # type: ignore[attr-defined]
        newest = None if loop is None else [int(t) for t in loop.predictor.channels.newest]
        senders = publisher_counts(self, self.diagnostics.input_topics)
        self._pub_diag.publish(self.diagnostics.message(
            now_ns, TimeMsg(sec=sec, nanosec=nsec), report, self.startup_error,
            self.measured_monitor, timeout, newest, senders))
