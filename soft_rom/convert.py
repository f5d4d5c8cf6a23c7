"""Bags to training sets: topic mapping, time alignment, streaming conversion, reports.

``soft-rom convert BAG... -o OUT.zarr`` (and :func:`convert`) turns ROS 2 bags (sqlite3 or
MCAP) into the chunked training set of :mod:`soft_rom.dataset`; :func:`read_episode` reads
one bag into an in-memory :class:`~soft_rom.data.Episode` (the replay tool uses it).

Mapping
-------
:class:`BagMapping` says which topics are the inputs, the output and the state. The defaults
(the bag contract of ``SPEC.md``) need no file; ``config/bag_mapping.yaml`` documents every
key. Inputs are a list of *sources*, each one ``FluidPressure`` topic (one input) or one
``Float64/Float32MultiArray`` topic with ``indices`` or ``slice`` (several inputs); every input
is mapped as ``u = scale * raw + offset`` (e.g. ``offset: -101325`` turns absolute into gauge
pressure). With ``topics: auto`` (default) the per-chamber topics
``/soft_robot/pressure/chamber_<i>`` found in the bag are used in chamber order, else
``/soft_robot/pressures``.

The output ``y`` is built from a ``PoseArray`` (or ``PoseStamped``): the selected points
(default all, 0-based ``points`` indices) and components (default ``[x, z]``), ordered
**component-major** by default, ``y = [x_1 .. x_N, z_1 .. z_N]`` with names ``x1 .. xN,
z1 .. zN`` -- so with the paper's 20 points ``y10`` is ``x10`` (mid-body) and ``y20`` is
``x20`` (tail tip); ``order: point_major`` gives ``[x_1, z_1, x_2, z_2, ...]`` instead.

The state is a ``Float64/Float32MultiArray`` (layout ``[nodes, 3]``) or a ``PointCloud2``
with ``x, y, z`` fields; ``Q`` rows are node-major, ``Q[3 i + c]`` = coordinate ``c`` of
node ``i``, stored as float64.

Time alignment
--------------
Every message is timed by its ``header.stamp``, or by the bag log time when the type has no
header (multi-arrays) or ``time.stamps: log`` is set. Samples are the output messages; with
a state topic, each output is paired with the state message whose time is within
``match_tolerance`` (default 0.45 of the output period) and unpaired ones are dropped. Inputs
are zero-order held: ``U[:, j]`` is the last input value with time ``<= t_j``. With ``dt``
the samples are resampled to a uniform grid (``Y`` and ``Q`` linearly interpolated, ``U``
held). With ``split_gap`` a bag is split into several episodes wherever consecutive samples
are further apart than that many seconds.

Streaming: the inputs and outputs of a bag (a few floats per message) are kept in memory;
state columns go to the training set as soon as they are paired with their output, so at
most one chunk column of ``Q`` (``n x 32`` values) is held.

Bad input: what stops and what continues
----------------------------------------
===================================================== =======================================
case                                                  behaviour
===================================================== =======================================
bag missing, truncated, corrupt, unreadable           **stop** (BagError, bag named)
empty bag, or no message on the output topic          **stop**
configured topic missing                              **stop** (topic named, topics listed)
wrong message type on a configured topic              **stop** (topic, found and expected type)
no usable sample left after dropping                  **stop**
NaN/Inf in a message                                  continue: message dropped (inputs keep
                                                      their held value), reported with stamp
array length differs from the topic's first message   continue: message dropped, reported
or from its layout
stamp duplicated or going backwards on a topic        continue: message dropped, reported
output with fewer points than configured              continue: message dropped, reported
output sample without a state (or state w/o output)   continue: dropped, reported
output sample before the first message of an input    continue: dropped, reported
===================================================== =======================================

Every report lists, per topic, messages read and used, dropped counts by reason with the
first stamps, gaps filled by holding (input held longer than 1.5 of its median period), and
stamp jitter. A stop never leaves a half-written training set (the writer is atomic).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
import json
import logging
import math
from pathlib import Path
import re
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.bags.reader import BagMessage, BagReader
from soft_rom.data import Episode
from soft_rom.dataset import EpisodeWriter, TrainingSet, TrainingSetWriter
from soft_rom.errors import BagError, ConfigError, DatasetError

__all__ = ['BagMapping', 'ConversionReport', 'InputSource', 'OutputMapping', 'StateMapping',
           'TopicReport', 'convert', 'load_mapping', 'read_episode']

log = logging.getLogger(__name__)

PRESSURE_TYPES = ('sensor_msgs/msg/FluidPressure',)
ARRAY_TYPES = ('std_msgs/msg/Float64MultiArray', 'std_msgs/msg/Float32MultiArray')
OUTPUT_TYPES = ('geometry_msgs/msg/PoseArray', 'geometry_msgs/msg/PoseStamped')
STATE_TYPES = ARRAY_TYPES + ('sensor_msgs/msg/PointCloud2',)
CHAMBER_RE = re.compile(r'^/soft_robot/pressure/chamber_(\d+)$')
DEFAULT_ARRAY_TOPIC = '/soft_robot/pressures'
MAX_EXAMPLES = 5


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

    def names(self, n_points: int) -> list[str]:
        """Output names for a message of ``n_points`` points."""
        pts = list(self.points) if self.points is not None else list(range(n_points))
        if self.order == 'component_major':
            return [f'{c}{i + 1}' for c in self.components for i in pts]
        return [f'{c}{i + 1}' for i in pts for c in self.components]


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
        Seconds; output/state pairing tolerance (default 0.45 output period).
    dt : float, optional
        Resample to this uniform step (s).
    split_gap : float, optional
        Split a bag where samples are further apart than this (s).
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
    split_gap: float | None = None

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
        _no_extra('time', tm, {'stamps', 'match_tolerance', 'dt', 'split_gap'})
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
        if not comps or any(c not in ('x', 'y', 'z') for c in comps):
            raise ConfigError(f'output.components must be a list of x, y, z; got {comps}.')
        order = str(out.get('order', 'component_major'))
        if order not in ('component_major', 'point_major'):
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
            split_gap=_opt_pos('time.split_gap', tm.get('split_gap')))

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (stored in the training set's provenance)."""
        return json.loads(json.dumps(asdict(self)))

    def replace(self, **changes: Any) -> BagMapping:
        """A copy with ``changes`` applied."""
        d = {f: getattr(self, f) for f in self.__dataclass_fields__}
        d.update(changes)
        return BagMapping(**d)


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
    vals = [v] if np.isscalar(v) else list(v)
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


# ---------------------------------------------------------------------------------------
# reports
# ---------------------------------------------------------------------------------------
@dataclass
class TopicReport:
    """What happened to the messages of one topic."""

    topic: str
    role: str
    msgtype: str = ''
    read: int = 0
    used: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    examples: list[str] = field(default_factory=list)
    gaps_filled: int = 0
    max_hold_s: float = 0.0
    period_s: float = float('nan')
    jitter_s: float = float('nan')
    min_interval_s: float = float('nan')
    max_interval_s: float = float('nan')

    def drop(self, reason: str, t_ns: int) -> None:
        """Count one dropped message (or sample) and keep the first few stamps."""
        self.dropped[reason] = self.dropped.get(reason, 0) + 1
        if len(self.examples) < MAX_EXAMPLES:
            self.examples.append(f'{reason} at t = {t_ns * 1e-9:.9f} s')

    def timing(self, times_ns: NDArray[np.int64]) -> None:
        """Fill period and jitter statistics from the used stamps."""
        if times_ns.size > 1:
            d = np.diff(times_ns).astype(np.float64) * 1e-9
            self.period_s = float(np.median(d))
            self.jitter_s = float(np.std(d))
            self.min_interval_s = float(d.min())
            self.max_interval_s = float(d.max())


@dataclass
class ConversionReport:
    """Report of one bag: per-topic figures and the episodes produced."""

    bag: str
    storage: str = ''
    topics: dict[str, TopicReport] = field(default_factory=dict)
    episodes: list[dict[str, Any]] = field(default_factory=list)
    n_samples: int = 0
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (stored in episode attributes)."""
        d = asdict(self)
        return json.loads(json.dumps(d, default=float))

    def format(self) -> str:
        """Human-readable multi-line summary."""
        lines = [f'bag {self.bag} ({self.storage}): {self.n_samples} samples in '
                 f'{len(self.episodes)} episode(s)']
        for ep in self.episodes:
            lines.append(f"  episode {ep['name']}: {ep['n_samples']} samples, "
                         f"t = {ep['t_start']:.6f} .. {ep['t_end']:.6f} s")
        for r in self.topics.values():
            drops = ', '.join(f'{k}: {v}' for k, v in r.dropped.items()) or 'none'
            line = (f'  {r.role:6s} {r.topic} [{r.msgtype.split("/")[-1]}]: read {r.read}, '
                    f'used {r.used}, dropped {drops}')
            if math.isfinite(r.period_s):
                line += f'; period {r.period_s * 1e3:.4g} ms, jitter {r.jitter_s * 1e3:.3g} ms'
            if r.role == 'input':
                line += f'; gaps filled {r.gaps_filled}, max hold {r.max_hold_s * 1e3:.4g} ms'
            lines.append(line)
            lines.extend(f'         {e}' for e in r.examples)
        lines.extend(f'  note: {n}' for n in self.notes)
        return '\n'.join(lines)


# ---------------------------------------------------------------------------------------
# core
# ---------------------------------------------------------------------------------------
@dataclass
class _Segment:
    """Samples of one episode being assembled."""

    t_ns: list[int] = field(default_factory=list)
    Y: list[NDArray[np.float64]] = field(default_factory=list)
    Q: list[NDArray[np.float64]] | None = None
    writer: EpisodeWriter | None = None
    name: str = ''


class _InputTrack:
    """Held-value timeline of one input source."""

    def __init__(self, source: InputSource, report: TopicReport) -> None:
        self.source = source
        self.report = report
        self.times: list[int] = []
        self.values: list[NDArray[np.float64]] = []
        self.width: int | None = None
        self.last_ns: int | None = None


def _resolve_inputs(mapping: BagMapping, topics: Mapping[str, tuple[str, int]]
                    ) -> tuple[InputSource, ...]:
    if mapping.inputs is not None:
        return mapping.inputs
    chambers = sorted((int(m.group(1)), t) for t in topics
                      if (m := CHAMBER_RE.match(t)) is not None)
    if chambers:
        return tuple(InputSource(t) for _, t in chambers)
    if DEFAULT_ARRAY_TOPIC in topics:
        return (InputSource(DEFAULT_ARRAY_TOPIC),)
    raise BagError('no pressure topics found: expected /soft_robot/pressure/chamber_<i> '
                   f'(FluidPressure) or {DEFAULT_ARRAY_TOPIC} (Float64MultiArray); the bag has '
                   f'{sorted(topics)}. Give the input topics in a mapping file (--mapping).')


def _check_topic(topics: Mapping[str, tuple[str, int]], topic: str, role: str,
                 allowed: Sequence[str], path: Path) -> str:
    if topic not in topics:
        raise BagError(f'{role} topic {topic} is missing from bag {path}; it has '
                       f'{sorted(topics)}. Fix the topic names in the mapping (--mapping).')
    msgtype = topics[topic][0]
    if msgtype not in allowed:
        raise BagError(f'{role} topic {topic} in bag {path} carries {msgtype}; expected one of '
                       f'{list(allowed)}.')
    return msgtype


class _BagConverter:
    """Streams one bag into one or more episodes (in memory or into a training set)."""

    def __init__(self, path: Path, mapping: BagMapping, *, include_state: bool | None,
                 storage: str, progress: bool) -> None:
        self.path = path
        self.mapping = mapping
        self.include_state = include_state
        self.storage = storage
        self.progress = progress
        self.report = ConversionReport(str(path))

    # -- message validation -------------------------------------------------------------
    def _time(self, msg: BagMessage) -> int:
        if self.mapping.stamps == 'log' or msg.stamp_ns is None:
            return msg.log_ns
        return msg.stamp_ns

    def _array_size(self, msg: BagMessage, rep: TopicReport, t: int) -> bool:
        if msg.layout:
            want = int(np.prod([s for _, s in msg.layout]))
            if want and want != msg.value.size:
                rep.drop('array length differs from its layout', t)
                return False
        return True

    def run(self, sink: Any, names_taken: set[str]) -> list[Episode]:
        """Convert; with ``sink`` the episodes go to the training set, else into memory."""
        m = self.mapping
        with BagReader(self.path, storage=self.storage) as bag:
            self.report.storage = bag.storage
            topics = bag.topics
            if bag.message_count == 0:
                raise BagError(f'bag {self.path} is empty (no messages).')
            sources = _resolve_inputs(m, topics)
            for s in sources:
                _check_topic(topics, s.topic, 'input', PRESSURE_TYPES + ARRAY_TYPES, self.path)
            out_type = _check_topic(topics, m.output.topic, 'output', OUTPUT_TYPES, self.path)
            if topics[m.output.topic][1] == 0:
                raise BagError(f'output topic {m.output.topic} has no messages in bag '
                               f'{self.path}.')
            include = self.include_state
            if include is None:
                include = m.state.include
            if include is None:
                include = m.state.topic in topics
            state_type = None
            if include:
                state_type = _check_topic(topics, m.state.topic, 'state', STATE_TYPES,
                                          self.path)
            self.sources = sources
            self.include = bool(include)
            self.tracks = {}
            for s in sources:
                rep = TopicReport(s.topic, 'input', topics[s.topic][0])
                self.report.topics[s.topic] = rep
                self.tracks[s.topic] = _InputTrack(s, rep)
            self.out_rep = TopicReport(m.output.topic, 'output', out_type)
            self.report.topics[m.output.topic] = self.out_rep
            self.state_rep = None
            if self.include:
                self.state_rep = TopicReport(m.state.topic, 'state', state_type or '')
                self.report.topics[m.state.topic] = self.state_rep
            n_out = topics[m.output.topic][1]
            span = (bag.end_ns - bag.start_ns) * 1e-9
            period = span / (n_out - 1) if n_out > 1 and span > 0 else 1e-3
            self.tol_ns = int(round(1e9 * (m.match_tolerance if m.match_tolerance is not None
                                           else 0.45 * period)))
            wanted = [s.topic for s in sources] + [m.output.topic]
            if self.include:
                wanted.append(m.state.topic)
            total = sum(topics[t][1] for t in set(wanted))
            return self._stream(bag, list(dict.fromkeys(wanted)), total, sink, names_taken)

    def _stream(self, bag: BagReader, wanted: list[str], total: int,
                sink: Any, names_taken: set[str]) -> list[Episode]:
        from tqdm import tqdm

        m = self.mapping
        outs: deque[tuple[int, NDArray[np.float64]]] = deque()
        states: deque[tuple[int, NDArray[np.float64]]] = deque()
        self.out_last: int | None = None
        self.state_last: int | None = None
        self.out_points: int | None = m.output.n_points
        self.state_size: int | None = None
        self.sink = sink
        self.names_taken = names_taken
        self.segments: list[_Segment] = []
        self.done: list[Episode] = []
        self.seg: _Segment | None = None
        self.prev: tuple[int, NDArray[np.float64], NDArray[np.float64] | None] | None = None
        self.grid_next: int | None = None
        self.out_times: list[int] = []
        self.state_times: list[int] = []
        bar = tqdm(total=total, unit='msg', desc=self.path.name, disable=not self.progress,
                   leave=False, mininterval=0.5)
        try:
            for msg in bag.messages(wanted):
                bar.update(1)
                if msg.topic in self.tracks:
                    self._on_input(msg)
                if msg.topic == m.output.topic:
                    item = self._on_output(msg)
                    if item is not None:
                        outs.append(item)
                        self._pair(outs, states)
                if self.include and msg.topic == m.state.topic:
                    item = self._on_state(msg)
                    if item is not None:
                        states.append(item)
                        self._pair(outs, states)
        finally:
            bar.close()
        self._pair(outs, states, final=True)
        self._finish_segment()
        self.out_rep.timing(np.asarray(self.out_times, dtype=np.int64))
        if self.state_rep is not None:
            self.state_rep.timing(np.asarray(self.state_times, dtype=np.int64))
        if not self.report.episodes:
            raise BagError(f'bag {self.path}: no usable sample left after dropping bad or '
                           f'unmatched messages:\n{self.report.format()}')
        return self.done

    # -- per-topic handlers -------------------------------------------------------------
    def _on_input(self, msg: BagMessage) -> None:
        tr = self.tracks[msg.topic]
        rep = tr.report
        rep.read += 1
        t = self._time(msg)
        v = np.asarray(msg.value, dtype=np.float64).reshape(-1)
        if not self._array_size(msg, rep, t):
            return
        if tr.source.indices is not None:
            if max(tr.source.indices) >= v.size:
                rep.drop(f'fewer than {max(tr.source.indices) + 1} values', t)
                return
            v = v[list(tr.source.indices)]
        if tr.width is None:
            tr.width = v.size
        elif v.size != tr.width:
            rep.drop('array length differs from the first message', t)
            return
        if not np.all(np.isfinite(v)):
            rep.drop('NaN/Inf', t)
            return
        if tr.last_ns is not None and t <= tr.last_ns:
            rep.drop('duplicated stamp' if t == tr.last_ns else 'stamp going backwards', t)
            return
        tr.last_ns = t
        tr.times.append(t)
        tr.values.append(v.copy())

    def _on_output(self, msg: BagMessage) -> tuple[int, NDArray[np.float64]] | None:
        m = self.mapping.output
        rep = self.out_rep
        rep.read += 1
        t = self._time(msg)
        pts = msg.value
        n = pts.shape[0]
        need = self.out_points
        if m.points is not None:
            need = max(need or 0, max(m.points) + 1)
        if need is not None and n < need:
            rep.drop(f'fewer than {need} points', t)
            return None
        if self.out_points is None:
            self.out_points = n
        elif n != self.out_points and m.points is None:
            rep.drop(f'{n} points instead of {self.out_points}', t)
            return None
        sel = pts if m.points is None else pts[list(m.points)]
        cols = ['xyz'.index(c) for c in m.components]
        y = sel[:, cols].T.reshape(-1) if m.order == 'component_major' else \
            sel[:, cols].reshape(-1)
        if not np.all(np.isfinite(y)):
            rep.drop('NaN/Inf', t)
            return None
        if self.out_last is not None and t <= self.out_last:
            rep.drop('duplicated stamp' if t == self.out_last else 'stamp going backwards', t)
            return None
        self.out_last = t
        return t, y

    def _on_state(self, msg: BagMessage) -> tuple[int, NDArray[np.float64]] | None:
        rep = self.state_rep
        if rep is None:
            return None
        rep.read += 1
        t = self._time(msg)
        q = msg.value.reshape(-1)
        if not self._array_size(msg, rep, t):
            return None
        if self.state_size is None:
            self.state_size = q.size
        elif q.size != self.state_size:
            rep.drop(f'{q.size} values instead of {self.state_size}', t)
            return None
        if not _all_finite(q):
            rep.drop('NaN/Inf', t)
            return None
        if self.state_last is not None and t <= self.state_last:
            rep.drop('duplicated stamp' if t == self.state_last else 'stamp going backwards', t)
            return None
        self.state_last = t
        return t, q

    # -- pairing, segments, resampling --------------------------------------------------
    def _pair(self, outs: deque[Any], states: deque[Any], final: bool = False) -> None:
        if not self.include:
            while outs:
                t, y = outs.popleft()
                self._sample(t, y, None)
            return
        srep = self.state_rep
        if srep is None:
            return
        while outs and states:
            (to, y), (ts, q) = outs[0], states[0]
            if abs(to - ts) <= self.tol_ns:
                outs.popleft()
                states.popleft()
                self._sample(to, y, q)
            elif to < ts:
                outs.popleft()
                self.out_rep.drop('no state message at this stamp', to)
            else:
                states.popleft()
                srep.drop('no output message at this stamp', ts)
        if final:
            for to, _ in outs:
                self.out_rep.drop('no state message at this stamp', to)
            for ts, _ in states:
                srep.drop('no output message at this stamp', ts)
            outs.clear()
            states.clear()

    def _inputs_ready(self, t: int) -> bool:
        return all(tr.times and tr.times[0] <= t for tr in self.tracks.values())

    def _sample(self, t: int, y: NDArray[np.float64], q: NDArray[np.float64] | None) -> None:
        if not self._inputs_ready(t):
            late = [tr.source.topic for tr in self.tracks.values()
                    if not tr.times or tr.times[0] > t]
            self.out_rep.drop(f'before the first message of {late[0]}', t)
            if q is not None and self.state_rep is not None:
                self.state_rep.drop(f'before the first message of {late[0]}', t)
            return
        gap = self.mapping.split_gap
        if self.seg is not None and gap is not None and self.seg.t_ns and \
                (t - self.seg.t_ns[-1]) * 1e-9 > gap:
            self._finish_segment()
        if self.seg is None:
            self._start_segment(q)
        self.out_rep.used += 1
        self.out_times.append(t)
        if q is not None and self.state_rep is not None:
            self.state_rep.used += 1
            self.state_times.append(t)
        dt = self.mapping.dt
        if dt is None:
            self._emit(t, y, q)
            return
        step = int(round(dt * 1e9))
        if self.prev is None:
            self._emit(t, y, q)
            self.grid_next = t + step
        else:
            t0, y0, q0 = self.prev
            while self.grid_next is not None and self.grid_next <= t:
                a = (self.grid_next - t0) / (t - t0)
                yi = y0 + a * (y - y0)
                qi = None if q is None or q0 is None else q0 + a * (q - q0)
                self._emit(self.grid_next, yi, qi)
                self.grid_next += step
        self.prev = (t, y, q)

    def _emit(self, t: int, y: NDArray[np.float64], q: NDArray[np.float64] | None) -> None:
        seg = self.seg
        if seg is None:
            return
        seg.t_ns.append(t)
        seg.Y.append(np.array(y, dtype=np.float64))
        if q is not None:
            if seg.writer is not None:
                seg.writer.append_states(q.reshape(-1, 1), check_finite=False, copy=False)
            elif seg.Q is not None:
                seg.Q.append(np.array(q, dtype=np.float64))

    def _start_segment(self, q: NDArray[np.float64] | None) -> None:
        base = re.sub(r'[^A-Za-z0-9_.-]+', '_', self.path.name.split('.')[0]) or 'episode'
        base = base.lstrip('.') or 'episode'
        index = len(self.report.episodes) + len(self.segments)
        name = base if index == 0 else f'{base}_{index + 1}'
        while name in self.names_taken:
            name = f'{name}_'
        self.names_taken.add(name)
        seg = _Segment(name=name)
        if q is not None:
            if self.sink is not None:
                seg.writer = self.sink.begin_episode(name, n_states=q.size)
            else:
                seg.Q = []
        elif self.sink is not None:
            seg.writer = self.sink.begin_episode(name)
        self.seg = seg
        self.prev = None
        self.grid_next = None

    def _held_inputs(self, t_ns: NDArray[np.int64]) -> NDArray[np.float64]:
        blocks = []
        for tr in self.tracks.values():
            times = np.asarray(tr.times, dtype=np.int64)
            vals = np.asarray(tr.values, dtype=np.float64)          # (count, width)
            idx = np.searchsorted(times, t_ns, side='right') - 1   # last stamp <= t
            if np.any(idx < 0):  # cannot happen: samples wait for the first input
                raise BagError(f'{tr.source.topic}: no input value before t = '
                               f'{t_ns[np.argmax(idx < 0)] * 1e-9:.9f} s.')
            blocks.append(vals[idx].T)
            rep = tr.report
            rep.used = int(np.unique(idx).size) + rep.used
            rep.timing(times)
            age = (t_ns - times[idx]) * 1e-9
            if age.size:
                rep.max_hold_s = max(rep.max_hold_s, float(age.max()))
            if math.isfinite(rep.period_s) and age.size:
                # a sample lies in a gap when the held message is followed by a longer
                # interval than 1.5 input periods (a message missing or dropped) and the
                # sample is after the held message's stamp
                limit = 1.5 * rep.period_s
                has_next = idx < times.size - 1
                interval = np.where(has_next, (times[np.minimum(idx + 1, times.size - 1)]
                                               - times[idx]) * 1e-9, np.inf)
                in_gap = (age > 0) & np.where(has_next, interval > limit, age > limit)
                rep.gaps_filled += int(np.sum(in_gap))
        U = np.concatenate(blocks, axis=0)
        m = self.mapping
        mm = U.shape[0]
        scale = np.asarray(_per_input('inputs.scale', m.scale, mm))
        offset = np.asarray(_per_input('inputs.offset', m.offset, mm))
        return scale[:, None] * U + offset[:, None]

    def _finish_segment(self) -> None:
        seg, self.seg = self.seg, None
        if seg is None or not seg.t_ns:
            return
        t_ns = np.asarray(seg.t_ns, dtype=np.int64)
        U = self._held_inputs(t_ns)
        Y = np.stack(seg.Y, axis=1)
        t = t_ns * 1e-9
        meta = {
            'source_bag': str(self.path.resolve()),
            'topics': {'inputs': [s.topic for s in self.sources],
                       'output': self.mapping.output.topic,
                       'state': self.mapping.state.topic if self.include else None},
            't_start': float(t[0]), 't_end': float(t[-1]),
        }
        self.report.episodes.append({'name': seg.name, 'n_samples': int(t.size),
                                     't_start': float(t[0]), 't_end': float(t[-1])})
        self.report.n_samples += int(t.size)
        if seg.writer is not None and self.sink is not None:
            names, units = self.input_names()
            self.sink.check_names(names, units, self.output_names(), self.path)
            seg.writer.metadata.update(meta)
            seg.writer.append_signals(t, U, Y)
            return
        Q = None if seg.Q is None else np.stack(seg.Q, axis=1)
        self.done.append(Episode(t=t, U=U, Y=Y, Q=Q, name=seg.name, metadata=meta))

    # -- names --------------------------------------------------------------------------
    def input_names(self) -> tuple[list[str], list[str]]:
        """Input names and units after the bag was read."""
        m = self.mapping
        widths = [tr.width or 0 for tr in self.tracks.values()]
        mm = int(sum(widths))
        names = list(m.input_names) if m.input_names else [f'p{i + 1}' for i in range(mm)]
        units = list(_per_input('inputs.units', m.input_units or ('Pa',), mm))
        if len(names) != mm:
            raise ConfigError(f'inputs.names has {len(names)} names for {mm} inputs.')
        return names, [str(u) for u in units]

    def output_names(self) -> list[str]:
        """Output names after the bag was read."""
        return self.mapping.output.names(self.out_points or 0)


def _all_finite(v: NDArray[Any]) -> bool:
    """True if every value is finite; one pass without a temporary in the common case."""
    with np.errstate(all='ignore'):
        total = np.add.reduce(v, axis=None)
    return bool(np.isfinite(total)) or bool(np.all(np.isfinite(v)))


def _per_input(name: str, values: Sequence[Any], m: int) -> list[Any]:
    vals = list(values)
    if len(vals) == 1:
        return vals * m
    if len(vals) != m:
        raise ConfigError(f'{name} has {len(vals)} values for {m} inputs; give one or {m}.')
    return vals


def _paths(bags: Iterable[str | Path]) -> list[Path]:
    out = [Path(b) for b in bags]
    if not out:
        raise BagError('no bag given.')
    for p in out:
        if not p.exists():
            raise FileNotFoundError(f'bag {p} does not exist.')
    return out


def read_episode(bag_path: str | Path, mapping: BagMapping | None = None, *,
                 include_state: bool = False, storage: str = 'auto',
                 progress: bool = False) -> tuple[Episode, ConversionReport]:
    """Read one bag into an in-memory :class:`~soft_rom.data.Episode`.

    ``mapping.split_gap`` is ignored (one bag, one episode). ``Q`` is held in memory, so
    ``include_state=True`` is for small models only; use :func:`convert` for large ones.

    Returns
    -------
    episode : Episode
        ``metadata`` holds source bag, topics, names and units, and the report.
    report : ConversionReport
    """
    m = (mapping or BagMapping()).replace(split_gap=None)
    conv = _BagConverter(_paths([bag_path])[0], m, include_state=include_state,
                         storage=storage, progress=progress)
    episodes = conv.run(None, set())
    ep = episodes[0]
    in_names, in_units = conv.input_names()
    meta = dict(ep.metadata)
    meta.update({'input_names': in_names, 'input_units': in_units,
                 'output_names': conv.output_names(),
                 'output_units': [m.output.units] * ep.Y.shape[0],
                 'conversion_report': conv.report.to_dict()})
    return Episode(t=ep.t, U=ep.U, Y=ep.Y, Q=ep.Q, name=ep.name, metadata=meta), conv.report


def convert(bags: Sequence[str | Path], out: str | Path, mapping: BagMapping | None = None, *,
            storage: str = 'auto', include_state: bool | None = None,
            overwrite: bool = False, progress: bool = True,
            echo: Any = None) -> tuple[TrainingSet, list[ConversionReport]]:
    """Convert bags (one episode each, or several with ``split_gap``) to a training set.

    Parameters
    ----------
    bags : sequence of path
        rosbag2 directories (or ``.mcap`` / ``.db3`` files), in episode order.
    out : path
        Training set to write (``*.zarr``); written atomically.
    mapping : BagMapping, optional
        Topic mapping and time options (defaults: the bag contract).
    storage : {'auto', 'mcap', 'sqlite3'}
        Require a storage format, or accept either.
    include_state : bool, optional
        Store ``Q``; default: when the bags have the state topic.
    overwrite : bool
        Replace ``out`` if it exists.
    progress : bool
        Show tqdm progress bars.
    echo : callable, optional
        Called with each bag's formatted report (the CLI prints them).

    Returns
    -------
    training_set : TrainingSet
    reports : list of ConversionReport
    """
    m = mapping or BagMapping()
    paths = _paths(bags)
    reports: list[ConversionReport] = []
    names_taken: set[str] = set()
    out = Path(out)
    writer: TrainingSetWriter | None = None
    in_names: list[str] = []
    try:
        for path in paths:
            conv = _BagConverter(path, m, include_state=include_state, storage=storage,
                                 progress=progress)
            if writer is None:
                writer = _LazyWriter(out, overwrite, m, paths)  # type: ignore[assignment]
            conv.run(writer, names_taken)
            names, units = conv.input_names()
            outs = conv.output_names()
            writer.check_names(names, units, outs, path)  # type: ignore[union-attr]
            in_names = names
            for ep in conv.report.episodes:
                writer.episode_metadata(ep['name'], conv.report.to_dict())  # type: ignore
            reports.append(conv.report)
            if echo is not None:
                echo(conv.report.format())
        if writer is None or not in_names:
            raise BagError('nothing converted.')
        writer.finish()  # type: ignore[union-attr]
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    return TrainingSet.open(out), reports


class _LazyWriter:
    """A :class:`TrainingSetWriter` created when the first episode begins.

    Names and units are known only once the first samples are read; the writer is created
    then, with names provisionally taken from the mapping and checked after each bag.
    """

    def __init__(self, out: Path, overwrite: bool, mapping: BagMapping,
                 paths: Sequence[Path]) -> None:
        if out.exists() and not overwrite:
            raise DatasetError(f'{out} exists already; pass --overwrite to replace it.')
        self.out = out
        self.overwrite = overwrite
        self.mapping = mapping
        self.paths = paths
        self.w: TrainingSetWriter | None = None
        self.meta: dict[str, dict[str, Any]] = {}
        self.eps: dict[str, EpisodeWriter] = {}
        self.names: tuple[list[str], list[str], list[str]] | None = None
        self.pending: list[tuple[str, int | None]] = []

    def begin_episode(self, name: str, n_states: int | None = None) -> EpisodeWriter:
        if self.w is None:
            self.w = _DeferredNames(self.out, self.overwrite, self.mapping, self.paths)
            self.w.open()
        ep = self.w.begin_episode(name, n_states=n_states)
        self.eps[name] = ep
        return ep

    def check_names(self, names: list[str], units: list[str], outs: list[str],
                    path: Path) -> None:
        if self.w is None:
            return
        got = (names, units, outs)
        if self.names is None:
            self.names = got
            self.w.set_names(names, units, outs, [self.mapping.output.units] * len(outs))
        elif got != self.names:
            raise BagError(f'bag {path} gives inputs {names} / outputs {len(outs)} that differ '
                           f'from the first bag ({self.names[0]} / {len(self.names[2])}).')

    def episode_metadata(self, name: str, report: dict[str, Any]) -> None:
        ep = self.eps.get(name)
        if ep is not None:
            ep.metadata['conversion_report'] = report

    def finish(self) -> None:
        if self.w is None:
            raise BagError('no episode was produced.')
        self.w.close()

    def abort(self) -> None:
        if self.w is not None:
            self.w.abort()


class _DeferredNames(TrainingSetWriter):
    """A training-set writer whose names are set after the first bag was read."""

    def __init__(self, out: Path, overwrite: bool, mapping: BagMapping,
                 paths: Sequence[Path]) -> None:
        # Placeholder names satisfy the constructor; replaced by set_names before data.
        super().__init__(out, input_names=['_'], input_units=['_'], output_names=['_'],
                         output_units=['_'], overwrite=overwrite, attrs={'provenance': {
                             'bags': [str(p.resolve()) for p in paths],
                             'mapping': mapping.to_dict(), 'tool': 'soft-rom convert'}})
        self._named = False

    def set_names(self, input_names: list[str], input_units: list[str],
                  output_names: list[str], output_units: list[str]) -> None:
        self.input_names, self.input_units = input_names, input_units
        self.output_names, self.output_units = output_names, output_units
        self._named = True
