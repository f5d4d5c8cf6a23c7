"""Streaming conversion of one bag onto a uniform time grid.

Two steps per bag:

1. :func:`~soft_rom.convert.probe.probe_bag` decides sizes, stamp offsets and periods from
   the first messages of every topic (:mod:`soft_rom.convert.probe`).
2. :class:`BagConverter` streams the bag once in log order. Messages that disagree with the
   probe (another size, NaN/Inf, a stamp more than :data:`STAMP_OFFSET_LIMIT_NS` from its
   log time, a stamp not after the previous one) are dropped and reported. Outputs are
   paired with states within 0.45 output periods. Every sample goes through the resampler:
   grid points ``t0_ns + j * dt_ns`` between two consecutive samples are interpolated
   linearly (output and state) when the samples are at most ``(1 + max_gap)`` output periods
   apart, otherwise the episode is split there. Inputs, kept in memory (a few floats per
   message), are zero-order held at each grid point when an episode ends. State columns go
   to the sink as they are produced, so at most ``min_samples`` of them are held.

All times are integer nanoseconds here; an episode leaves with ``t = j * dt`` seconds and
its integer start ``t0_ns``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
import logging
import re
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from soft_rom.bags.reader import BagMessage, BagReader
from soft_rom.convert.clocks import TopicClocks
from soft_rom.convert.hold import InputTrack, LOST_FACTOR
from soft_rom.convert.mapping import BagMapping, per_input
from soft_rom.convert.probe import (
    BagPlan,
    layout_ok,
    message_time,
    probe_bag,
)
from soft_rom.convert.report import ConversionReport, TopicReport
from soft_rom.data import all_finite
from soft_rom.errors import BagError, ConfigError
from soft_rom.layout import OutputLayout

__all__ = ['BagConverter', 'BagPlan', 'EpisodeSink', 'SegmentSink', 'input_names',
           'probe_bag']

Array = NDArray[np.float64]

LOG = logging.getLogger(__name__)



class SegmentSink(Protocol):
    """Receives one episode: state columns while streaming, signals at the end."""

    def append_state(self, q: Array) -> None:
        """One state column ``(n,)``; the caller does not modify it afterwards."""

    def finish(self, t: Array, U: Array, Y: Array, metadata: dict[str, Any]) -> None:
        """The episode's times (s from its start), inputs and outputs."""


class EpisodeSink(Protocol):
    """Where the episodes of a conversion go (a training set, or memory)."""

    def begin(self, name: str, n_states: int | None, t0_ns: int) -> SegmentSink:
        """Start episode ``name``."""


@dataclass
class _Segment:
    """One episode being assembled on the grid."""

    t0_ns: int
    k: int = 0
    Y: list[Array] = field(default_factory=list)
    pending: list[Array] = field(default_factory=list)
    sink: SegmentSink | None = None
    name: str = ''


class BagConverter:
    """Streams one probed bag into episodes on a uniform grid of ``dt_ns``.

    Parameters
    ----------
    plan : BagPlan
        From :func:`probe_bag`.
    mapping : BagMapping
    dt_ns : int
        Grid step (ns).
    sink : EpisodeSink
        Receives the episodes.
    names_taken : set of str
        Episode names already used (shared between the bags of one training set).
    progress : bool
        Show a tqdm bar.
    """

    def __init__(self, plan: BagPlan, mapping: BagMapping, dt_ns: int, sink: EpisodeSink,
                 names_taken: set[str], progress: bool = False) -> None:
        self.plan = plan
        self.mapping = mapping
        self.dt_ns = int(dt_ns)
        self.sink = sink
        self.names_taken = names_taken
        self.progress = progress
        self.report = ConversionReport(str(plan.path), plan.storage, plan.t_ref_ns,
                                       self.dt_ns * 1e-9)
        ref = plan.t_ref_ns
        self.tracks: dict[str, InputTrack] = {}
        for tp in plan.inputs:
            src = next(s for s in plan.sources if s.topic == tp.topic)
            rep = TopicReport(tp.topic, 'input', tp.msgtype, ref)
            self.report.topics[tp.topic] = rep
            self.tracks[tp.topic] = InputTrack(src, rep, int(tp.size or 0), tp.offset_ns)
        out = plan.output
        self.out_plan = out
        self.out_rep = TopicReport(out.topic, 'output', out.msgtype, ref)
        self.report.topics[out.topic] = self.out_rep
        self.state_plan = plan.state
        self.state_rep: TopicReport | None = None
        if self.state_plan is not None:
            self.state_rep = TopicReport(self.state_plan.topic, 'state',
                                         self.state_plan.msgtype, ref)
            self.report.topics[self.state_plan.topic] = self.state_rep
        period = out.period_ns or self.dt_ns
        self.period_ns = int(period)
        tol = mapping.match_tolerance
        self.tol_ns = int(round(tol * 1e9)) if tol is not None else int(0.45 * period)
        self.limit_ns = int(round(mapping.split_gap * 1e9)) if mapping.split_gap is not None \
            else int((1.0 + mapping.max_gap) * period)
        self.lost_ns = int(LOST_FACTOR * period)
        self.n_points = out.size
        m = mapping.output
        self.columns = ['xyz'.index(c) for c in m.components]
        self.need_points = None if m.points is None else max(m.points) + 1
        self.outs: deque[tuple[int, Array]] = deque()
        self.states: deque[tuple[int, Array]] = deque()
        self.clocks = TopicClocks(str(plan.path))
        self.out_used: list[int] = []
        self.state_used: list[int] = []
        self.seg: _Segment | None = None
        self.prev: tuple[int, Array, Array | None] | None = None
        self.next_ns = 0
        self.base = (re.sub(r'[^A-Za-z0-9_.-]+', '_', plan.path.name.split('.')[0])
                     .lstrip('.') or 'episode')
        self.pieces = 0

    # -- stream -----------------------------------------------------------------------
    def run(self) -> ConversionReport:
        """Convert the bag; returns its report (raises when nothing usable is left)."""
        from tqdm import tqdm

        wanted = list(self.plan.topics)
        total = sum(p.count for p in self.plan.topics.values())
        state_topic = None if self.state_plan is None else self.state_plan.topic
        with BagReader(self.plan.path, storage=self.plan.storage) as bag, \
                tqdm(total=total, unit='msg', desc=self.plan.path.name, leave=False,
                     disable=not self.progress, mininterval=0.5) as bar:
            for msg in bag.messages(wanted):
                bar.update(1)
                if msg.topic in self.tracks:
                    self._on_input(msg)
                elif msg.topic == self.out_plan.topic:
                    item = self._on_output(msg)
                    if item is not None:
                        self.outs.append(item)
                        self._pair()
                elif msg.topic == state_topic:
                    q = self._on_state(msg)
                    if q is not None:
                        self.states.append(q)
                        self._pair()
        self._pair(final=True)
        self._finish_segment()
        self.out_rep.timing(np.asarray(self.out_used, dtype=np.int64))
        if self.state_rep is not None:
            self.state_rep.timing(np.asarray(self.state_used, dtype=np.int64))
        for tr in self.tracks.values():
            tr.report.timing(np.asarray(tr.times, dtype=np.int64))
        if not self.report.episodes:
            cause = self.report.main_cause()
            hint = ''
            if self.out_rep.dropped and all(k.startswith('piece shorter')
                                            for k in self.out_rep.dropped):
                hint = (f'; gaps split it into {self.out_rep.splits + 1} pieces, each shorter '
                        f'than {self.mapping.min_samples} samples of the '
                        f'{self.dt_ns * 1e-9:g} s grid (a larger --max-gap or --split-gap '
                        'keeps them whole)' if self.out_rep.splits else
                        f'; the {self.dt_ns * 1e-9:g} s grid step is longer than the recording')
            LOG.debug('the whole report of %s:\n%s', self.plan.path, self.report.format())
            raise BagError(f'bag {self.plan.path}: no usable sample left after dropping bad or '
                           f'unmatched messages: {cause}{hint} (-vv prints the whole report)')
        return self.report

    def _on_input(self, msg: BagMessage) -> None:
        tr = self.tracks[msg.topic]
        rep = tr.report
        rep.read += 1
        t = message_time(msg, self.mapping.stamps)
        if not layout_ok(msg):
            rep.drop('array length differs from its layout', t)
            return
        v = np.asarray(msg.value, dtype=np.float64).reshape(-1)
        idx = tr.source.indices
        if idx is not None:
            if max(idx) >= v.size:
                rep.drop(f'fewer than {max(idx) + 1} values', t)
                return
            v = v[list(idx)]
        if v.size != tr.width:
            rep.drop(f'{v.size} values instead of {tr.width}', t)
            return
        if not all_finite(v):
            rep.drop('NaN/Inf', t)
            return
        if not self.clocks.ok(msg.topic, rep, t, msg.log_ns, tr.offset_ns):
            return
        tr.times.append(t)
        tr.values.append(v.copy())

    def _on_output(self, msg: BagMessage) -> tuple[int, Array] | None:
        m = self.mapping.output
        rep = self.out_rep
        rep.read += 1
        t = message_time(msg, self.mapping.stamps)
        pts = msg.value
        n = int(pts.shape[0])
        need = self.need_points if m.points is not None else self.n_points
        if need is not None and n < need:
            rep.drop(f'fewer than {need} points', t)
            return None
        if m.points is None and n != self.n_points:
            rep.drop(f'{n} points instead of {self.n_points}', t)
            return None
        sel = pts if m.points is None else pts[list(m.points)]
        sel = sel[:, self.columns]
        y = np.ascontiguousarray(sel.T if m.order == 'component_major' else sel,
                                 dtype=np.float64).reshape(-1)
        if not all_finite(y):
            rep.drop('NaN/Inf', t)
            return None
        if msg.frame_id != self.out_plan.frame_id:      # positions in another frame
            rep.drop(f'frame_id {msg.frame_id!r} instead of {self.out_plan.frame_id!r}', t)
            return None
        if not self.clocks.ok(m.topic, rep, t, msg.log_ns, self.out_plan.offset_ns):
            return None
        return t, y

    def _on_state(self, msg: BagMessage) -> tuple[int, Array] | None:
        rep, plan = self.state_rep, self.state_plan
        if rep is None or plan is None:
            return None
        rep.read += 1
        t = message_time(msg, self.mapping.stamps)
        if not layout_ok(msg):
            rep.drop('array length differs from its layout', t)
            return None
        q = np.asarray(msg.value, dtype=np.float64).reshape(-1)
        if q.size != plan.size:
            rep.drop(f'{q.size} values instead of {plan.size}', t)
            return None
        if not all_finite(q):
            rep.drop('NaN/Inf', t)
            return None
        if not self.clocks.ok(plan.topic, rep, t, msg.log_ns, plan.offset_ns):
            return None
        return t, q

    # -- pairing ----------------------------------------------------------------------
    def _pair(self, final: bool = False) -> None:
        outs, states, srep = self.outs, self.states, self.state_rep
        if srep is None:
            while outs:
                t, y = outs.popleft()
                self._sample(t, y, None)
            return
        while outs and states:
            (to, y), (ts, q) = outs[0], states[0]
            if abs(to - ts) <= self.tol_ns:
                outs.popleft()
                states.popleft()
                self._sample(to, y, q)
            elif to < ts:
                outs.popleft()
                self.out_rep.drop('no state message within 0.45 output periods', to)
            else:
                states.popleft()
                srep.drop('no output message within 0.45 output periods', ts)
        if final:
            for to, _ in outs:
                self.out_rep.drop('no state message within 0.45 output periods', to)
            for ts, _ in states:
                srep.drop('no output message within 0.45 output periods', ts)
            outs.clear()
            states.clear()

    # -- resampling onto the grid -------------------------------------------------------
    def _inputs_ready(self, t: int) -> str | None:
        for tr in self.tracks.values():
            if not tr.times or tr.times[0] > t:
                return tr.source.topic
        return None

    def _sample(self, t: int, y: Array, q: Array | None) -> None:
        late = self._inputs_ready(t)
        if late is not None:
            self.out_rep.drop(f'before the first message of {late}', t)
            if q is not None and self.state_rep is not None:
                self.state_rep.drop(f'before the first message of {late}', t)
            return
        self.out_used.append(t)
        self.out_rep.used += 1
        if q is not None and self.state_rep is not None:
            self.state_used.append(t)
            self.state_rep.used += 1
        prev = self.prev
        if prev is not None and t - prev[0] > self.limit_ns:
            self.out_rep.splits += 1
            self._finish_segment()
            prev = None
        if prev is None:
            self.seg = _Segment(t0_ns=t)
            self._emit(y, q, 'exact')
            self.next_ns = t + self.dt_ns
            self.prev = (t, y, q)
            return
        tp, yp, qp = prev
        span = t - tp
        kind = 'gap' if span > self.lost_ns else 'interp'
        while self.next_ns <= t:
            if self.next_ns == t:
                self._emit(y, q, 'exact')
            else:
                a = (self.next_ns - tp) / span
                yi = yp + a * (y - yp)
                qi = None if q is None or qp is None else qp + a * (q - qp)
                self._emit(yi, qi, kind)
            self.next_ns += self.dt_ns
        self.prev = (t, y, q)

    def _emit(self, y: Array, q: Array | None, kind: str) -> None:
        seg = self.seg
        if seg is None:
            return
        seg.Y.append(y)
        seg.k += 1
        for rep in (self.out_rep, self.state_rep if q is not None else None):
            if rep is None:
                continue
            if kind == 'exact':
                rep.grid_exact += 1
            elif kind == 'gap':
                rep.grid_gap_interpolated += 1
            else:
                rep.grid_interpolated += 1
        if q is None:
            return
        if seg.sink is not None:
            seg.sink.append_state(q)
            return
        seg.pending.append(q)
        if len(seg.pending) >= self.mapping.min_samples:
            self._open_sink(seg)

    def _open_sink(self, seg: _Segment) -> SegmentSink:
        index = self.pieces
        self.pieces += 1
        name = self.base if index == 0 else f'{self.base}_{index + 1}'
        while name in self.names_taken:
            name = f'{name}_'
        self.names_taken.add(name)
        seg.name = name
        n = None if self.state_plan is None else self.state_plan.size
        sink = self.sink.begin(name, n, seg.t0_ns)
        for q in seg.pending:
            sink.append_state(q)
        seg.pending = []
        seg.sink = sink
        return sink

    def _finish_segment(self) -> None:
        seg, self.seg, self.prev = self.seg, None, None
        if seg is None or seg.k == 0:
            return
        need = self.mapping.min_samples if self.out_rep.splits else 2
        if seg.k < need:
            self.out_rep.drop(f'piece shorter than {need} grid points'
                              + (' (between long gaps)' if self.out_rep.splits else ''),
                              seg.t0_ns, count=seg.k)
            return
        sink = seg.sink if seg.sink is not None else self._open_sink(seg)
        grid = seg.t0_ns + np.arange(seg.k, dtype=np.int64) * self.dt_ns
        U = self._held_inputs(grid)
        Y = np.stack(seg.Y, axis=1)
        t = (np.arange(seg.k, dtype=np.int64) * self.dt_ns).astype(np.float64) * 1e-9
        m = self.mapping
        meta = {
            'source_bag': str(self.plan.path.resolve()),
            'topics': {'inputs': [s.topic for s in self.plan.sources],
                       'output': m.output.topic,
                       'state': None if self.state_plan is None else self.state_plan.topic},
            't0_ns': int(seg.t0_ns), 'dt_ns': self.dt_ns,
        }
        sink.finish(t, U, Y, meta)
        self.report.episodes.append({'name': seg.name, 'n_samples': int(seg.k),
                                     't0_ns': int(seg.t0_ns), 'duration_s': float(t[-1])})
        self.report.n_samples += int(seg.k)

    def _held_inputs(self, grid: NDArray[np.int64]) -> Array:
        U = np.concatenate([tr.held(grid) for tr in self.tracks.values()], axis=0)
        mm = U.shape[0]
        scale = np.asarray(per_input('inputs.scale', self.mapping.scale, mm), dtype=np.float64)
        offset = np.asarray(per_input('inputs.offset', self.mapping.offset, mm),
                            dtype=np.float64)
        return np.asarray(scale[:, None] * U + offset[:, None], dtype=np.float64)

    # -- names ------------------------------------------------------------------------
    def input_names(self) -> tuple[list[str], list[str]]:
        """Input names and units."""
        return input_names(self.mapping, self.plan)

    def output_layout(self) -> OutputLayout:
        """Which points and components form ``y``."""
        return self.mapping.output.layout(self.n_points or 0)

    def output_names(self) -> list[str]:
        """Output names."""
        return self.output_layout().names()


def input_names(mapping: BagMapping, plan: BagPlan) -> tuple[list[str], list[str]]:
    """Input names and units of a probed bag."""
    mm = plan.n_inputs
    names = list(mapping.input_names) if mapping.input_names else [
        f'p{i + 1}' for i in range(mm)]
    units = [str(u) for u in per_input('inputs.units', mapping.input_units or ('Pa',), mm)]
    if len(names) != mm:
        raise ConfigError(f'inputs.names has {len(names)} names for {mm} inputs.')
    return names, units
