"""The probe: the first messages of a bag decide sizes, stamp offsets and the output period.

:func:`probe_bag` reads the bag from its start, once, until it has the first
:data:`PROBE_MESSAGES` messages of every mapped topic (:data:`PROBE_STATE_MESSAGES` of the
state), and decides from the majority of them (never from the first message alone) the input
widths, the number of centerline points and the state size; the median offset of each
topic's stamps from its log times; and each topic's period (a line through the stamps, so
jitter averages out and lost frames count). A topic whose stamps mostly go backwards (or do
not move) is refused.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from soft_rom.bags.reader import BagMessage, BagReader
from soft_rom.convert.mapping import (
    ARRAY_TYPES,
    BagMapping,
    CHAMBER_RE,
    DEFAULT_ARRAY_TOPIC,
    InputSource,
    OUTPUT_TYPES,
    PRESSURE_TYPES,
    STATE_TYPES,
)
from soft_rom.errors import BagError

__all__ = ['BagPlan', 'clocks_apart', 'PROBE_MESSAGES', 'PROBE_STATE_MESSAGES',
           'STAMP_OFFSET_LIMIT_NS',
           'TopicPlan', 'layout_ok', 'message_time', 'probe_bag']

#: Messages per topic read by the probe (state topics: fewer, they are large).
PROBE_MESSAGES = 256
PROBE_STATE_MESSAGES = 32
#: A stamp further than this from its log time (after the topic's offset) is dropped.
STAMP_OFFSET_LIMIT_NS = 1_000_000_000


@dataclass
class TopicPlan:
    """What the probe found on one topic."""

    topic: str
    role: str
    msgtype: str
    count: int
    size: int | None = None
    offset_ns: int = 0
    period_ns: int | None = None
    first_ns: int | None = None
    first_log_ns: int | None = None
    frame_id: str | None = None


@dataclass
class BagPlan:
    """The probe's decisions for one bag (see the module docstring)."""

    path: Path
    storage: str
    sources: tuple[InputSource, ...]
    include_state: bool
    topics: dict[str, TopicPlan] = field(default_factory=dict)
    log_start_ns: int = 0
    log_end_ns: int = 0

    @property
    def output(self) -> TopicPlan:
        """The output topic's plan."""
        return next(p for p in self.topics.values() if p.role == 'output')

    @property
    def state(self) -> TopicPlan | None:
        """The state topic's plan, if states are converted."""
        return next((p for p in self.topics.values() if p.role == 'state'), None)

    @property
    def inputs(self) -> list[TopicPlan]:
        """The input topics' plans, in input order."""
        return [self.topics[s.topic] for s in self.sources]

    @property
    def n_inputs(self) -> int:
        """Number of inputs ``m``."""
        return int(sum(p.size or 0 for p in self.inputs))

    @property
    def first_log_ns(self) -> int:
        """The earliest log time the probe saw (ns)."""
        firsts = [p.first_log_ns for p in self.topics.values() if p.first_log_ns is not None]
        return min(firsts) if firsts else self.log_start_ns

    @property
    def t_ref_ns(self) -> int:
        """The earliest stamp the probe saw (reference of the report's relative times)."""
        firsts = [p.first_ns for p in self.topics.values() if p.first_ns is not None]
        return min(firsts) if firsts else 0

    def min_period(self) -> tuple[str, int] | None:
        """``(topic, median period ns)`` of the fastest topic."""
        per = [(p.topic, p.period_ns) for p in self.topics.values() if p.period_ns]
        return min(per, key=lambda x: x[1]) if per else None


def message_time(msg: BagMessage, stamps: str) -> int:
    return msg.log_ns if stamps == 'log' or msg.stamp_ns is None else msg.stamp_ns


def layout_ok(msg: BagMessage) -> bool:
    if msg.layout:
        want = int(np.prod([s for _, s in msg.layout]))
        return not want or want == msg.value.size
    return True


def _size(role: str, msg: BagMessage, source: InputSource | None) -> int:
    """The size the probe votes on: values (inputs, states) or points (outputs)."""
    if role == 'output':
        return int(msg.value.shape[0])
    n = int(msg.value.size)
    if role == 'input' and source is not None and source.indices is not None:
        return len(source.indices) if n > max(source.indices) else 0
    return n


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


def probe_bag(path: Path, mapping: BagMapping, *, include_state: bool | None,
              storage: str) -> BagPlan:
    """Open ``path``, check its topics and decide sizes, stamp offsets and the output period."""
    with BagReader(path, storage=storage) as bag:
        topics = bag.topics
        if not topics:
            raise BagError(f'bag {path} is empty (no topics, no messages).')
        sources = _resolve_inputs(mapping, topics)
        for s in sources:
            _check_topic(topics, s.topic, 'input', PRESSURE_TYPES + ARRAY_TYPES, path)
        out = mapping.output
        out_type = _check_topic(topics, out.topic, 'output', OUTPUT_TYPES, path)
        include = include_state
        if include is None:
            include = mapping.state.include
        if include is None:
            include = mapping.state.topic in topics
        plan = BagPlan(path, bag.storage, sources, bool(include),
                       log_start_ns=bag.start_ns, log_end_ns=bag.end_ns)
        roles: list[tuple[str, str, str, InputSource | None]] = [
            (s.topic, 'input', topics[s.topic][0], s) for s in sources]
        roles.append((out.topic, 'output', out_type, None))
        if include:
            st = _check_topic(topics, mapping.state.topic, 'state', STATE_TYPES, path)
            roles.append((mapping.state.topic, 'state', st, None))
        plan.topics = _probe(bag, roles, mapping, topics)
    if plan.output.first_ns is None:
        if not any(p.first_ns is not None for p in plan.topics.values()):
            raise BagError(f'bag {path} is empty (no messages on the mapped topics).')
        raise BagError(f'output topic {out.topic} has no messages in bag {path}.')
    for tp in plan.inputs:
        if tp.first_ns is None:
            raise BagError(f'input topic {tp.topic} has no messages in bag {path} (it is '
                           f'listed with {tp.count} messages); record it again, or give the '
                           'input topics in a mapping file (inputs.topics, --mapping).')
    return plan


def _probe(bag: BagReader, roles: list[tuple[str, str, str, InputSource | None]],
           mapping: BagMapping, topics: Mapping[str, tuple[str, int]]) -> dict[str, TopicPlan]:
    """One pass from the start until every topic has its quota of messages."""
    seen: dict[str, list[BagMessage]] = {t: [] for t, *_ in roles}
    quota = {t: max(1, min(PROBE_STATE_MESSAGES if role == 'state' else PROBE_MESSAGES,
                           topics[t][1] or PROBE_MESSAGES)) for t, role, *_ in roles}
    # the counts are the storage files' (BagReader.topics), not metadata.yaml's
    short = set(seen)
    for msg in bag.messages(list(seen)):
        got = seen[msg.topic]
        if len(got) < quota[msg.topic]:
            got.append(msg)
            if len(got) == quota[msg.topic]:
                short.discard(msg.topic)
                if not short:
                    break
    return {t: _probe_topic(bag, t, role, msgtype, source, mapping, topics[t][1], seen[t])
            for t, role, msgtype, source in roles}


def _probe_topic(bag: BagReader, topic: str, role: str, msgtype: str,
                 source: InputSource | None, mapping: BagMapping, count: int,
                 messages: list[BagMessage]) -> TopicPlan:
    plan = TopicPlan(topic, role, msgtype, count)
    sizes: Counter[int] = Counter()
    frames: Counter[str | None] = Counter()
    times: list[int] = []
    offsets: list[int] = []
    last: BagMessage | None = None
    for msg in messages:
        t = message_time(msg, mapping.stamps)
        if last is not None and t == message_time(last, mapping.stamps) and np.array_equal(
                msg.value, last.value):
            continue    # the same message recorded twice: dropped when streaming, no clock
        last = msg
        if plan.first_log_ns is None:
            plan.first_log_ns = msg.log_ns
        times.append(t)
        offsets.append(t - msg.log_ns)
        frames[msg.frame_id] += 1
        if layout_ok(msg):
            sizes[_size(role, msg, source)] += 1
    if not times:
        return plan
    plan.first_ns = min(times)
    d = np.diff(np.asarray(times, dtype=np.int64))
    if d.size >= 2 and np.mean(d <= 0) > 0.5:
        how = 'go backwards' if np.mean(d < 0) > 0.5 else 'do not advance'
        by_log = mapping.stamps == 'log' or last is None or last.stamp_ns is None
        fix = ("the recording's clock is broken; re-record it, or time it by header stamps "
               "with 'time: {stamps: header}' in the mapping (--mapping) if its messages "
               'carry them.') if by_log else (
            "time this bag by its log time with 'time: {stamps: log}' in the mapping "
            '(--mapping).')
        raise BagError(f'{topic} in bag {bag.path}: the '
                       f'{"log times" if by_log else "header stamps"} {how} in '
                       f'{np.mean(d <= 0):.0%} of its first {len(times)} messages, so they '
                       f'cannot time the samples; {fix}')
    plan.offset_ns = int(np.median(offsets))
    plan.frame_id = frames.most_common(1)[0][0]
    if role == 'output' and mapping.output.n_points is not None:
        plan.size = int(mapping.output.n_points)
    elif role == 'input' and source is not None and source.indices is not None:
        plan.size = len(source.indices)
    elif role == 'input' and msgtype in PRESSURE_TYPES:
        plan.size = 1
    else:
        good = [(n, c) for n, c in sizes.most_common() if n > 0]
        plan.size = good[0][0] if good else None
    ok = np.abs(np.asarray(offsets) - plan.offset_ns) <= STAMP_OFFSET_LIMIT_NS
    plan.period_ns = _period(np.asarray(times, dtype=np.int64)[ok])
    return plan


def clocks_apart(plan: BagPlan) -> str | None:
    """A note when a topic's stamps are over 1 s from the output's, both against log time.

    Samples are aligned by their stamps; a camera or sensor machine whose clock is off by
    seconds (not synchronised) gives inputs that many seconds off the outputs, which nothing
    else in the conversion shows (only inputs held at one end).
    """
    out = next((t for t in plan.topics.values() if t.role == 'output'), None)
    if out is None:
        return None
    far = max((t for t in plan.topics.values() if t.role != 'output'), default=None,
              key=lambda t: abs(t.offset_ns - out.offset_ns))
    if far is None or abs(far.offset_ns - out.offset_ns) <= STAMP_OFFSET_LIMIT_NS:
        return None
    return (f'the stamps of {out.topic} are {(out.offset_ns - far.offset_ns) * 1e-9:+.6g} s from '
            f"those of {far.topic} (each against its log time); samples are aligned by stamp, "
            'so if these clocks were not synchronised the inputs are that far off the outputs: '
            "synchronise them, or time the bag by log time ('time: {stamps: log}')")


def _period(tt: NDArray[np.int64]) -> int | None:
    """Median period of stamps ``tt``, refined by a line through them (jitter averages out).

    Each stamp gets its frame number from the median interval (so lost frames count), and
    the period is the slope of the least-squares line of stamp against frame number.
    """
    tt = np.sort(np.unique(tt))
    d = np.diff(tt)
    if not d.size:
        return None
    med = float(np.median(d))
    frame = np.round((tt - tt[0]) / med)
    if frame[-1] < 2 or np.unique(frame).size < 3:
        return int(round(med))
    rel = (tt - tt[0]).astype(np.float64)
    slope = np.polyfit(frame, rel, 1)[0]
    return int(round(slope)) if 0.5 * med < slope < 1.5 * med else int(round(med))
