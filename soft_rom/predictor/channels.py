"""Per-input figures of the predictor (for diagnostics): counts, newest stamps, timeouts."""

from __future__ import annotations

__all__ = ['ChannelStats', 'NO_STAMP']

#: Newest stamp of an input that has not sent a value yet.
NO_STAMP = -(2 ** 63)


class ChannelStats:
    """Counts and stamps per input channel (plain lists: cheap to update at 1 kHz).

    Attributes
    ----------
    names : list of str
    newest : list of int
        Newest accepted stamp per input (ns; :data:`NO_STAMP` before the first).
    received, late, dropped, clipped, out_of_envelope : list of int
    timed_out : list of bool
        Whether the input currently stops holding the model back (silent too long).
    measured : int
        Accepted measurements; ``measured_newest`` their newest stamp (ns or None).
    """

    def __init__(self, names: list[str]) -> None:
        self.names = list(names)
        m = len(self.names)
        self.newest = [NO_STAMP] * m
        self.received = [0] * m
        self.late = [0] * m
        self.dropped = [0] * m
        self.clipped = [0] * m
        self.out_of_envelope = [0] * m
        self.timed_out = [False] * m
        self.measured = 0
        self.measured_newest: int | None = None

    def received_one(self, index: int | None, stamp_ns: int) -> None:
        """One accepted value on ``index`` (``None``: every input, an array message)."""
        if index is None:
            for i in range(len(self.newest)):
                self.received[i] += 1
                if stamp_ns > self.newest[i]:
                    self.newest[i] = stamp_ns
        else:
            self.received[index] += 1
            if stamp_ns > self.newest[index]:
                self.newest[index] = stamp_ns

    def late_one(self, index: int | None) -> None:
        """One value applied late on ``index`` (``None``: every input)."""
        for i in (range(len(self.late)) if index is None else (index,)):
            self.late[i] += 1

    def measured_one(self, stamp_ns: int) -> None:
        """One accepted measurement."""
        self.measured += 1
        if self.measured_newest is None or stamp_ns > self.measured_newest:
            self.measured_newest = stamp_ns

    def newest_max(self) -> int:
        """Newest stamp over all inputs."""
        return max(self.newest) if self.newest else NO_STAMP

    def forget_stamps(self) -> None:
        """After a reset: stamps start over (counts are kept)."""
        self.newest = [NO_STAMP] * len(self.newest)
        self.timed_out = [False] * len(self.newest)
        self.measured_newest = None

    def take_over(self, old: ChannelStats) -> None:
        """Keep the counts of the same inputs across a reload."""
        if len(old.names) == len(self.names):
            for name in ('newest', 'received', 'late', 'dropped', 'clipped', 'out_of_envelope',
                         'timed_out'):
                setattr(self, name, list(getattr(old, name)))
            self.measured, self.measured_newest = old.measured, old.measured_newest
