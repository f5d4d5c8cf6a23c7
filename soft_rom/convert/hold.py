"""The inputs of a bag conversion, zero-order held at the grid points of an episode.

Inputs are kept in memory while a bag streams (a few floats per message, one
:class:`InputTrack` per input source); when an episode ends, every grid point takes the last
value stamped at or before it, and the topic's report counts the messages used, the longest
hold and the grid points held over a gap (a missing or dropped message).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from soft_rom.convert.mapping import InputSource
from soft_rom.convert.report import TopicReport
from soft_rom.errors import BagError

__all__ = ['InputTrack', 'LOST_FACTOR']

Array = NDArray[np.float64]

#: Interval (in periods) above which samples are counted as lost between two others.
LOST_FACTOR = 1.5


@dataclass
class InputTrack:
    """Held-value timeline of one input source."""

    source: InputSource
    report: TopicReport
    width: int
    offset_ns: int
    times: list[int] = field(default_factory=list)
    values: list[Array] = field(default_factory=list)

    def held(self, grid: NDArray[np.int64]) -> Array:
        """The values held at the ``grid`` stamps, ``(width, len(grid))``; updates the report."""
        times = np.asarray(self.times, dtype=np.int64)
        vals = np.asarray(self.values, dtype=np.float64)          # (count, width)
        idx = np.searchsorted(times, grid, side='right') - 1     # last stamp <= t
        if np.any(idx < 0):  # cannot happen: a piece starts after every first input
            raise BagError(f'{self.source.topic}: no input value before grid stamp '
                           f'{int(grid[np.argmax(idx < 0)])} ns.')
        rep = self.report
        rep.used += int(np.unique(idx).size)
        age = (grid - times[idx]) * 1e-9
        rep.max_hold_s = max(rep.max_hold_s, float(age.max()))
        if times.size > 1:
            # held over a gap: the held message is followed by an interval longer than
            # 1.5 input periods (a message missing or dropped), and the grid point is
            # after the held message's stamp
            limit = LOST_FACTOR * float(np.median(np.diff(times))) * 1e-9
            has_next = idx < times.size - 1
            nxt = times[np.minimum(idx + 1, times.size - 1)]
            interval = np.where(has_next, (nxt - times[idx]) * 1e-9, np.inf)
            in_gap = (age > 0) & np.where(has_next, interval > limit, age > limit)
            rep.held_over_gap += int(np.sum(in_gap))
        return vals[idx].T
