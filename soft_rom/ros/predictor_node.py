"""``ros2 run soft_rom predictor``: the ROM predictor node (Jazzy rclpy), a thin shell.

All behaviour lives in the ROS-free core: a :class:`soft_rom.predictor.loop.RuntimeLoop`
around a :class:`soft_rom.predictor.Predictor` decides what is due (the same loop runs in
``soft-rom replay``); this node declares the parameters, converts messages, feeds the loop
and publishes what it returns (the parameters are declared and checked in
:mod:`soft_rom.ros.node_params`, the messages published by
:mod:`soft_rom.ros.prediction_publishers`):

* ``~/output`` (``std_msgs/Float64MultiArray``) at every step (``publish_rate_hz`` 0) or
  decimated, and with each one ``~/output_stamped`` (``sensor_msgs/JointState``:
  ``header.stamp`` = the model time of that prediction, ``name`` = the model's output names,
  ``position`` = the outputs), so that each prediction is paired with its model time;
* ``~/state`` (``sensor_msgs/JointState``): the ROM state estimate after each batch of
  steps (deviation coordinates; ``header.stamp`` = its model time), for controllers;
* ``~/centerline`` (``geometry_msgs/PoseArray``) and ``~/centerline_marker``
  (``visualization_msgs/Marker`` LINE_STRIP, ns ``predicted``; ns ``measured`` when a
  measured centerline is known) at their own rate ``centerline_rate_hz`` (default 30 Hz);
* ``~/error`` (``std_msgs/Float64``, windowed relative error), ``/diagnostics``
  (``diagnostic_msgs/DiagnosticArray``, see :mod:`soft_rom.ros.diagnostics`) and, latched
  (transient local), ``~/model_info`` (``std_msgs/String``, JSON);
* service ``~/reset`` (``std_srvs/Trigger``).

Stepping: with ``stepping: event`` (default) the inputs drive the model: outputs are
published from the input callbacks, and the only timer runs at the diagnostics rate; with
``stepping: fixed`` one timer at the publish period integrates every whole step due.

``lifecycle: true`` makes it a managed node (configure loads and validates the model,
activate creates the subscriptions, publishers, timers and the reset service, deactivate
destroys them keeping the state, cleanup unloads the model); default false: everything
happens at start-up, as a plain node.

Start-up: a bad parameter (wrong type, out of range, not one of the choices, an empty list,
settings that contradict each other) or an unparsable ``--ros-args`` is one error line naming
it and exit status 1, whatever ``wait_for_model`` says (that one waits for a valid model
only); a missing or bad model file is one error line naming the file, then exit status 1
(``wait_for_model: false``) or waiting for a valid ``model_path``.

Shutdown: rclpy's signal handlers are off; SIGINT and SIGTERM set a flag that the spin loop
checks at least every 0.1 s, so no callback runs after the context shuts down (no
"context is invalid" errors) and the process exits 0.
"""

from __future__ import annotations

import functools
import signal
import sys
import threading
from typing import Any

from geometry_msgs.msg import PoseArray
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNodeMixin, LifecycleState, TransitionCallbackReturn
from rclpy.logging import get_logger
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import FluidPressure
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import Trigger

from soft_rom.errors import ConfigError
from soft_rom.predictor import Predictor
from soft_rom.predictor.conversions import (
    data_to_array,
    poses_to_points,
    stamp_to_ns,
)
from soft_rom.predictor.loop import RuntimeLoop
from soft_rom.ros.diagnostics import Diagnostics, TopicMonitor
from soft_rom.ros.node_params import (
    init_rclpy,
    NodeSettings,
    ParameterMixin,
    rclpy_reason,
    warn_unknown_parameters,
    watch_sim_clock,
)
from soft_rom.ros.prediction_publishers import PredictionPublishers

__all__ = ['PredictorNode', 'StartupError', 'main']


class StartupError(Exception):
    """A bad parameter at start-up; already logged (one error line): exit status 1."""


class PredictorNode(LifecycleNodeMixin, ParameterMixin, PredictionPublishers, Node):
    """Subscribes to pressures (and a measured centerline), publishes the ROM's prediction.

    Parameters
    ----------
    node_name : str
        Default ``soft_rom_predictor``.
    **kwargs
        Passed to :class:`rclpy.node.Node` (``context``, ``parameter_overrides``,
        ``cli_args``, ``namespace``).

    Attributes
    ----------
    loop : RuntimeLoop or None
        The core (``None`` while no valid model is loaded).
    startup_error : str or None
        Why the node cannot run: a bad parameter, or the model could not be loaded (plain
        mode: at start-up; lifecycle: at configure).
    managed : bool
        Whether the node runs as a lifecycle (managed) node.

    Raises
    ------
    StartupError
        A bad parameter at start-up (logged as one error line first).
    """

    def __init__(self, node_name: str = 'soft_rom_predictor', **kwargs: Any) -> None:
        self.startup_error: str | None = None
        try:
            Node.__init__(self, node_name, **kwargs)    # declares use_sim_time
            self.settings: NodeSettings = self.declare_predictor_parameters()
            if not self.settings.lifecycle:     # managed: checked at configure (changeable)
                self.check_core_settings()
        except (ConfigError, ParameterException) as err:
            self._fail_start(node_name, str(err) if isinstance(err, ConfigError) else
                             f'parameter {rclpy_reason(err)}.')
        warn_unknown_parameters(self)
        watch_sim_clock(self)
        self.managed = self.settings.lifecycle
        self.loop: RuntimeLoop | None = None
        self.callback_errors = 0
        self._entities: list[Any] = []
        self._timer: Any = None
        self._info_sent: str | None = None
        self._active = False
        self._latched = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                                   reliability=ReliabilityPolicy.RELIABLE,
                                   durability=DurabilityPolicy.TRANSIENT_LOCAL)
        s = self.settings
        self.measured_monitor = (TopicMonitor(s.measured_topic, 'measured', s.frame_id)
                                 if s.measured_topic else None)
        inputs = s.input_topics if s.input_mode == 'per_chamber' else (s.array_topic,)
        self.diagnostics = Diagnostics(self.get_name(), s.hardware_id
                                       or self.get_fully_qualified_name(), list(inputs))
        if self.managed:
            LifecycleNodeMixin.__init__(self)
            self.get_logger().info('lifecycle node: unconfigured (ros2 lifecycle set '
                                   f'{self.get_fully_qualified_name()} configure)')
            return
        if self._configure():
            self._activate()
        elif s.wait_for_model:
            self._activate()        # idle, diagnostics ERROR, until a valid model_path is set

    def _fail_start(self, node_name: str, reason: str) -> None:
        """Log ``reason`` as the one error line and raise :class:`StartupError`."""
        self.startup_error = reason.rstrip('.')
        try:
            logger = Node.get_logger(self)
        except AttributeError:          # rclpy failed before the node had a logger
            logger = get_logger(node_name)
        logger.error(f'{self.startup_error}; exiting with status 1.')
        try:
            Node.destroy_node(self)
        except Exception:  # noqa: BLE001 - a half-built node; the context goes next
            pass
        raise StartupError(self.startup_error)

    @property
    def predictor(self) -> Predictor | None:
        """The running core's predictor (``None`` without a model)."""
        return None if self.loop is None else self.loop.predictor

    # -- lifecycle transitions (managed mode) -----------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Load and validate the model; FAILURE (stay unconfigured) with the reason."""
        return (TransitionCallbackReturn.SUCCESS if self._configure()
                else TransitionCallbackReturn.FAILURE)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Create subscriptions, publishers, timers and the reset service."""
        self._activate()
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Destroy the communication entities; the model and its state are kept."""
        self._deactivate()
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Unload the model."""
        self._deactivate()
        self.loop = None
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Stop everything (from any state)."""
        return self.on_cleanup(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Back to unconfigured after an error."""
        return self.on_cleanup(state)

    # -- set-up ------------------------------------------------------------------------------
    def _configure(self) -> bool:
        path = self.settings_value('model_path')
        loop = None
        try:
            config, settings = self.predictor_config(), self.loop_settings()
        except ConfigError as err:          # managed: changeable settings, fix and retry
            self.startup_error = str(err).rstrip('.')
        else:
            if not path:
                self.startup_error = 'model_path is empty (give -p model_path:=FILE)'
            else:
                loop = self._load(path, config, settings)
        if loop is None:
            if self.managed:
                then = 'staying unconfigured'
            elif self.settings.wait_for_model:
                then = ('waiting for a valid model_path (ros2 param set '
                        f'{self.get_fully_qualified_name()} model_path FILE)')
            else:
                then = 'exiting with status 1 (wait_for_model:=true to wait instead)'
            self.startup_error = str(self.startup_error).rstrip('.')
            self.get_logger().error(f'{self.startup_error}; {then}.')
            return False
        self._use(loop)
        return True

    def _load(self, path: str, config: Any, settings: Any) -> RuntimeLoop | None:
        """The model file run with these settings, or ``None`` with :attr:`startup_error`."""
        try:
            predictor = Predictor(path, config)
        except ConfigError as err:
            self.startup_error = f'the parameters do not fit model_path {path!r}: {err}'
            return None
        except Exception as err:  # noqa: BLE001 - reported once, clearly
            self.startup_error = f'cannot load model_path {path!r}: {err}'
            return None
        try:
            self._check_model(predictor.model)
            return RuntimeLoop(predictor, settings)
        except Exception as err:  # noqa: BLE001
            self.startup_error = f'the parameters do not fit model_path {path!r}: {err}'
            return None

    def _check_model(self, model: Any) -> None:
        if self.settings.input_mode == 'per_chamber' and len(
                self.settings.input_topics) != model.n_inputs:
            raise ValueError(f'the model has {model.n_inputs} inputs '
                             f'({", ".join(model.input_names)}) but input_topics lists '
                             f'{len(self.settings.input_topics)} topics')

    def _use(self, loop: RuntimeLoop) -> None:
        """Make ``loop`` the running core: messages sized for its model, timer, model info."""
        self.startup_error = None
        self.loop = loop
        self._prepare_messages()
        pred = loop.predictor
        model = pred.model
        how = ('inputs drive the steps' if pred.config.stepping == 'event'
               else f'{pred.config.stepping} stepping')
        self.get_logger().info(
            f'running {model.method} model r={model.r} ({model.n_inputs} inputs, '
            f'{model.n_outputs} outputs, dt={model.dt:g} s) from {pred.info["path"]}; '
            f'step {pred.h:g} s, {how}'
            + (', Kalman correction on' if pred.config.kalman else ''))
        trust = pred.info.get('trust') or []
        if trust:
            self.get_logger().warning('model not trusted (its predictions may be absurd; '
                                      'strict_model:=true refuses it): ' + '; '.join(trust))
        self._start_timer()
        self._publish_info()

    def _input_qos(self) -> QoSProfile:
        best = self.settings.input_qos == 'sensor_data'
        return QoSProfile(depth=self.settings.qos_depth, history=HistoryPolicy.KEEP_LAST,
                          reliability=(ReliabilityPolicy.BEST_EFFORT if best
                                       else ReliabilityPolicy.RELIABLE),
                          durability=DurabilityPolicy.VOLATILE)

    def _activate(self) -> None:
        if self._active:
            return
        s = self.settings
        ents: list[Any] = self._create_publishers()
        ents.append(self.create_service(Trigger, '~/reset', self._on_reset))
        qos = self._input_qos()
        if s.input_mode == 'per_chamber':
            for i, topic in enumerate(s.input_topics):
                ents.append(self.create_subscription(
                    FluidPressure, topic, functools.partial(self._on_pressure, i), qos))
        else:
            ents.append(self.create_subscription(Float64MultiArray, s.array_topic,
                                                 self._on_array, qos))
        if s.measured_topic:
            ents.append(self.create_subscription(PoseArray, s.measured_topic,
                                                 self._on_measured, qos))
        self._entities = ents
        self._active = True
        self._start_timer()
        self._publish_info()

    def _deactivate(self) -> None:
        if not self._active:
            return
        self._active = False
        self._start_timer()
        for ent in self._entities:
            for destroy in (self.destroy_subscription, self.destroy_publisher,
                            self.destroy_service):
                if destroy(ent):
                    break
        self._entities = []

    def _start_timer(self) -> None:
        """(Re)start the one timer at the loop's period, or the diagnostics rate.

        Fixed stepping: the publish period; event stepping: the diagnostics period.
        """
        if self._timer is not None:
            self.destroy_timer(self._timer)
            self._timer = None
        if not self._active:
            return
        if self.loop is None:
            self._timer = self.create_timer(1.0 / self.settings.diagnostics_rate_hz,
                                            self._on_tick)
        else:
            self._timer = self.create_timer(self.loop.timer_period_ns() * 1e-9,
                                            self._on_tick)

    # -- callbacks -----------------------------------------------------------------------------
    def _guard(self, what: str, err: Exception) -> None:
        self.callback_errors += 1
        self.get_logger().warning(f'{what}: {type(err).__name__}: {err} (message dropped)',
                                  throttle_duration_sec=5.0)

    def _on_pressure(self, index: int, msg: FluidPressure) -> None:
        if (loop := self.loop) is None:
            return
        try:
            self._publish(loop.on_channel(index, msg.fluid_pressure,
                                          stamp_to_ns(msg.header.stamp), self._now_ns()))
            self._taken(loop)
        except Exception as err:  # noqa: BLE001 - the node never dies on a message
            self._guard('pressure', err)

    def _on_array(self, msg: Float64MultiArray) -> None:
        # The middleware's reception time (rclpy's MessageInfo, given to a two-argument
        # callback) would time an array before its wait in the node's queue, but the
        # EventsExecutor of Jazzy's rclpy 7.1.6 (the default here) raises "SystemError: null
        # argument to internal routine" for such callbacks (tried 2026-12-07): the array is
        # timed on taking it, and the sequence clock reads the node's queue from ``_taken``.
        if (loop := self.loop) is None:
            return
        try:
            self._publish(loop.on_array(data_to_array(msg.data), 0, self._now_ns()))
            self._taken(loop)               # after publishing
        except Exception as err:  # noqa: BLE001
            self._guard('pressures', err)

    def _on_measured(self, msg: PoseArray) -> None:
        loop = self.loop
        if loop is None or self.measured_monitor is None:
            return
        try:
            stamp = stamp_to_ns(msg.header.stamp)
            monitor = self.measured_monitor
            monitor.seen(stamp)
            frame = msg.header.frame_id
            monitor.frame = '' if not frame or frame == monitor.expected_frame else frame
            self._publish(loop.on_measured(poses_to_points(msg.poses), stamp,
                                           self._now_ns()))
        except Exception as err:  # noqa: BLE001
            self._guard('measured centerline', err)

    def _on_tick(self) -> None:
        try:
            if self.loop is None:
                self._publish_diagnostics(self._now_ns())
            else:
                self._publish(self.loop.tick(self._now_ns()))
        except Exception as err:  # noqa: BLE001
            self._guard('timer', err)

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response
                  ) -> Trigger.Response:
        if self.loop is None:
            response.success = False
            response.message = f'no model loaded: {self.startup_error}'
            return response
        self.loop.reset()
        response.success = True
        response.message = f'reset to the {self.loop.predictor.config.initial_state} state'
        return response

    # -- run-time parameter changes (called by ParameterMixin) ---------------------------------
    def apply_parameters(self, names: set[str], values: dict[str, Any]) -> None:
        """Apply accepted run-time changes; raises (with the reason) to refuse them."""
        config = self.predictor_config(values)
        loop = self.loop
        if 'model_path' in names:
            path = str(values['model_path'])
            if not path:
                if loop is None:
                    return
                raise ValueError('model_path is empty')
            if self.managed and loop is None:
                return      # used at the next configure
            if loop is None:
                candidate = Predictor(path, config)
                self._check_model(candidate.model)
                loop = RuntimeLoop(candidate, self.loop_settings())
            else:   # atomic: the running model is kept on any failure
                loop.reload(path, config, validate=self._check_model)
            self._use(loop)
        elif loop is not None:
            stepping = loop.predictor.config.stepping
            loop.set_config(config)
            if config.stepping != stepping:
                self._start_timer()
            self._publish_info(if_changed=True)     # e.g. the envelopes in force


class _StopFlag:
    """SIGINT/SIGTERM handlers that ask the spin loop to stop (nothing else runs in them)."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: int | None = None
        self._previous = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)

    def _handle(self, signum: int, frame: Any) -> None:
        self.signal = signum
        self.event.set()

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def _executor(node: PredictorNode) -> Any:
    if node.settings.executor == 'events':
        try:
            from rclpy.experimental import EventsExecutor
        except ImportError:
            node.get_logger().warning('this rclpy has no EventsExecutor: using the '
                                      'SingleThreadedExecutor (more CPU per message)')
        else:
            return EventsExecutor()
    return SingleThreadedExecutor()


def main(args: list[str] | None = None) -> int:
    """Run the node until SIGINT/SIGTERM; returns the exit status (0, or 1: bad start)."""
    stop = _StopFlag()
    refused = init_rclpy(args)
    if refused is not None:
        stop.restore()
        get_logger('soft_rom_predictor').error(
            f'bad command line (--ros-args): {refused}; exiting with status 1.')
        return 1
    node = None
    code = 0
    executor = None
    try:
        node = PredictorNode()
        if node.startup_error is not None and not (node.settings.wait_for_model
                                                   or node.managed):
            code = 1
        else:
            executor = _executor(node)
            executor.add_node(node)
            while not stop.event.is_set() and rclpy.ok():
                executor.spin_once(timeout_sec=0.1)
    except StartupError:        # logged by the node: one line
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        stop.restore()
    return code


if __name__ == '__main__':  # pragma: no cover
    sys.exit(main())
