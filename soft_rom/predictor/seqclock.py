"""Stamps for un-stamped messages: :class:`SequenceClock`, the sender's sequence.

Un-stamped sources (``Float64MultiArray`` pressures) carry no time; the runtime loop
(:mod:`soft_rom.predictor.loop`) gives each such message the next step of its sender's
sequence on the reception clock, so that a burst after a stall of the node still takes one
sender period per message.
"""

from __future__ import annotations

from collections import deque

__all__ = ['SequenceClock']

#: Messages after which a sequence trailing the reception clock must show that it catches up
#: (a burst after a stall of the node) or is moved to the reception time (the sender paused).
_CATCH_UP_MESSAGES = 32


class SequenceClock:
    """Stamps for un-stamped messages: the sender's sequence, not the reception times.

    A message without a stamp is placed one *sender period* after the previous one, so a
    1 kHz sender on a 1 kHz model gets exactly one step per message, however the executor
    bunches them: after a pause of the node (a GC pause, a busy CPU, ``SIGSTOP``) the
    messages sent meanwhile arrive in a burst and still take one period each.

    The period is the sender's, in whole steps ``h``: one step until 8 intervals are seen,
    then the mean of those 8 (start-up), then re-estimated from the arrivals over the last
    :attr:`window_ns` of reception time (so a stall shorter than half of it cannot move the
    rounded period) and changed only when 3 estimates in a row agree on another value (a
    real rate change, counted in :attr:`resyncs`).

    The sequence leaves the reception clock only in two cases, each counted in
    :attr:`resyncs`:

    * it trails the reception clock by more than ``resync_ns`` and does not catch up over
      the next 32 messages (by at least 2 periods; the backlog of a stalled node catches
      up, however slowly a loaded machine takes it): the sender paused or slowed, no burst
      is coming, and the stamps jump to the reception time;
    * it leads the reception clock by more than ``resync_ns`` (a sender faster than its
      period): the next step, or the previous stamp for a sender faster than the model
      (stamps never go backwards).

    A reception time more than ``reset_ns`` before the previous one is a restarted clock
    (``/clock`` of a bag played again): the sequence starts over there (counted in
    :attr:`resyncs`), so the stamps go back with it and the predictor sees the restart.

    Parameters
    ----------
    h_ns : int
        Step of the model in ns.
    resync_ns : int
        Largest accepted disagreement with the reception clock.
    reset_ns : int, optional
        Largest step back of the reception clock that is not a restart (``0``: never one).
    window_ns : int, optional
        Reception time over which the period is estimated (default 1 s).
    """

    def __init__(self, h_ns: int, resync_ns: int, reset_ns: int = 0,
                 window_ns: int = 1_000_000_000) -> None:
        self.h_ns = max(1, int(h_ns))
        self.resync_ns = int(resync_ns)
        self.reset_ns = int(reset_ns)
        self.window_ns = max(1, int(window_ns))
        self.last: int | None = None
        self.last_received: int | None = None
        self.period = self.h_ns
        self.resyncs = 0
        self._start()

    def _start(self) -> None:
        self.last = None
        self.period = self.h_ns
        self._arrivals: deque[tuple[int, int]] = deque()     # (count, reception time)
        self._count = 0
        self._votes = 0
        self._since = 0                                      # messages since an estimate
        self._late: tuple[int, int] | None = None            # (count, lag) while behind

    def _estimate(self, now_ns: int) -> None:
        """Update the period from the arrivals (start-up, then the window, with votes)."""
        arr = self._arrivals
        if arr and now_ns - arr[-1][1] > self.window_ns // 4:
            arr.clear()                 # a gap (the sender paused): no evidence of its rate
        arr.append((self._count, now_ns))
        while len(arr) > 2 and now_ns - arr[1][1] >= self.window_ns:
            arr.popleft()
        if self._count == 9:                                  # start-up: 8 intervals
            c0, t0 = arr[0]
            self.period = self._rounded((now_ns - t0) / (self._count - c0))
            return
        self._since += 1
        c0, t0 = arr[0]
        if self._count < 9 or now_ns - t0 < self.window_ns or self._since < 16 \
                or len(arr) < 64 or self._late is not None:
            return
        self._since = 0
        estimate = self._rounded((now_ns - t0) / (self._count - c0))
        if estimate == self.period:
            self._votes = 0
            return
        self._votes += 1
        if self._votes >= 3:                                   # a real rate change
            self.period = estimate
            self._votes = 0
            self.resyncs += 1

    def _rounded(self, interval: float) -> int:
        return max(1, round(interval / self.h_ns)) * self.h_ns

    def stamp(self, now_ns: int) -> int:
        """The stamp of a message received at ``now_ns``."""
        if self.reset_ns > 0 and self.last_received is not None and \
                now_ns < self.last_received - self.reset_ns:       # the clock restarted
            self._start()
            self.resyncs += 1
        self._count += 1
        self.last_received = now_ns
        if self.last is None:
            self._estimate(now_ns)
            self.last = now_ns
            return now_ns
        t = self._sequence(now_ns)
        self._estimate(now_ns)
        self.last = t
        return t

    def _sequence(self, now_ns: int) -> int:
        assert self.last is not None
        candidate = self.last + self.period
        lag = now_ns - candidate
        if lag < -self.resync_ns:       # far ahead of the reception clock: never backwards;
            # the next step while that stays within the bound, else join the current step
            # (a sender faster than the model)
            t = (self.last + self.h_ns if self.last + self.h_ns <= now_ns + self.resync_ns
                 else self.last)
            self.resyncs += 1
            self._late = None
        elif lag > self.resync_ns:
            t = candidate
            if self._late is None:
                self._late = (self._count, lag)
            elif self._count - self._late[0] >= _CATCH_UP_MESSAGES:
                if self._late[1] - lag >= 2 * self.period:
                    self._late = (self._count, lag)     # catching up: a burst after a stall
                else:
                    t = now_ns                           # behind and not catching up
                    self.resyncs += 1
                    self._late = None
        else:
            t = candidate
            self._late = None
        return t
