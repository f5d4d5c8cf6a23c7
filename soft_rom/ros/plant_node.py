"""``ros2 run soft_rom plant``: the embedded eel FOM as a ROS 2 node (the closed loop's plant).

A thin shell over :class:`soft_rom.sim.EelStepper`: it takes chamber pressures on the
predictor's inputs (``input_mode``: one ``sensor_msgs/FluidPressure`` per chamber on
``input_topics``, or all chambers in one ``std_msgs/Float64MultiArray`` on ``array_topic``,
applied from the plant time at which it arrives), steps the FOM at
``dt`` and publishes ``/clock`` at every step, so that the closed loop runs in sim time at
the plant's pace, and the measured centerline (``geometry_msgs/PoseArray``, with Gaussian
noise ``sensor_noise`` at ``sensor_rate_hz``, stamped with the plant time).

The pressure subscriptions are reliable (``input_qos``, as the controller publishes);
``input_qos: sensor_data`` makes them best effort, which a best-effort commander needs (a
reliable reader never matches it: the plant held the last pressures at every lockstep point).
A pressure stamped ``t`` applies from the first plant step at or after ``t``. With
``lockstep_s`` > 0 (default 0.01, the controller's step), at each multiple of it the plant
waits (up to ``command_timeout_s`` of wall time, then holds) for a command stamped at that
time on every chamber, so a slow or loaded machine does not change the loop. After
``duration_s`` (0: none) of sim time it stops stepping; ``record_path`` then gets an
``.npz`` with ``t``, ``U`` (applied) and ``Y`` (noise-free centerline, ``x`` then ``z``
rows), as ``soft-rom control`` records it.

The first step waits until a publisher (the controller) is on every pressure topic and,
with ``wait_for_subscribers`` = N, N subscribers besides the plant (the predictor: 1, as
``closed_loop.launch.py`` sets), then 1 s for the connections to match: a predictor that
joined late missed the controller's first commands, which the plant applied.

A lockstep point that timed out is logged (throttled); a pressure above 1e7 Pa (kPa sent as
Pa?) or not finite is dropped and the last one held; a FOM that diverges anyway ends the node
with one error line and exit status 1 (``record_path`` written up to there).
"""

from __future__ import annotations

import functools
import math
import signal
import sys
import threading
import time
from typing import Any

from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import Pose, PoseArray
import numpy as np
from rcl_interfaces.msg import ParameterDescriptor
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import FluidPressure
from std_msgs.msg import Float64MultiArray

from soft_rom.errors import SolverError
from soft_rom.predictor.conversions import data_to_array, ns_to_stamp, set_points, stamp_to_ns
from soft_rom.ros.node_params import init_rclpy, rclpy_reason, warn_unknown_parameters

__all__ = ['PlantNode', 'main']

DEFAULT_TOPICS = [f'/soft_robot/pressure/chamber_{i}' for i in range(1, 7)]
#: Larger pressure commands are dropped (Pa; ``soft-rom simulate --amplitude``'s limit).
MAX_PRESSURE = 1e7


class PlantNode(Node):
    """The FOM, stepped on pressure messages; publishes ``/clock`` and the measured centerline."""

    def __init__(self, node_name: str = 'soft_rom_plant', **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)

        def declare(name: str, value: Any, text: str) -> Any:
            return self.declare_parameter(name, value, ParameterDescriptor(
                description=text, read_only=True)).value

        self.resolution = int(declare('resolution', 1, 'FOM mesh resolution (1: 5,145 DOF)'))
        self.dt = float(declare('dt', 1e-3, 'plant step, s'))
        self.sensor_rate = float(declare('sensor_rate_hz', 120.0, 'measured centerline rate'))
        self.noise = float(declare('sensor_noise', 5e-4, 'measurement noise std, m'))
        self.seed = int(declare('seed', 0, 'noise seed'))
        self.input_mode = str(declare('input_mode', 'per_chamber',
                                      'per_chamber (FluidPressure topics) or array'))
        self.topics = list(declare('input_topics', DEFAULT_TOPICS, 'chamber pressure topics'))
        self.array_topic = str(declare('array_topic', '/soft_robot/pressures',
                                       'Float64MultiArray pressures (input_mode array)'))
        self.input_qos = str(declare('input_qos', 'reliable', 'QoS of the pressure '
                                     'subscriptions: reliable (as the controller publishes) '
                                     'or sensor_data (best effort: takes best-effort '
                                     'commanders too)'))
        self.measured_topic = str(declare('measured_topic', '/soft_robot/centerline',
                                          'measured centerline topic'))
        self.frame_id = str(declare('frame_id', 'world', 'frame of the centerline'))
        self.lockstep = float(declare('lockstep_s', 0.01, 'wait for commands at multiples of '
                                                          'this sim time (0: never)'))
        self.timeout = float(declare('command_timeout_s', 2.0, 'wall seconds to wait'))
        self.duration = float(declare('duration_s', 0.0, 'sim seconds to run (0: no end)'))
        self.record_path = str(declare('record_path', '', '.npz written at the end'))
        self.wait_for_subscribers = int(declare(
            'wait_for_subscribers', 0, 'other subscribers of every pressure topic (the '
            'predictor: 1) to wait for, besides a publisher, before the first step'))
        self._check_values()
        from soft_rom.sim import EelModel
        self.eel = EelModel(resolution=self.resolution)
        self.stepper = self.eel.stepper(self.dt)
        self.rng = np.random.default_rng(self.seed)
        m = self.eel.n_chambers
        if self.input_mode == 'per_chamber' and len(self.topics) != m:
            raise ValueError(f'input_topics needs {m} topics (one per chamber); got '
                             f'{len(self.topics)}')
        self.stop_event: threading.Event | None = None     # main(): SIGINT/SIGTERM
        self.too_large = 0
        self.value = np.zeros(m)
        self.pending: list[list[tuple[int, float]]] = [[] for _ in range(m)]
        self.newest = np.full(m, -1, dtype=np.int64)
        # a reliable reader never matches a best-effort writer (and the plant, waiting for
        # commands, would hold at every lockstep point); a best-effort reader takes both
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE
                         if self.input_qos == 'reliable' else ReliabilityPolicy.BEST_EFFORT)
        if self.input_mode not in ('per_chamber', 'array'):
            raise ValueError(f'input_mode {self.input_mode!r} is not per_chamber or array')
        self.t_ns = 0
        self.bad_arrays = 0
        if self.input_mode == 'array':
            self.create_subscription(Float64MultiArray, self.array_topic, self._on_array, qos)
            self.command_topics = [self.array_topic]
        else:
            for i, topic in enumerate(self.topics):
                self.create_subscription(FluidPressure, topic,
                                         functools.partial(self._on_pressure, i), qos)
            self.command_topics = list(self.topics)
        self.pub_clock = self.create_publisher(Clock, '/clock', 10)
        self.pub_measured = self.create_publisher(PoseArray, self.measured_topic, 10)
        n = self.eel.centerline_map.shape[0]
        self.msg = PoseArray()
        self.msg.header.frame_id = self.frame_id
        self.msg.poses = [Pose() for _ in range(n)]
        self.positions = [p.position for p in self.msg.poses]
        self.t_rec: list[float] = []
        self.U_rec: list[np.ndarray] = []
        self.Y_rec: list[np.ndarray] = []
        self.held = 0
        self.frame = 0

    def _sane(self, v: float) -> bool:
        """Whether a pressure is finite and at most ``MAX_PRESSURE`` (counted, warned)."""
        if abs(v) <= MAX_PRESSURE:           # False for NaN
            return True
        if math.isfinite(v):
            self.too_large += 1
            self.get_logger().warning(
                f'pressure command {v:g} Pa dropped: more than {MAX_PRESSURE:g} Pa (kPa sent as '
                f'Pa?); {self.too_large} so far', throttle_duration_sec=5.0)
        return False

    def _on_pressure(self, i: int, msg: FluidPressure) -> None:
        v = float(msg.fluid_pressure)
        if not self._sane(v):
            return
        t = stamp_to_ns(msg.header.stamp)
        self.pending[i].append((t, v))
        self.newest[i] = max(self.newest[i], t)

    def _on_array(self, msg: Float64MultiArray) -> None:
        v = data_to_array(msg.data)
        if v.shape != (self.eel.n_chambers,) or not all(self._sane(x) for x in v.tolist()):
            self.bad_arrays += 1
            return
        for i, value in enumerate(v.tolist()):
            self.pending[i].append((self.t_ns, value))
            self.newest[i] = max(self.newest[i], self.t_ns)

    def _apply(self, t_ns: int) -> None:
        for i, queue in enumerate(self.pending):
            keep = []
            for ts, v in sorted(queue):
                if ts <= t_ns:
                    self.value[i] = v
                else:
                    keep.append((ts, v))
            self.pending[i] = keep

    def step(self, spin: Any) -> bool:
        """One plant step (False when ``duration_s`` is reached)."""
        j = self.stepper.j
        t = j * self.dt
        if self.duration > 0 and t >= self.duration - 1e-9:
            return False
        t_ns = int(round(t * 1e9))
        self.t_ns = t_ns
        sec, nsec = ns_to_stamp(t_ns)
        self.pub_clock.publish(Clock(clock=TimeMsg(sec=sec, nanosec=nsec)))
        points = self.stepper.centerline()
        per = self.sensor_rate * self.dt

        def sample(k: int) -> int:               # frame k is taken at plant sample j
            return int(np.floor(k / per + 1e-9))

        while sample(self.frame) < j:
            self.frame += 1
        if sample(self.frame) == j:
            while sample(self.frame) == j:
                self.frame += 1
            noisy = points + (self.noise * self.rng.standard_normal(points.shape)
                              if self.noise > 0 else 0.0)
            self.msg.header.stamp = TimeMsg(sec=sec, nanosec=nsec)
            set_points(self.positions, noisy)
            self.pub_measured.publish(self.msg)
        if self.lockstep > 0 and j > 0 and \
                abs(t / self.lockstep - round(t / self.lockstep)) < 1e-6:
            deadline = time.monotonic() + self.timeout
            stopping = self.stop_event.is_set if self.stop_event is not None else lambda: False
            while np.any(self.newest < t_ns) and time.monotonic() < deadline \
                    and not stopping():
                spin(0.002)
            if np.any(self.newest < t_ns) and not stopping():     # not a Ctrl-C
                self.held += 1
                self.get_logger().warning(
                    f'no command for t = {t:.3f} s within command_timeout_s '
                    f'({self.timeout:g} s): the last pressures are held; {self.held} '
                    'lockstep point(s) held so far', throttle_duration_sec=5.0)
        spin(0.0)
        self._apply(t_ns)
        if self.record_path:
            self.t_rec.append(t)
            self.U_rec.append(self.value.copy())
            self.Y_rec.append(np.concatenate([points[:, 0], points[:, 2]]))
        self.stepper.step(self.value.copy())
        return True

    def _check_values(self) -> None:
        """Refuse values the loop cannot run with (ValueError naming the parameter)."""
        if not 1 <= self.resolution <= 4:
            raise ValueError(f'resolution must be 1 to 4 (a plant steps in real time); '
                             f'got {self.resolution}')
        for name, value, low in (('sensor_rate_hz', self.sensor_rate, 'positive'),
                                 ('command_timeout_s', self.timeout, 'positive'),
                                 ('sensor_noise', self.noise, 'zero or positive'),
                                 ('lockstep_s', self.lockstep, 'zero or positive'),
                                 ('duration_s', self.duration, 'zero or positive')):
            if not (math.isfinite(value) and (value > 0 or (value == 0 and low != 'positive'))):
                raise ValueError(f'{name} must be finite and {low}; got {value!r}')
        if self.input_qos not in ('reliable', 'sensor_data'):
            raise ValueError(f'input_qos must be reliable or sensor_data; got {self.input_qos!r}')
        if self.wait_for_subscribers < 0:
            raise ValueError(f'wait_for_subscribers must be 0 or more; got '
                             f'{self.wait_for_subscribers}')

    def save(self) -> None:
        """Write ``record_path`` (when set)."""
        if not self.record_path or not self.t_rec:
            return
        np.savez(self.record_path, t=np.array(self.t_rec), U=np.array(self.U_rec).T,
                 Y=np.array(self.Y_rec).T, held=np.array(self.held))


def main(args: list[str] | None = None) -> int:
    """Run the plant until SIGINT/SIGTERM (or ``duration_s``); exit status 0 (1: bad parameter)."""
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT,
                                                                       signal.SIGTERM)}
    refused = init_rclpy(args)
    if refused is not None:
        for s, h in previous.items():
            signal.signal(s, h)
        print(f'soft_rom plant: bad command line (--ros-args): {refused}', file=sys.stderr)
        return 1
    node = None
    code = 0
    executor = SingleThreadedExecutor()
    try:
        try:
            node = PlantNode(parameter_overrides=[Parameter('use_sim_time', value=False)])
        except ValueError as err:
            print(f'soft_rom plant: cannot start: {err}', file=sys.stderr)
            return 1
        except ParameterException as err:       # a value of the wrong type
            print(f'soft_rom plant: cannot start: parameter {rclpy_reason(err)}', file=sys.stderr)
            return 1
        node.stop_event = stop
        warn_unknown_parameters(node)
        executor.add_node(node)

        def spin(timeout: float) -> None:
            executor.spin_once(timeout_sec=timeout)

        # start when a commander (the controller) publishes on every pressure topic, and
        # (wait_for_subscribers) the predictor listens, so that it sees the first commands
        others = 1 + node.wait_for_subscribers
        say = time.monotonic() + 5.0
        while not stop.is_set() and rclpy.ok() and not all(
                node.count_publishers(topic) and node.count_subscribers(topic) >= others
                for topic in node.command_topics):
            if say and time.monotonic() > say:
                say = 0.0
                node.get_logger().info(
                    f'waiting for a controller publishing on {", ".join(node.command_topics)}'
                    + (f' and {node.wait_for_subscribers} more subscriber(s) there (the '
                       'predictor)' if node.wait_for_subscribers else '')
                    + ' before the first step')
            spin(0.05)
        if node.wait_for_subscribers:
            end = time.monotonic() + 1.0      # the graph shows them: let the endpoints match
            while not stop.is_set() and time.monotonic() < end:
                spin(0.05)

        while not stop.is_set() and rclpy.ok():
            if not node.step(spin):
                node.save()
                node.record_path = ''
                while not stop.is_set() and rclpy.ok():
                    spin(0.1)
        if node.record_path:
            node.save()
    except SolverError as err:                  # the FOM diverged: it cannot go on
        assert node is not None                 # raised by node.step only
        node.get_logger().error(f'{err} Pressures at the end: '
                                f'{np.round(node.value / 1e3, 1).tolist()} kPa; exiting.')
        node.save()
        code = 1
    except KeyboardInterrupt:
        pass
    finally:
        executor.shutdown(timeout_sec=1.0)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        for s, h in previous.items():
            signal.signal(s, h)
    return code


if __name__ == '__main__':  # pragma: no cover
    sys.exit(main())
