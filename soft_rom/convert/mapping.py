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

from soft_rom.errors import ConfigError
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
        """Build from the YAML structure of ``config/bag_mapping.yaml``."""
        d = dict(d or {})
        unknown = set(d) - {'inputs', 'output', 'state', 'time'}
        if unknown:
            raise ConfigError(f'unknown mapping section(s) {sorted(unknown)}; expected inputs, '
                              'output, state, time.')
        inp = dict(d.get('inputs') or {})
        out = dict(d.get('output') or {})
        st = dict(d.get('state') or {})
        tm = dict(d.get('time') or {})
        _no_extra('inputs', inp, {'sources', 'topics', 'topic', 'indices', 'slice', 'names',
                                  'units', 'scale', 'offset'})
        _no_extra('output', out, {'topic', 'points', 'n_points', 'components', 'order',
                                  'units'})
        _no_extra('state', st, {'topic', 'include'})
        _no_extra('time', tm, {'stamps', 'match_tolerance', 'dt', 'max_gap', 'split_gap',
                               'min_samples'})
        sources: list[InputSource] | None
        if 'sources' in inp:
            sources = [_source(s) for s in inp['sources'] or []]
        elif 'topic' in inp:
            sources = [_source({k: inp[k] for k in ('topic', 'indices', 'slice') if k in inp})]
        elif inp.get('topics', 'auto') in ('auto', None):
            sources = None
        elif isinstance(inp['topics'], list):
            sources = [InputSource(str(t)) for t in inp['topics']]
        else:
            raise ConfigError(f"inputs.topics must be 'auto' or a list; got {inp['topics']!r}.")
        if sources is not None and not sources:
            raise ConfigError('inputs: at least one input source is needed.')
        names = inp.get('names')
        units = inp.get('units', 'Pa')
        comps = tuple(str(c) for c in out.get('components', ('x', 'z')))
        if not comps or any(c not in COMPONENTS for c in comps) or len(set(comps)) < len(comps):
            raise ConfigError(f'output.components must be a list of distinct x, y, z; got '
                              f'{comps}.')
        order = str(out.get('order', 'component_major'))
        if order not in ORDERS:
            raise ConfigError(f"output.order must be 'component_major' or 'point_major'; "
                              f'got {order!r}.')
        stamps = str(tm.get('stamps', 'header'))
        if stamps not in ('header', 'log'):
            raise ConfigError(f"time.stamps must be 'header' or 'log'; got {stamps!r}.")
        points = out.get('points')
        return cls(
            inputs=None if sources is None else tuple(sources),
            input_names=None if names is None else tuple(str(n) for n in names),
            input_units=None if units is None else (
                (str(units),) if isinstance(units, str) else tuple(str(u) for u in units)),
            scale=_floats('inputs.scale', inp.get('scale', 1.0)),
            offset=_floats('inputs.offset', inp.get('offset', 0.0)),
            output=OutputMapping(
                topic=str(out.get('topic', OutputMapping.topic)),
                points=None if points is None else tuple(int(i) for i in points),
                n_points=None if out.get('n_points') is None else int(out['n_points']),
                components=comps, order=order, units=str(out.get('units', 'm'))),
            state=StateMapping(topic=str(st.get('topic', StateMapping.topic)),
                               include=None if st.get('include') is None else bool(
                                   st['include'])),
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


def _no_extra(section: str, d: Mapping[str, Any], allowed: set[str]) -> None:
    extra = set(d) - allowed
    if extra:
        raise ConfigError(f'unknown key(s) {sorted(extra)} in mapping section {section!r}; '
                          f'allowed: {sorted(allowed)}.')


def _source(s: Any) -> InputSource:
    if isinstance(s, str):
        return InputSource(s)
    if not isinstance(s, Mapping) or 'topic' not in s:
        raise ConfigError(f'an input source needs a topic; got {s!r}.')
    idx = s.get('indices')
    if s.get('slice') is not None:
        sl = list(s['slice'])
        if len(sl) != 2:
            raise ConfigError(f"inputs slice must be [start, stop]; got {s['slice']!r}.")
        idx = list(range(int(sl[0]), int(sl[1])))
    return InputSource(str(s['topic']), None if idx is None else tuple(int(i) for i in idx))


def _floats(name: str, v: Any) -> tuple[float, ...]:
    vals: list[Any] = [v] if np.isscalar(v) else list(v)
    try:
        out = tuple(float(x) for x in vals)
    except (TypeError, ValueError) as err:
        raise ConfigError(f'{name} must be a number or a list of numbers; got {v!r}.') from err
    if not out or not all(math.isfinite(x) for x in out):
        raise ConfigError(f'{name} must be finite numbers; got {v!r}.')
    return out


def _opt_pos(name: str, v: Any) -> float | None:
    if v is None:
        return None
    try:
        x = float(v)
    except (TypeError, ValueError) as err:
        raise ConfigError(f'{name} must be a positive number of seconds; got {v!r}.') from err
    if not x > 0 or not math.isfinite(x):
        raise ConfigError(f'{name} must be a positive number of seconds; got {v!r}.')
    return x


def _nonneg(name: str, v: Any) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError) as err:
        raise ConfigError(f'{name} must be a number >= 0; got {v!r}.') from err
    if not x >= 0 or not math.isfinite(x):
        raise ConfigError(f'{name} must be a number >= 0; got {v!r}.')
    return x


def _min_samples(v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or int(v) < 2:
        raise ConfigError(f'time.min_samples must be an integer >= 2; got {v!r}.')
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
    """Read a mapping YAML file (``None``: the defaults)."""
    if path is None:
        return BagMapping()
    import yaml
    p = Path(path)
    if not p.exists():
        raise ConfigError(f'mapping file {p} does not exist.')
    try:
        data = yaml.safe_load(p.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f'mapping file {p} is not valid YAML: {err}') from err
    if data is not None and not isinstance(data, Mapping):
        raise ConfigError(f'mapping file {p} must hold a mapping (inputs/output/state/time).')
    return BagMapping.from_dict(data)


