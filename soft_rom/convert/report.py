"""What a conversion did, per bag and per topic.

Messages read, used, dropped (and why), grid points interpolated, inputs held, episodes
split. Stored with every episode (``metadata['conversion_report']``) and printed by
``soft-rom convert``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
import json
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ['ConversionReport', 'MAX_EXAMPLES', 'TopicReport']

#: Stamps kept per topic as examples of what was dropped.
MAX_EXAMPLES = 5


@dataclass
class TopicReport:
    """What happened to the messages of one topic.

    Attributes
    ----------
    read, used : int
        Messages read, and messages that went into a sample (inputs: held at a grid point).
    dropped : dict of str to int
        Messages (or samples) dropped, by reason.
    examples : list of str
        The first few drops, with their stamp (ns) and time from the bag's first stamp.
    grid_exact, grid_interpolated, grid_gap_interpolated : int
        Outputs and states: grid points taken from a sample at that stamp, interpolated
        between neighbouring samples, and interpolated across lost samples (a stretch
        longer than 1.5 periods without one, up to the bound ``max_gap``).
    splits : int
        Outputs: longer stretches without samples, where the episode was split.
    held_over_gap, max_hold_s : int, float
        Inputs: grid points whose value is older than 1.5 input periods (a message was
        missing), and the oldest held value (s).
    period_s, jitter_s, min_interval_s, max_interval_s : float
        Median interval, standard deviation and extremes of the used stamps.
    """

    topic: str
    role: str
    msgtype: str = ''
    t_ref_ns: int = 0
    read: int = 0
    used: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    examples: list[str] = field(default_factory=list)
    grid_exact: int = 0
    grid_interpolated: int = 0
    grid_gap_interpolated: int = 0
    splits: int = 0
    held_over_gap: int = 0
    max_hold_s: float = 0.0
    period_s: float = float('nan')
    jitter_s: float = float('nan')
    min_interval_s: float = float('nan')
    max_interval_s: float = float('nan')

    def drop(self, reason: str, t_ns: int, count: int = 1) -> None:
        """Count dropped messages (or samples) and keep the first few stamps."""
        self.dropped[reason] = self.dropped.get(reason, 0) + count
        if len(self.examples) < MAX_EXAMPLES:
            self.examples.append(f'{reason} at stamp {t_ns} ns '
                                 f'(t = {(t_ns - self.t_ref_ns) * 1e-9:.6f} s)')

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
    t_ref_ns: int = 0
    dt: float = float('nan')
    topics: dict[str, TopicReport] = field(default_factory=dict)
    episodes: list[dict[str, Any]] = field(default_factory=list)
    n_samples: int = 0
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able form (stored in episode attributes)."""
        d = asdict(self)
        return dict(json.loads(json.dumps(d, default=float)))

    def main_cause(self) -> str:
        """The largest drop of any topic, as one phrase (what an error should say first)."""
        best: tuple[int, TopicReport, str] | None = None
        for r in self.topics.values():
            for reason, n in r.dropped.items():
                if best is None or n > best[0]:
                    best = (n, r, reason)
        if best is None:
            return 'no message was dropped, but no output sample fell on the grid'
        n, r, reason = best
        return f'{r.role} {r.topic}: {n} of {r.read} dropped ({reason})'

    def summary_line(self) -> str:
        """One line: samples, episodes, grid, and only what was not plain (drops, gaps, splits).

        ``'bag ep1 (mcap): 2000 samples, 1 episode, 1 ms grid; nothing dropped, filled or
        split'``; the details are in :meth:`format`.
        """
        n_ep = len(self.episodes)
        head = (f'bag {self.bag} ({self.storage}): {self.n_samples} samples, {n_ep} '
                f'episode{"s" if n_ep != 1 else ""}, {_ms(self.dt)} grid')
        dropped = sum(sum(r.dropped.values()) for r in self.topics.values())
        read = sum(r.read for r in self.topics.values())
        notes = []
        if dropped:
            notes.append(f'dropped {dropped} of {read} messages (most: {self.main_cause()})')
        gaps = sum(r.grid_gap_interpolated for r in self.topics.values())
        if gaps:
            notes.append(f'{gaps} grid points interpolated across lost samples')
        holds = sorted((r for r in self.topics.values()
                        if r.role == 'input' and r.held_over_gap),
                       key=lambda r: (-r.held_over_gap, r.topic))
        if holds:
            held = sum(r.held_over_gap for r in holds)
            most = holds[0]
            pts = f'{held} grid point{"s" if held != 1 else ""}'
            notes.append(f'inputs held over a gap at {pts} (most: {most.topic}, '
                         f'{most.held_over_gap}, longest hold {_ms(most.max_hold_s)})'
                         if len(holds) > 1 else
                         f'input {most.topic} held over a gap at {pts} (longest '
                         f'hold {_ms(most.max_hold_s)})')
        splits = sum(r.splits for r in self.topics.values() if r.role == 'output')
        if splits:
            notes.append(f'split {splits} time{"s" if splits != 1 else ""} at long gaps')
        notes += self.notes
        return head + '; ' + ('; '.join(notes) if notes else 'nothing dropped, filled or split')

    def format(self) -> str:
        """Human-readable multi-line summary."""
        lines = [f'bag {self.bag} ({self.storage}): {self.n_samples} samples in '
                 f'{len(self.episodes)} episode(s) on a {_ms(self.dt)} grid']
        for ep in self.episodes:
            lines.append(f"  episode {ep['name']}: {ep['n_samples']} samples, "
                         f"{ep['duration_s']:.6f} s from stamp {ep['t0_ns']} ns")
        for r in self.topics.values():
            drops = ', '.join(f'{k}: {v}' for k, v in r.dropped.items()) or 'none'
            line = (f'  {r.role:6s} {r.topic} [{r.msgtype.split("/")[-1]}]: read {r.read}, '
                    f'used {r.used}, dropped {drops}')
            if math.isfinite(r.period_s):
                line += f'; period {_ms(r.period_s)}, jitter {_ms(r.jitter_s)}'
            if r.role == 'input':
                line += (f'; held over a gap at {r.held_over_gap} grid points, max hold '
                         f'{_ms(r.max_hold_s)}')
            else:
                line += (f'; grid points: {r.grid_exact} at a sample, {r.grid_interpolated} '
                         f'interpolated, {r.grid_gap_interpolated} across lost samples')
                if r.role == 'output':
                    line += f'; {r.splits} split(s)'
            lines.append(line)
            lines.extend(f'         {e}' for e in r.examples)
        lines.extend(f'  note: {n}' for n in self.notes)
        return '\n'.join(lines)


def _ms(seconds: float) -> str:
    """A duration in ms to the nanosecond the stamps have: ``'1 ms'``, ``'8.333 ms'``, ``'0 ms'``.

    Stamps are whole nanoseconds, so anything below half a nanosecond (a float rest such as
    a jitter of 4e-16 ms) is 0.
    """
    if not math.isfinite(seconds):
        return 'n/a'
    ns = round(seconds * 1e9)
    return f'{ns / 1e6:.6g} ms'
