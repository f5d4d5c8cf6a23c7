"""Declaring the predictor node's parameters, and refusing or applying run-time changes.

The core's parameters (names, defaults, ranges, which change at run time) are stated once
in :mod:`soft_rom.predictor.params`; two more exist only on the node (``NODE_PARAMS``).

* A double parameter accepts an integer (``-p rate_hz:=100``, ``ros2 param set ... 100``),
  and a double array an integer array (``input_max:=[100000]``): they are converted before
  rclpy checks the type.
* A refused change is logged at WARN with the reason (read-only, wrong type, out of range,
  undeclared, or refused by the core / the model file) and returned as the reason to the
  caller. Each change of a run-time parameter is checked together with every other setting
  as it is in force (``input_min`` against the ``input_max`` in force, ``warn_threshold``
  against ``error_threshold``, ...), so that one ``ros2 param set`` at a time works.
* At start-up a bad value (wrong type, out of range, not one of the choices, an empty list)
  raises :class:`~soft_rom.errors.ConfigError` naming the parameter, before rclpy would
  raise its own exception.
"""

from __future__ import annotations

from dataclasses import dataclass
import re
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import ParameterException
from rclpy.logging import get_logger_level, LoggingSeverity, set_logger_level
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions

from soft_rom.errors import ConfigError, show_value
from soft_rom.predictor import PredictorConfig
from soft_rom.predictor.loop import LoopSettings
from soft_rom.predictor.params import loop_settings as _loop_settings
from soft_rom.predictor.params import NODE_PARAMS, Param, PARAMS, predictor_config

__all__ = ['NODE_PARAMS', 'NodeSettings', 'ParameterMixin', 'init_rclpy', 'rclpy_reason',
           'warn_unknown_parameters', 'watch_sim_clock']

ALL_PARAMS = PARAMS + NODE_PARAMS
_BY_NAME = {p.name: p for p in ALL_PARAMS}
_DOUBLE_ARRAYS = {p.name for p in ALL_PARAMS
                  if isinstance(p.default, list) and p.default
                  and all(isinstance(v, float) for v in p.default)}
_DOUBLES = {p.name for p in ALL_PARAMS
            if isinstance(p.default, float) and not isinstance(p.default, bool)}


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
    diagnostics_rate_hz: float
    frame_id: str
    output_components: str
    fill_value: float
    measured_topic: str
    wait_for_model: bool
    lifecycle: bool
    executor: str
    hardware_id: str


def _descriptor(p: Param) -> ParameterDescriptor:
    text = p.description
    if p.choices:
        text += f' One of: {", ".join(p.choices)}.'
    if not p.read_only:
        text += ' Changeable at run time.'
    d = ParameterDescriptor(description=text, read_only=p.read_only)
    if p.choices:
        d.additional_constraints = f'one of {", ".join(p.choices)}'
    if p.range is not None and not isinstance(p.default, bool):
        if isinstance(p.default, int):
            d.integer_range = [IntegerRange(from_value=int(p.range[0]),
                                            to_value=int(p.range[1]), step=1)]
        elif isinstance(p.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(p.range[0]),
                                                         to_value=float(p.range[1]),
                                                         step=0.0)]
    return d


def _type_or_range(p: Param, param: Parameter) -> str | None:
    expected = Parameter.Type.from_parameter_value(p.default)
    if param.type_ != expected:
        return (f'{param.name} must be of type {expected.name}; got {param.type_.name} '
                f'{show_value(param.value)}')
    if p.range is not None and not p.range[0] <= param.value <= p.range[1]:
        return f'{param.name} = {param.value!r} outside {p.range[0]:g}..{p.range[1]:g}'
    return None


_WRONG_TYPE = re.compile(r"Trying to set parameter '(?P<name>[^']*)' to '(?P<value>.*)' of "
                         r"type '(?P<got>\w+)', expecting type '(?:Type\.)?(?P<want>\w+)'")


def rclpy_reason(err: ParameterException) -> str:
    """One of rclpy's parameter exceptions as ``'NAME must be ...'`` (or its own text)."""
    text = str(err)
    text = text.rsplit(': ', 1)[0] if ': ' in text else text    # its trailing ': NAME'
    wrong = _WRONG_TYPE.fullmatch(text)
    if wrong:
        return (f'{wrong["name"]} must be of type {wrong["want"]}; got {wrong["got"]} '
                f'{wrong["value"]}')
    return text


def _as_double(param: Parameter) -> Parameter:
    """An integer (or integer array) given for a double (array) parameter, converted."""
    if param.name in _DOUBLES and param.type_ == Parameter.Type.INTEGER:
        return Parameter(param.name, Parameter.Type.DOUBLE, float(param.value))
    if param.name in _DOUBLE_ARRAYS and param.type_ == Parameter.Type.INTEGER_ARRAY:
        return Parameter(param.name, Parameter.Type.DOUBLE_ARRAY,
                         [float(v) for v in param.value])
    return param


class ParameterMixin:
    """Parameter handling of :class:`~soft_rom.ros.predictor_node.PredictorNode`.

    The node implements ``apply_parameters(names, values)``, which raises to refuse.
    """

    def declare_predictor_parameters(self) -> NodeSettings:
        """Declare every parameter (integers given for doubles converted); the settings.

        Raises
        ------
        ConfigError
            A value given at start-up (``-p``, ``--params-file``) does not fit: wrong type,
            out of range, not one of the choices, or an empty list (which has no type in
            ROS 2). The message names the parameter.
        """
        overrides = self._parameter_overrides  # type: ignore[attr-defined]
        for name, param in list(overrides.items()):
            param = overrides[name] = _as_double(param)
            p = _BY_NAME.get(name)
            why = None if p is None else self._start_refusal(p, param)
            if why:
                raise ConfigError(f'parameter {why}.')
        for p in ALL_PARAMS:
            try:
                self.declare_parameter(p.name, p.default,  # type: ignore[attr-defined]
                                       _descriptor(p))
            except ParameterException as err:     # what the check above did not foresee
                raise ConfigError(f'parameter {p.name}: {rclpy_reason(err)}.') from None
        self.check_settings()
        self.add_pre_set_parameters_callback(self._pre_set)  # type: ignore[attr-defined]
        self.add_on_set_parameters_callback(self._on_set)  # type: ignore[attr-defined]
        v = self.parameter_values()
        return NodeSettings(
            input_mode=str(v['input_mode']), input_topics=tuple(v['input_topics']),
            array_topic=str(v['array_topic']), input_scale=float(v['input_scale']),
            input_offset=float(v['input_offset']), input_qos=str(v['input_qos']),
            qos_depth=int(v['qos_depth']),
            diagnostics_rate_hz=float(v['diagnostics_rate_hz']), frame_id=str(v['frame_id']),
            output_components=str(v['output_components']), fill_value=float(v['fill_value']),
            measured_topic=str(v['measured_topic']), wait_for_model=bool(v['wait_for_model']),
            lifecycle=bool(v['lifecycle']), executor=str(v['executor']),
            hardware_id=str(v['hardware_id']))

    def parameter_values(self, changes: list[Parameter] | None = None) -> dict[str, Any]:
        """Every parameter's value, with ``changes`` applied over them."""
        values = {p.name: self.get_parameter(p.name).value  # type: ignore[attr-defined]
                  for p in ALL_PARAMS}
        for param in changes or []:
            values[param.name] = param.value
        return values

    def settings_value(self, name: str) -> Any:
        """One parameter's current value."""
        return self.get_parameter(name).value  # type: ignore[attr-defined]

    def predictor_config(self, values: dict[str, Any] | None = None) -> PredictorConfig:
        """The core's settings from the parameters (or from ``values``)."""
        return predictor_config(self.parameter_values() if values is None else values)

    def loop_settings(self) -> LoopSettings:
        """The runtime loop's settings (publish rates, layout, input scaling)."""
        return _loop_settings(self.parameter_values())

    def check_settings(self) -> None:
        """Refuse settings outside their choices (a start-up error): ConfigError."""
        for p in ALL_PARAMS:
            if p.choices and self.settings_value(p.name) not in p.choices:
                raise ConfigError(f'parameter {p.name} must be one of '
                                  f'{", ".join(p.choices)}; got '
                                  f'{show_value(self.settings_value(p.name))}.')

    def check_core_settings(self) -> None:
        """Build the core's and the loop's settings once: ConfigError naming the parameter."""
        self.predictor_config()
        self.loop_settings()

    def _warn_refused(self, reason: str) -> None:
        self.get_logger().warning(  # type: ignore[attr-defined]
            f'parameter change refused: {reason}')

    def _pre_set(self, params: list[Parameter]) -> list[Parameter]:
        # Runs before rclpy's own checks: converts integers for doubles, and logs (WARN) the
        # refusals that rclpy then returns without logging (read-only, type, range,
        # undeclared), for this node's parameters and rclpy's own (use_sim_time).
        out = []
        for param in params:
            param = _as_double(param)
            p = _BY_NAME.get(param.name)
            why = self._refusal(p, param) if p is not None else self._other_refusal(param)
            if why:
                self._warn_refused(why)
            out.append(param)
        return out

    @staticmethod
    def _refusal(p: Param, param: Parameter) -> str | None:
        if p.read_only:
            return (f'{param.name} is read-only (set it at start-up: --ros-args -p '
                    f'{param.name}:=VALUE)')
        return _type_or_range(p, param)

    @staticmethod
    def _start_refusal(p: Param, param: Parameter) -> str | None:
        if param.type_ == Parameter.Type.NOT_SET:
            return (f'{param.name} has no value (an empty list has no type in ROS 2): leave '
                    'it out for its default, or give values')
        why = _type_or_range(p, param)
        if why is None and p.choices and param.value not in p.choices:
            why = (f'{param.name} must be one of {", ".join(p.choices)}; got '
                   f'{show_value(param.value)}')
        return why

    def _other_refusal(self, param: Parameter) -> str | None:
        """Why rclpy will refuse a change of a parameter that is not the predictor's own."""
        node: Any = self
        if not node.has_parameter(param.name):
            return f'{param.name} is not a parameter of this node'
        d = node.describe_parameter(param.name)
        if d.read_only:
            return f'{param.name} is read-only'
        if d.dynamic_typing:
            return None
        expected = Parameter.Type(d.type)
        if param.type_ == Parameter.Type.NOT_SET:
            return f'{param.name} cannot be undeclared'
        if param.type_ != expected:
            return (f'{param.name} must be of type {expected.name}; got {param.type_.name} '
                    f'{show_value(param.value)}')
        return None

    def _on_set(self, params: list[Parameter]) -> SetParametersResult:
        names = {p.name for p in params}
        changeable = {p.name for p in ALL_PARAMS if not p.read_only}
        if not names & changeable:
            return SetParametersResult(successful=True)
        try:
            self.apply_parameters(names, self.parameter_values(params))  # type: ignore
        except Exception as err:  # noqa: BLE001 - refused, running model stays
            why = str(err).rstrip('.')
            reason = f'{type(err).__name__}: {why}; the running model is unchanged'
            self._warn_refused(reason)
            return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)


def init_rclpy(args: list[str] | None) -> str | None:
    """``rclpy.init``; ``None``, or why the command line was refused (one line).

    rcl's own "Failed to parse global arguments" error line is held back meanwhile: the
    reason returned says more (which ``-p`` rule, which file).
    """
    quiet = get_logger_level('rcl') == LoggingSeverity.UNSET
    if quiet:
        set_logger_level('rcl', LoggingSeverity.FATAL)
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except RuntimeError as err:         # rclpy's RCLError: a bad --ros-args
        text = re.sub(r'(\. Error: error not set)?\s*,? at /\S+:\d+', '', str(err))
        return ' '.join(text.split()).removeprefix('failed to initialize rcl: ')
    finally:
        if quiet and get_logger_level('rcl') == LoggingSeverity.FATAL:
            set_logger_level('rcl', LoggingSeverity.UNSET)
    return None


def warn_unknown_parameters(node: Any) -> list[str]:
    """Log the parameters given to ``node`` (params file, ``-p``) that it does not declare.

    rclpy ignores them without a word; most are typos (``kalmann``). Returns their names.
    """
    given = getattr(node, '_parameter_overrides', None) or {}
    unknown = sorted(name for name in given if not node.has_parameter(name))
    if unknown:
        node.get_logger().warning(
            f'parameter(s) {", ".join(unknown)} given but not declared by this node: ignored '
            '(a typo?)')
    return unknown


def watch_sim_clock(node: Any, after_s: float = 5.0) -> None:
    """With ``use_sim_time``, say so once if no ``/clock`` came ``after_s`` s after start.

    Under sim time the node's timers wait for ``/clock``: without it the node publishes
    nothing (no diagnostics either), which looked like a hang. The check runs on the
    steady clock.
    """
    if not node.get_parameter('use_sim_time').value:
        return

    def check() -> None:
        timer.cancel()
        if node.get_clock().now().nanoseconds == 0:
            node.get_logger().warning(
                f'use_sim_time is true and no /clock has come in {after_s:g} s: waiting for '
                'it (nothing is published until then)')

    timer = node.create_timer(after_s, check, clock=Clock(clock_type=ClockType.STEADY_TIME))
