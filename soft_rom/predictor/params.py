"""The predictor node's parameters, stated once (no ROS import).

:func:`predictor_config` makes the core's :class:`~soft_rom.predictor.PredictorConfig`
and :func:`loop_settings` the :class:`~soft_rom.predictor.loop.LoopSettings` from the same
values. The node declares each :class:`Param` with a ``ParameterDescriptor`` (description, range,
``read_only``); ``soft-rom replay --config`` reads the same names from the same YAML file
(``config/predictor.yaml``, ROS 2 params-file layout) so both run the core identically.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
import math
import numbers
from pathlib import Path
from typing import Any

from soft_rom.errors import ConfigError, show_value
from soft_rom.predictor.config import PredictorConfig
from soft_rom.predictor.loop import LoopSettings

__all__ = ['NODE_NAME', 'NODE_PARAMS', 'PARAMS', 'Param', 'check_param', 'load_params_file',
           'loop_settings', 'predictor_config', 'render_params_file']

NODE_NAME = 'soft_rom_predictor'


@dataclass(frozen=True)
class Param:
    """One node parameter: name, default, description, optional range, read-only flag."""

    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None
    read_only: bool = True
    choices: tuple[str, ...] | None = None


_CHAMBERS = [f'/soft_robot/pressure/chamber_{i}' for i in range(1, 7)]

PARAMS: tuple[Param, ...] = (
    Param('model_path', '', 'Model file (.npz) to run; set at run time to reload atomically.',
          read_only=False),
    Param('wait_for_model', False,
          'If the model cannot be loaded at start-up: true = stay up idle until a valid '
          'model_path is set; false = log the error and exit with status 1.'),
    Param('input_mode', 'per_chamber', 'per_chamber: one FluidPressure topic per input; '
          'array: one Float64MultiArray with all inputs.', choices=('per_chamber', 'array')),
    Param('input_topics', _CHAMBERS, 'FluidPressure topics, one per model input, in order.'),
    Param('array_topic', '/soft_robot/pressures', 'Float64MultiArray topic (input_mode array).'),
    Param('input_scale', 1.0, 'u = input_scale * value + input_offset (e.g. Pa to kPa).'),
    Param('input_offset', 0.0, 'u = input_scale * value + input_offset (e.g. gauge vs '
          'absolute pressure).'),
    Param('input_qos', 'sensor_data', 'QoS of input and measured subscriptions: sensor_data '
          '(best effort) or reliable.', choices=('sensor_data', 'reliable')),
    Param('qos_depth', 10, 'History depth of the subscriptions.', range=(1, 1000)),
    Param('stepping', 'event', 'event: the inputs drive the model up to the newest time at '
          'which every input is known (exact at the stamps); fixed: integrate at rate_hz on '
          'a timer; input: step exactly to each input stamp on arrival.',
          choices=('event', 'fixed', 'input')),
    Param('rate_hz', 0.0, 'Step rate (event and fixed stepping); 0 = the model rate 1/dt.',
          range=(0.0, 100000.0)),
    Param('publish_rate_hz', 0.0, 'Rate of ~/output on the model clock; 0 = every step.',
          range=(0.0, 100000.0)),
    Param('centerline_rate_hz', 30.0, 'Rate of ~/centerline and the markers (RViz); '
          '0 = with every output.', range=(0.0, 100000.0)),
    Param('diagnostics_rate_hz', 1.0, 'Rate of /diagnostics.', range=(0.01, 100.0)),
    Param('frame_id', 'world', 'Frame of the published centerline.'),
    Param('output_components', 'xz', 'Which coordinates the output vector holds, '
          'component-major (xz: [x_1..x_N, z_1..z_N]).'),
    Param('fill_value', 0.0, 'Coordinate value for components the model does not predict.'),
    Param('measured_topic', '/soft_robot/centerline', 'Measured centerline (PoseArray) for '
          'error monitoring and state correction; empty = none.'),
    # Predictor core settings (PredictorConfig); changeable at run time.
    Param('input_timeout_s', 0.5, 'An input silent longer than this: value held, STALE.',
          range=(0.0, 3600.0), read_only=False),
    Param('max_lag_s', 0.1, 'Most the model may trail the newest input stamp (event '
          'stepping); beyond it missing inputs are held.', range=(0.0, 3600.0),
          read_only=False),
    Param('error_window_s', 2.0, 'Measurements older than this leave the error window; '
          'an empty window after measurements is STALE.', range=(0.0, 1e6), read_only=False),
    Param('alarm_hold_s', 2.0, 'How long a dropped/clipped input, clock jump or divergence '
          'keeps the status WARN/ERROR.', range=(0.0, 3600.0), read_only=False),
    Param('input_min', [0.0], 'Input envelope, lower bounds (after scale/offset): one per '
          'input, or one for every input; [0.0] (the default) or empty = from the model file '
          '(training range). Must not exceed input_max.', read_only=False),
    Param('input_max', [0.0], 'Input envelope, upper bounds: one per input, or one for '
          'every input; [0.0] (the default) or empty = from the model file (training range). '
          'input_min and input_max can be set one at a time.', read_only=False),
    Param('input_envelope_margin', 1.0, 'The default input envelope is the training range '
          'widened by this times its width on each side.', range=(0.0, 1e6), read_only=False),
    Param('input_envelope_action', 'clip', 'clip or drop an input outside its envelope.',
          read_only=False, choices=('clip', 'drop')),
    Param('output_envelope_factor', 100.0, 'Divergence: max |y - y_ref| beyond this times '
          'the training max deviation (or max |y_ref|).', range=(1e-6, 1e12), read_only=False),
    Param('strict_model', False, 'Refuse a model that loads but cannot be trusted '
          '(unstable, indefinite K or C, absurd offsets); false = run it with a WARN.',
          read_only=False),
    Param('auto_reset', True, 'Reset the state to the reference when the prediction '
          'diverges.', read_only=False),
    Param('error_window', 100, 'Measurements in the windowed relative error.',
          range=(1, 1000000), read_only=False),
    Param('error_metric', 'deviation', 'Error held against the thresholds: deviation (from '
          'y_ref) or absolute.', read_only=False, choices=('deviation', 'absolute')),
    Param('warn_threshold', 0.0, 'Windowed relative error above which status is WARN; 0 = '
          "2 x the model's held-out error recorded in its file (0.1 for files without it).",
          range=(0.0, 100.0), read_only=False),
    Param('error_threshold', 0.0, 'Windowed relative error above which status is ERROR; 0 = '
          "4 x the model's held-out error recorded in its file (0.3 for files without it).",
          range=(0.0, 100.0), read_only=False),
    Param('initial_state', 'reference', 'reference, or measured (from the first measured '
          'centerline).', read_only=False, choices=('reference', 'measured')),
    Param('kalman', False, 'Correct the state with a steady-state Kalman filter at each '
          'measurement (default open loop, as in the paper).', read_only=False),
    Param('process_noise', 1e-6, 'Kalman process noise variance per state and step.',
          range=(1e-30, 1e30), read_only=False),
    Param('measurement_noise', 1e-4, 'Kalman measurement noise variance per output.',
          range=(1e-30, 1e30), read_only=False),
    Param('max_catchup_steps', 10000, 'Most integration steps in one update; beyond that '
          'model time jumps (counted).', range=(1, 10000000), read_only=False),
    Param('clock_reset_s', 1.0, 'An input stamp this much older than the newest (fixed '
          'stepping: the node clock going back this far) is a restarted clock (bag replayed): '
          'reset and take it; a measurement this far ahead of the model is dropped; 0 = never '
          '(drop as backwards).',
          range=(0.0, 1e9), read_only=False),
)

#: Parameters only the ROS node has (executor, lifecycle, diagnostics id); ``replay --config``
#: accepts and ignores them so that one params file serves both.
NODE_PARAMS: tuple[Param, ...] = (
    Param('lifecycle', False, 'true: a managed (lifecycle) node, started by configure and '
          'activate transitions; false: a plain node that starts at once.'),
    Param('executor', 'events', 'rclpy executor: events (rclpy.experimental.EventsExecutor: '
          'about half the CPU per message, what 1 kHz inputs need; falls back to '
          'single_threaded where this rclpy lacks it) or single_threaded '
          '(SingleThreadedExecutor).', choices=('events', 'single_threaded')),
    Param('hardware_id', '', "hardware_id of the /diagnostics statuses; empty = the node's "
          'fully qualified name.'),
)

#: ``input_min`` / ``input_max`` at this value (their default; ROS 2 cannot declare an empty
#: double array) mean "not set": that bound comes from the model file. A zero bound for
#: every input is written out per input (``[0.0, 0.0, ...]``).
UNSET_BOUND = (0.0,)

_CONFIG_FIELDS = {f.name for f in fields(PredictorConfig)}
_BY_NAME = {p.name: p for p in PARAMS + NODE_PARAMS}


def _float(value: Any) -> float | None:
    """``value`` as a finite float, or ``None``.

    Accepts the numbers YAML writes as strings (PyYAML reads ``1e3`` as the string '1e3'
    while ROS reads it as a double), refuses booleans.
    """
    if isinstance(value, bool) or not isinstance(value, (numbers.Real, str)):
        return None
    try:
        x = float(value)
    except (ValueError, OverflowError):
        return None
    return x if math.isfinite(x) else None


def _int(value: Any) -> int | None:
    if isinstance(value, bool):
        return None
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, str):
        try:
            return int(value.strip().replace('_', ''), 10)
        except ValueError:
            return None
    return None


def check_param(name: str, value: Any) -> Any:
    """``value`` of parameter ``name``, of the parameter's type, in its range and choices.

    The type is that of the parameter's default (bool, int, float, str, list of str, list
    of float); integers are taken for floats and numbers spelled as strings (``1e3``) for
    numbers. Unknown names (``use_sim_time``) pass unchanged.

    Raises
    ------
    ConfigError
        ``'NAME must be ...; got VALUE.'``: the value does not fit.
    """
    p = _BY_NAME.get(name)
    if p is None:
        return value
    default = p.default
    out: Any
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f'{name} must be true or false; got {show_value(value)}.')
        return value
    if isinstance(default, (int, float)):
        kind = 'an integer' if isinstance(default, int) else 'a number'
        out = _int(value) if isinstance(default, int) else _float(value)
        fmt = 'd' if isinstance(default, int) else 'g'
        within = '' if p.range is None else (f' in {p.range[0]:{fmt}}..'
                                             f'{p.range[1]:{fmt}}')
        if out is None or (p.range is not None and not p.range[0] <= out <= p.range[1]):
            raise ConfigError(f'{name} must be {kind}{within}; got {show_value(value)}.')
        if name == 'input_scale' and out == 0:
            raise ConfigError('input_scale must not be 0 (every input would read 0); got 0.')
        return out
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f'{name} must be a string; got {show_value(value)}.')
        if p.choices is not None and value not in p.choices:
            raise ConfigError(f'{name} must be one of {", ".join(p.choices)}; got '
                              f'{show_value(value)}.')
        return value
    # lists: of strings (topics) or of numbers (bounds); rclpy gives array.array for the
    # latter
    strings = all(isinstance(v, str) for v in default)
    what = 'a list of strings' if strings else 'a list of numbers'
    if value is None or isinstance(value, (str, bytes, Mapping)):
        raise ConfigError(f'{name} must be {what}; got {show_value(value)}.')
    try:
        items = list(value)
    except TypeError:
        raise ConfigError(f'{name} must be {what}; got {show_value(value)}.') from None
    out = [v if isinstance(v, str) else None for v in items] if strings else [
        _float(v) for v in items]
    if any(v is None for v in out):
        raise ConfigError(f'{name} must be {what}; got {show_value(value)}.')
    return out


def predictor_config(values: Mapping[str, Any]) -> PredictorConfig:
    """The :class:`PredictorConfig` from node parameter values (other names ignored).

    Each value is checked by :func:`check_param`; a bad one raises
    :class:`~soft_rom.errors.ConfigError` naming the parameter.
    """
    kwargs = {k: _checked(k, v) for k, v in values.items() if k in _CONFIG_FIELDS}
    for name in ('input_min', 'input_max'):
        if name in kwargs:
            bound = tuple(kwargs[name])
            kwargs[name] = () if bound == UNSET_BOUND else bound   # the node's "unset" value
    return PredictorConfig(**kwargs)


def _checked(name: str, value: Any) -> Any:
    try:
        return check_param(name, value)
    except ConfigError as err:
        raise ConfigError(f'parameter {err}') from err


def loop_settings(values: Mapping[str, Any]) -> LoopSettings:
    """The :class:`LoopSettings` from node parameter values (defaults for missing ones)."""
    d = {p.name: p.default for p in PARAMS}
    d.update({k: _checked(k, v) for k, v in values.items()})
    return LoopSettings(output_rate_hz=float(d['publish_rate_hz']),
                        centerline_rate_hz=float(d['centerline_rate_hz']),
                        diagnostics_rate_hz=float(d['diagnostics_rate_hz']),
                        components=str(d['output_components']),
                        fill_value=float(d['fill_value']),
                        input_scale=float(d['input_scale']),
                        input_offset=float(d['input_offset']))


def load_params_file(path: str | Path, node_name: str = NODE_NAME) -> dict[str, Any]:
    """Read ``ros__parameters`` of ``node_name`` (or ``/**``) from a ROS 2 params YAML file.

    Each value is checked and converted by :func:`check_param`.

    Raises
    ------
    ConfigError
        The file is not UTF-8 YAML, a section is not a mapping, a parameter name is
        unknown or a value does not fit; the message names the file and the parameter.
    """
    import yaml

    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text(encoding='utf-8'))
    except UnicodeDecodeError as err:
        raise ConfigError(f'{path}: not UTF-8 text (byte {err.start}); give a ROS 2 params '
                          'YAML file like config/predictor.yaml.') from err
    except yaml.YAMLError as err:
        raise ConfigError(f'{path}: not valid YAML ({err}).') from err
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: a ROS 2 params file must map node names ('/**:') to "
                          f'sections; got {show_value(doc)}.')
    values: dict[str, Any] = {}
    for key in ('/**', node_name, f'/{node_name}'):
        if key not in doc:
            continue
        section = doc[key]
        if section is None:
            continue
        if not isinstance(section, dict):
            raise ConfigError(f"{path}: section {key!r} must be a mapping with "
                              f"'ros__parameters:'; got {show_value(section)}.")
        params = section.get('ros__parameters')
        if params is None:
            continue
        if not isinstance(params, dict):
            raise ConfigError(f'{path}: ros__parameters of {key!r} must be a mapping of '
                              f'parameter names to values; got {show_value(params)}.')
        values.update(params)
    unknown = sorted((str(k) for k in set(values) - set(_BY_NAME) - {'use_sim_time'}))
    if unknown:
        raise ConfigError(f'{path}: unknown predictor parameters {unknown}; known: '
                          f'{sorted(_BY_NAME)}.')
    for name, value in values.items():
        try:
            values[name] = check_param(name, value)
        except ConfigError as err:
            raise ConfigError(f'{path}: parameter {err}') from err
    return values


_HEADER = """\
# Parameters of the soft_rom predictor node (`ros2 run soft_rom predictor`).
# Also read by `soft-rom replay --config` so that replay runs the core exactly like the node.
# Start: ros2 launch soft_rom predictor.launch.py model_path:=/path/to/model.npz
# Keyed '/**' (any node name) so that it still applies when the launch file's node_name
# argument renames the node; a section keyed by node name would then be ignored by rcl.
# Generated from soft_rom/predictor/params.py (render_params_file); edit there.
/**:
  ros__parameters:
"""


def _yaml_value(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    if isinstance(value, float):
        text = repr(value)
        if 'e' in text and '.' not in text.split('e')[0]:
            mant, exp = text.split('e')
            text = f'{mant}.0e{exp}'
        return text
    return str(value)


def render_params_file() -> str:
    """``config/predictor.yaml``: every parameter with its default and description."""
    import textwrap

    lines = [_HEADER.rstrip('\n')]
    for p in PARAMS:
        text = p.description
        if p.range is not None and not isinstance(p.default, bool):
            lo, hi = p.range
            text += f' Range {lo:g}..{hi:g}.'
        if not p.read_only:
            text += ' (Changeable at run time.)'
        lines += textwrap.wrap(text, 99, initial_indent='    # ', subsequent_indent='    # ')
        if isinstance(p.default, list):
            lines.append(f'    {p.name}:')
            lines += [f'      - {_yaml_value(v)}' for v in p.default]
        else:
            lines.append(f'    {p.name}: {_yaml_value(p.default)}')
    return '\n'.join(lines) + '\n'
