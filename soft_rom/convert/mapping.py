"""The topic mapping of a conversion: inputs, output, state and the time options.

The mapping is validated when it is built (:meth:`BagMapping.from_dict`,
:func:`load_mapping`, :meth:`BagMapping.replace`).

See :mod:`soft_rom.convert` for what each key means and ``config/bag_mapping.yaml`` for a
documented file.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
import json
import math
from pathlib import Path
import re
from typing import Any

import numpy as np

from soft_rom.errors import ConfigError, show_value
from soft_rom.layout import COMPONENTS, ORDERS, OutputLayout

__all__ = ['ARRAY_TYPES', 'BagMapping', 'InputSource', 'OUTPUT_TYPES', 'OutputMapping',
           'PRESSURE_TYPES', 'STATE_TYPES', 'StateMapping', 'load_mapping', 'per_input']

PRESSURE_TYPES = ('sensor_msgs/msg/FluidPressure',)
ARRAY_TYPES = ('std_msgs/msg/Float64MultiArray', 'std_msgs/msg/Float32MultiArray')
OUTPUT_TYPES = ('geometry_msgs/msg/PoseArray', 'geometry_msgs/msg/PoseStamped')
STATE_TYPES = ARRAY_TYPES + ('sensor_msgs/msg/PointCloud2',)
CHAMBER_RE = re.compile(r'^/soft_robot/pressure/chamber_(\d+)$')
DEFAULT_ARRAY_TOPIC = '/soft_robot/pressures'


# ---------------------------------------------------------------------------------------
# mapping
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class InputSource:
    """One input topic: a ``FluidPressure`` (one value) or a multi-array with a selection.

    Parameters
    ----------
    topic : str
    indices : tuple of int, optional
        Array elements to take (multi-arrays); ``None`` takes all of them.
    """

    topic: str
    indices: tuple[int, ...] | None = None


@dataclass(frozen=True)
class OutputMapping:
    """Which centerline points and components form ``y``."""

    topic: str = '/soft_robot/centerline'
    points: tuple[int, ...] | None = None
    n_points: int | None = None
    components: tuple[str, ...] = ('x', 'z')
    order: str = 'component_major'
    units: str = 'm'

    def layout(self, n_points: int) -> OutputLayout:
        """The output layout for a message of ``n_points`` points (stored with the data)."""
        pts = tuple(self.points) if self.points is not None else tuple(range(n_points))
        return OutputLayout(tuple(self.components), self.order, pts)

    def names(self, n_points: int) -> list[str]:
        """Output names for a message of ``n_points`` points."""
        return self.layout(n_points).names()


@dataclass(frozen=True)
class StateMapping:
    """The full-state topic; ``include=None`` means 'if the bag has it'."""

    topic: str = '/soft_robot/state'
    include: bool | None = None


@dataclass(frozen=True)
class BagMapping:
    """Topic mapping and time options of a conversion (see the module docstring).

    Parameters
    ----------
    inputs : tuple of InputSource, optional
        ``None`` detects the pressure topics in each bag (``topics: auto``).
    input_names, input_units : tuple of str, optional
        Default ``p1..pm`` and ``Pa``.
    scale, offset : tuple of float
        Per input (or one value for all): ``u = scale * raw + offset``.
    output, state : OutputMapping, StateMapping
    stamps : {'header', 'log'}
        Time messages by their header stamp when they have one, or always by log time.
    match_tolerance : float, optional
        Seconds; output/state pairing tolerance (default 0.45 of the output's median period).
    dt : float, optional
        Step of the uniform grid (s); default the output's median period.
    max_gap : float
        Longest stretch without output samples that is interpolated, in output periods
        (default 1.5: one lost frame in a row); a longer one splits the episode.
    split_gap : float, optional
        Seconds; split where consecutive samples are further apart than this (overrides
        ``max_gap``).
    min_samples : int
        When a bag is split, pieces with fewer grid points are dropped and reported
        (default 32: enough for every learner's derivative stencil); a bag that is not
        split is kept from 2 samples on.
    """

    inputs: tuple[InputSource, ...] | None = None
    input_names: tuple[str, ...] | None = None
    input_units: tuple[str, ...] | None = ('Pa',)
    scale: tuple[float, ...] = (1.0,)
    offset: tuple[float, ...] = (0.0,)
    output: OutputMapping = field(default_factory=OutputMapping)
    state: StateMapping = field(default_factory=StateMapping)
    stamps: str = 'header'
    match_tolerance: float | None = None
    dt: float | None = None
    max_gap: float = 1.5
    split_gap: float | None = None
    min_samples: int = 32

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> BagMapping:
        """Build from the YAML structure of ``config/bag_mapping.yaml``.

        Every key is type-checked here, once: a wrong type or value raises
        :class:`~soft_rom.errors.ConfigError` naming the key (``output.points``, ...), in
        the order of the file, top to bottom.
        """
        if d is None:
            d = {}
        if not isinstance(d, Mapping):
            raise ConfigError(f'a mapping must be a mapping of sections (inputs, output, state, '
                              f'time); got {show_value(d)}.')
        unknown = set(d) - {'inputs', 'output', 'state', 'time'}
        if unknown:
            raise ConfigError(f'unknown mapping section(s) {_sorted(unknown)}; expected inputs, '
                              'output, state, time.')
        inp = _section('inputs', d.get('inputs'))
        out = _section('output', d.get('output'))
        st = _section('state', d.get('state'))
        tm = _section('time', d.get('time'))
        _no_extra('inputs', inp, {'sources', 'topics', 'topic', 'indices', 'slice', 'names',
                                  'units', 'scale', 'offset'})
        _no_extra('output', out, {'topic', 'points', 'n_points', 'components', 'order',
                                  'units'})
        _no_extra('state', st, {'topic', 'include'})
        _no_extra('time', tm, {'stamps', 'match_tolerance', 'dt', 'max_gap', 'split_gap',
                               'min_samples'})
        sources = _input_sources(inp)
        names = _strs('inputs.names', inp.get('names'), one=False)
        units = _strs('inputs.units', inp.get('units', 'Pa'), one=True)
        comps = _components(out.get('components', ('x', 'z')))
        order = _choice('output.order', out.get('order', 'component_major'), ORDERS)
        stamps = _choice('time.stamps', tm.get('stamps', 'header'), ('header', 'log'))
        points = _indices('output.points', out.get('points'))
        if points is not None and len(set(points)) < len(points):
            raise ConfigError(f"output.points must be distinct point indices; got "
                              f"{show_value(out['points'])}.")
        include = st.get('include')
        if include is not None and not isinstance(include, bool):
            raise ConfigError(f'state.include must be true, false or null (if the bag has '
                              f'the state topic); got {show_value(include)}.')
        return cls(
            inputs=None if sources is None else tuple(sources),
            input_names=names,
            input_units=units,
            scale=_floats('inputs.scale', inp.get('scale', 1.0)),
            offset=_floats('inputs.offset', inp.get('offset', 0.0)),
            output=OutputMapping(
                topic=_topic('output.topic', out.get('topic', OutputMapping.topic)),
                points=points,
                n_points=_opt_count('output.n_points', out.get('n_points')),
                components=comps, order=order,
                units=_topic('output.units', out.get('units', 'm'), what='a unit')),
            state=StateMapping(topic=_topic('state.topic', st.get('topic', StateMapping.topic),
                                            hint=' (to leave the state out, set '
                                                 'state.include: false)'),
                               include=include),
            stamps=stamps,
            match_tolerance=_opt_pos('time.match_tolerance', tm.get('match_tolerance')),
            dt=_opt_pos('time.dt', tm.get('dt')),
            max_gap=_nonneg('time.max_gap', tm.get('max_gap', 1.5)),
            split_gap=_opt_pos('time.split_gap', tm.get('split_gap')),
            min_samples=_min_samples(tm.get('min_samples', 32)))

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (stored in the training set's provenance)."""
        return json.loads(json.dumps(asdict(self)))

    def replace(self, **changes: Any) -> BagMapping:
        """A copy with ``changes`` applied, validated like a mapping file."""
        d = {f: getattr(self, f) for f in self.__dataclass_fields__}
        d.update(changes)
        new = BagMapping(**d)
        return BagMapping.from_dict(new.to_yaml_dict())

    def to_yaml_dict(self) -> dict[str, Any]:
        """The structure of a mapping file (``from_dict(m.to_yaml_dict()) == m``)."""
        d = self.to_dict()
        inputs: dict[str, Any] = {}
        if d['inputs'] is not None:
            inputs['sources'] = [{'topic': s['topic'], 'indices': s['indices']}
                                 for s in d['inputs']]
        if d['input_names'] is not None:
            inputs['names'] = d['input_names']
        inputs['units'] = d['input_units']
        inputs['scale'] = d['scale']
        inputs['offset'] = d['offset']
        return {'inputs': inputs, 'output': d['output'], 'state': d['state'],
                'time': {k: d[k] for k in ('stamps', 'match_tolerance', 'dt', 'max_gap',
                                           'split_gap', 'min_samples')}}


def _sorted(keys: Any) -> list[str]:
    return sorted(str(k) for k in keys)


def _input_sources(inp: Mapping[str, Any]) -> list[InputSource] | None:
    """The input sources of the ``inputs`` section (``None``: every pressure topic, ``auto``)."""
    sources: list[InputSource] | None
    if 'sources' in inp:
        if not isinstance(inp['sources'], (list, tuple)):
            raise ConfigError(f'inputs.sources must be a list of sources (a topic, or '
                              f'{{topic, slice}} / {{topic, indices}}); got '
                              f"{show_value(inp['sources'])}.")
        sources = [_source('inputs.sources', s) for s in inp['sources']]
    elif 'topic' in inp:
        sources = [_source('inputs', {k: inp[k] for k in ('topic', 'indices', 'slice')
                                      if k in inp})]
    elif inp.get('topics', 'auto') in ('auto', None):
        sources = None
    elif isinstance(inp['topics'], (list, tuple)):
        sources = [InputSource(_topic('inputs.topics', t)) for t in inp['topics']]
    else:
        raise ConfigError(f"inputs.topics must be 'auto' or a list of topics; got "
                          f"{show_value(inp['topics'])}.")
    if sources is not None and not sources:
        raise ConfigError('inputs: at least one input source is needed.')
    return sources


def _components(comps_v: Any) -> tuple[str, ...]:
    """``output.components``: distinct x, y, z (``'xz'`` spells ``[x, z]``)."""
    if isinstance(comps_v, str):
        comps_v = list(comps_v)          # 'xz' spells [x, z]
    if not isinstance(comps_v, (list, tuple)) or not all(isinstance(c, str)
                                                         for c in comps_v):
        raise ConfigError(f'output.components must be a list of distinct x, y, z; got '
                          f'{show_value(comps_v)}.')
    comps = tuple(comps_v)
    if not comps or any(c not in COMPONENTS for c in comps) or len(set(comps)) < len(comps):
        raise ConfigError(f'output.components must be a list of distinct x, y, z; got '
                          f'{show_value(list(comps))}.')
    return comps


def _section(name: str, v: Any) -> dict[str, Any]:
    if v is None:
        return {}
    if not isinstance(v, Mapping):
        raise ConfigError(f'mapping section {name!r} must be a mapping of keys (see '
                          f'config/bag_mapping.yaml); got {show_value(v)}.')
    return dict(v)


def _no_extra(section: str, d: Mapping[str, Any], allowed: set[str]) -> None:
    extra = set(d) - allowed
    if extra:
        raise ConfigError(f'unknown key(s) {_sorted(extra)} in mapping section {section!r}; '
                          f'allowed: {sorted(allowed)}.')


def _topic(name: str, v: Any, *, what: str = 'a topic name', hint: str = '') -> str:
    if not isinstance(v, str) or not v:
        raise ConfigError(f'{name} must be {what} (a non-empty string); got {show_value(v)}'
                          f'{hint}.')
    return v


def _strs(name: str, v: Any, *, one: bool) -> tuple[str, ...] | None:
    """``None``, or a list of strings (``one``: or one string for all).

    Names (``one=False``) may be numbers (``[1, 2]`` names the inputs '1', '2').
    """
    if v is None:
        return None
    if one and isinstance(v, str):
        return (v,)
    kinds: tuple[type, ...] = (str,) if one else (str, int, float)
    if (not isinstance(v, (list, tuple)) or not v
            or not all(isinstance(x, kinds) and not isinstance(x, bool) for x in v)):
        what = 'one unit or a list of units' if one else 'a list of names'
        raise ConfigError(f'{name} must be {what}; got {show_value(v)}.')
    return tuple(str(x) for x in v)


def _is_int(x: Any) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, (bool, np.bool_))


def _indices(name: str, v: Any) -> tuple[int, ...] | None:
    """``None``, or a non-empty list of 0-based indices (integers, not 1.5 or true)."""
    if v is None:
        return None
    if not isinstance(v, (list, tuple)) or not all(_is_int(i) for i in v):
        raise ConfigError(f'{name} must be a list of integers (0-based indices); got '
                          f'{show_value(v)}.')
    if not v:
        raise ConfigError(f'{name} must list at least one index (or be null for all); got [].')
    if any(i < 0 for i in v):
        raise ConfigError(f'{name} must be 0-based indices (>= 0); got {show_value(v)}.')
    return tuple(int(i) for i in v)


def _source(name: str, s: Any) -> InputSource:
    if isinstance(s, str) and s:
        return InputSource(s)
    if not isinstance(s, Mapping) or 'topic' not in s:
        raise ConfigError(f'{name}: an input source needs a topic; got {show_value(s)}.')
    _no_extra(name, s, {'topic', 'indices', 'slice'})
    topic = _topic(f'{name} topic', s['topic'])
    idx = _indices(f'{name} indices of {topic}', s.get('indices'))
    if s.get('slice') is not None:
        sl = s['slice']
        if (not isinstance(sl, (list, tuple)) or len(sl) != 2
                or not all(_is_int(i) for i in sl) or not 0 <= sl[0] < sl[1]):
            raise ConfigError(f'{name} slice of {topic} must be [start, stop], integers with '
                              f'0 <= start < stop; got {show_value(sl)}.')
        idx = tuple(range(int(sl[0]), int(sl[1])))
    return InputSource(topic, idx)


def _floats(name: str, v: Any) -> tuple[float, ...]:
    vals: list[Any] = list(v) if isinstance(v, (list, tuple)) else [v]
    if not vals or any(isinstance(x, (bool, np.bool_)) for x in vals):
        raise ConfigError(f'{name} must be a number or a list of numbers; got {show_value(v)}.')
    try:
        out = tuple(float(x) for x in vals)
    except (TypeError, ValueError) as err:
        raise ConfigError(f'{name} must be a number or a list of numbers; got {show_value(v)}.'
                          ) from err
    if not all(math.isfinite(x) for x in out):
        raise ConfigError(f'{name} must be finite numbers; got {show_value(v)}.')
    return out


def _choice(name: str, v: Any, choices: Sequence[str]) -> str:
    if not isinstance(v, str) or v not in choices:
        raise ConfigError(f'{name} must be one of {", ".join(choices)}; got {show_value(v)}.')
    return v


def _opt_count(name: str, v: Any) -> int | None:
    if v is None:
        return None
    if not _is_int(v) or v < 1:
        raise ConfigError(f'{name} must be a positive integer or null; got {show_value(v)}.')
    return int(v)


def _number(v: Any) -> float:
    """``float(v)``; ``TypeError`` for ``true``/``false``, which YAML would make 1 and 0."""
    if isinstance(v, (bool, np.bool_)):
        raise TypeError('a boolean is not a number')
    return float(v)


#: Bounds of the time settings: a day of seconds, a million periods (beyond, the nanosecond
#: arithmetic of the grid overflows; no recording needs them).
_MAX_SECONDS = 86_400.0
_MAX_PERIODS = 1e6


def _opt_pos(name: str, v: Any) -> float | None:
    if v is None:
        return None
    try:
        x = _number(v)
    except (TypeError, ValueError) as err:
        raise ConfigError(f'{name} must be a positive number of seconds; got {show_value(v)}.'
                          ) from err
    if not 0 < x <= _MAX_SECONDS:
        raise ConfigError(f'{name} must be a positive number of seconds, at most '
                          f'{_MAX_SECONDS:g}; got {show_value(v)}.')
    return x


def _nonneg(name: str, v: Any) -> float:
    try:
        x = _number(v)
    except (TypeError, ValueError) as err:
        raise ConfigError(f'{name} must be a number >= 0; got {show_value(v)}.') from err
    if not 0 <= x <= _MAX_PERIODS:
        raise ConfigError(f'{name} must be a number >= 0, at most {_MAX_PERIODS:g}; got '
                          f'{show_value(v)}.')
    return x


def _min_samples(v: Any) -> int:
    if not _is_int(v) or int(v) < 2:
        raise ConfigError(f'time.min_samples must be an integer >= 2; got {show_value(v)}.')
    return int(v)


def per_input(name: str, values: Sequence[Any], m: int) -> list[Any]:
    """``values`` for ``m`` inputs: one value for all, or one per input."""
    vals = list(values)
    if len(vals) == 1:
        return vals * m
    if len(vals) != m:
        raise ConfigError(f'{name} has {len(vals)} values for {m} inputs; give one or {m}.')
    return vals


def load_mapping(path: str | Path | None) -> BagMapping:
    """Read a mapping YAML file (``None``: the defaults).

    Raises
    ------
    ConfigError
        The file does not exist, is not UTF-8 YAML text, or a key is invalid; the message
        names the file and the key (``mapping m.yaml: output.points must be ...``).
    """
    if path is None:
        return BagMapping()
    import yaml
    p = Path(path)
    if not p.exists():
        raise ConfigError(f'mapping file {p} does not exist.')
    try:
        data = yaml.safe_load(p.read_text(encoding='utf-8'))
    except UnicodeDecodeError as err:
        raise ConfigError(f'mapping file {p} is not UTF-8 text (byte {err.start}); give a YAML '
                          'file like config/bag_mapping.yaml.') from err
    except yaml.YAMLError as err:
        raise ConfigError(f'mapping file {p} is not valid YAML: {err}') from err
    if data is not None and not isinstance(data, Mapping):
        raise ConfigError(f'mapping file {p} must hold a mapping (inputs/output/state/time); '
                          f'got {show_value(data)}.')
    try:
        return BagMapping.from_dict(data)
    except ConfigError as err:
        raise ConfigError(f'mapping {p}: {err}') from err
