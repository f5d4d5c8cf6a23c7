"""Stamps for un-stamped messages: :class:`SequenceClock`, the sender's sequence.

Un-stamped sources (``Float64MultiArray`` pressures) carry no time; the runtime loop
(:mod:`soft_rom.predictor.loop`) gives each such message the next step of its sender's
sequence on the reception clock, so that a burst after a stall of the node still takes one
sender period per message.
"""

from __future__ import annotations

from collections import deque

__all__ = ['SequenceClock']

#: Arrivals (not queued behind the node), each 2 steps or more behind the sequence and not
#: catching up, that show a sender back from a pause.
_PAUSE_MESSAGES = 16
#: Arrivals that an estimate of the window needs (the window is widened to hold them).
_WINDOW_ARRIVALS = 64
#: Steps within which a period is taken as whole steps: fitted to the 9 start-up arrivals
#: (each off by up to a step of jitter, or a few in sim time), fitted again or estimated
#: early (the first 16 arrivals or more), and from a full window.
_START_TOL = 0.2
_EARLY_TOL = 0.1
_WINDOW_TOL = 0.02
#: Relative change of a period in ns that an estimate makes at once (a refinement, not a
#: change of rate, which needs 3 votes).
_REFINE = 0.02
#: Counts at which the period and phase of a sender of 2 steps or more are also checked
#: before the window is full (the start-up stamps follow the reception clock, and the
#: start-up period is fitted to 9 jittered arrivals, a few % off at 300 Hz).
_EARLY = (17, 25, 33, 65, 129)
#: Counts at which the start-up period is fitted again, to all the arrivals so far.
_REFIT = (17, 25)
#: Time after the node finished the previous message within which the next one was taken
#: from its queue, not sent meanwhile (at most a quarter of a step).
_QUEUED_NS = 250_000
#: Arrivals of a third of the window that its quartile is taken over (evenly spaced).
_SAMPLE = 64


def _median(values: list[float]) -> float:
    v = sorted(values)
    return (v[(len(v) - 1) // 2] + v[len(v) // 2]) / 2


class SequenceClock:
    """Stamps for un-stamped messages: the sender's sequence, not the reception times.

    A message without a stamp is placed one *sender period* after the previous one, so a
    1 kHz sender on a 1 kHz model gets exactly one step per message, however the executor
    bunches them: after a pause of the node (a GC pause, a busy CPU, ``SIGSTOP``) the
    messages sent meanwhile arrive in a burst and still take one period each.

    The period is the sender's, in whole steps ``h`` (or in ns, below). Until 8 intervals
    are seen (start-up) it is not known, and a message takes the whole steps that the
    reception clock has moved since the previous stamp, at least one, and one once a stamp
    was after its reception (a burst, or a sender faster than the model): a
    burst still takes one step per message, as does a 1 kHz sender on a 1 kHz model with up
    to a step of jitter, while a sender slower than the model is not compressed into one
    step per message (which left its whole sequence trailing the reception clock: 72 ms for
    a 100 Hz sender on a 1 kHz model).
    A message taken less than a step after the node finished taking the previous one
    (:meth:`taken`) waited in the queue while the node was busy (its first callback took
    1.6-2.0 ms under rclpy, most of it the first publish of the outputs): the reception clock
    then shows the node's delay, not the sender's period, and the message takes one step, as
    in a burst (before, a 1 kHz sender got a step more at its second array, and its whole
    sequence stayed a step late).
    Then the period is fitted to those 9 arrivals (the repeated median of the slopes between
    them: the arrivals in step decide, however far off a few are), and the 9th stamp of a
    sender of 2 steps or more is the whole step nearest that fitted sequence, not its own
    reception; the period is fitted again to the first 17 and 25 arrivals. It was the mean
    of the 8 intervals, the first and the 9th arrival's alone: in sim time either can be
    taken a few steps off its send time, and 2 steps between them made a 100 Hz sender's
    period 9.75 ms, off the model's grid, its stamps 4-11 ms early until a window's votes
    (1.45 s: the model's state 0.1-0.4 off, as in the closed-loop test's failures in CI).
    After that the period is re-estimated from the arrivals over the last
    :attr:`window_ns` of reception time (and at least 64 arrivals), as the slope of their
    lower envelope (the first quartiles of its first and last thirds: a stall or a burst
    only delays arrivals), and changed only when 3 estimates in a row agree on another value
    (a real rate change, counted in :attr:`resyncs`).

    A sender whose period is not a whole number of steps (120 Hz on a 1 kHz model: 8.33 ms)
    gets a period in ns, refined by each estimate, and its stamps leave the model's grid.
    Rounding it to whole steps drifted the stamps from the sender's by a third of a step per
    message, until they were ``resync_ns`` off and jumped back (a saw-tooth of 0 to 110 ms at
    120 Hz). A sender of 2 steps or more is also kept in phase: when the first quartile of a
    window's arrivals less their stamps is a step or more off (half a step for a period in
    ns: a start-up stamp taken from a late reception, a period in ns slightly off), the next
    stamps move by that much (in whole steps for a period in whole steps), spread so that
    they stay a step apart (counted in :attr:`resyncs`). A quartile, not the
    earliest arrival: in sim time a message can be taken before the ``/clock`` of the step
    it was sent in, a step early. Each arrival is compared with the sequence as it goes on,
    not with its own stamp (a start-up stamp taken from a reception a step early agreed with
    it, and the sequence after it stayed a step early until the 65th message).

    Beyond those phase steps, the sequence leaves the reception clock only in two cases,
    each counted in :attr:`resyncs`:

    * 16 messages trail it by 2 steps or more and do not catch up (by 2 steps; the backlog
      of a stalled node catches up by nearly a period a message): the sender paused or
      slowed, no burst is coming, and the sequence moves by the least of their lags, to
      the sender's phase after the pause. On wall time, where the node says when it is
      free (:meth:`taken`), a message taken at once after that (within a quarter step, at
      most 0.25 ms) and less than a step after the previous arrival waited in the node's
      queue: it is not counted, and ends the count only if it shows the catching up.
      After a jump that stayed (not a slow drift) the arrivals before it are no evidence
      of the rate, and are dropped. Before, a pause shorter than ``resync_ns`` left a
      1 kHz sender's sequence that far behind for ever and a 100 Hz sender's for up to
      2.5 s (its period voted wrong from the pause in the window), and a longer one took
      32 messages and a jump to one reception time;
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
        self._arrivals: deque[tuple[int, int, int]] = deque()   # (count, reception, stamp)
        self._count = 0
        self._votes = 0
        self._since = 0                                      # messages since an estimate
        self._late = False                 # beyond resync_ns behind: no estimates
        self._behind: tuple[int, int, int, int] | None = None  # (arrivals, lag, least, most)
        self._shift = 0                                      # phase step of the next stamp
        self._burst = False                # start-up: a stamp was after its reception
        self._free: int | None = None      # when the node finished the previous message
        self._joined = 0                   # first message of the sequence that goes on

    def _estimate(self, now_ns: int, stamp_ns: int) -> None:
        """Update the period from the arrivals (start-up, then the window, with votes)."""
        arr = self._arrivals
        if arr and now_ns - arr[-1][1] > self.window_ns // 4:
            arr.clear()                 # a gap (the sender paused): no evidence of its rate
        arr.append((self._count, now_ns, stamp_ns))
        while len(arr) > _WINDOW_ARRIVALS and now_ns - arr[1][1] >= self.window_ns:
            arr.popleft()
        if self._count == 9:                    # start-up: 8 intervals (_end_start_up)
            return
        self._since += 1
        if self._count in _REFIT and len(arr) >= 16 and not self._late:
            self.period = self._rounded(self._fitted_slope(), _EARLY_TOL)
        early = self.period >= 2 * self.h_ns and self._count in _EARLY and len(arr) >= 15 \
            and not self._late
        if not early and (self._count < 9 or now_ns - arr[0][1] < self.window_ns
                          or self._since < 16 or len(arr) < _WINDOW_ARRIVALS
                          or self._late):
            return
        self._since = 0
        if early and len(arr) < 24 or self._update_period(early):     # 16: the phase only
            self._keep_in_phase()

    def _update_period(self, early: bool) -> bool:
        """A window's estimate: refine a period in ns, or vote for a new one (False)."""
        estimate = self._rounded(self._envelope_slope(), _EARLY_TOL if early else _WINDOW_TOL)
        if estimate == self.period:
            self._votes = 0
        elif (estimate % self.h_ns or self.period % self.h_ns) \
                and abs(estimate - self.period) <= _REFINE * self.period:
            self.period = estimate                            # a period in ns, refined
            self._votes = 0
        elif early:
            return False
        else:
            self._votes += 1
            if self._votes >= 3:                              # a real rate change
                self.period = estimate
                self._votes = 0
                self.resyncs += 1
            return False
        return True

    def _keep_in_phase(self) -> None:
        """Move the sequence when a quarter of the window's arrivals are a step or more off.

        Each arrival is compared with the sequence as it goes on (the newest stamp less
        whole periods), not with the stamp it was given: a start-up stamp follows its own
        reception, so it agreed with it even when the sequence after it was a step off.
        """
        if self.period < 2 * self.h_ns or self._shift:
            return                      # one step a message: a phase step would drop one
        arr = self._arrivals
        c_now, _, st_now = arr[-1]
        offsets = sorted(t - st_now + (c_now - c) * self.period
                         for c, t, _ in list(arr)[::max(1, len(arr) // (4 * _SAMPLE))]
                         if c >= self._joined)
        if len(offsets) < 8:
            return
        offset = offsets[len(offsets) // 4]
        whole = self.period % self.h_ns == 0
        if abs(offset) >= (self.h_ns if whole else self.h_ns // 2):
            # whole steps for a sequence on the model's grid, which it keeps
            self._shift = round(offset / self.h_ns) * self.h_ns if whole else offset
            self.resyncs += 1
            arr.clear()

    def _fitted_slope(self) -> float:
        """The repeated median of the slopes between the arrivals (a robust line fit).

        Each arrival's median slope to the others, then the median of those: exact when
        most arrivals are in step, however far off the others are (in sim time, taken
        before the ``/clock`` of their step or after later ones).
        """
        arr = self._arrivals
        return _median([_median([(tb - ta) / (cb - ca) for cb, tb, _ in arr if cb != ca])
                        for ca, ta, _ in arr])

    def _envelope_slope(self) -> float:
        """The sender's period: the slope between the first quartiles of the window's thirds.

        The arrivals less the current period's sequence, ``t - p c``: a stall or a burst only
        delays arrivals, and the first quartile of each third is where the undelayed ones
        are (not the earliest one: in sim time a message can be taken a step early).
        """
        arr = list(self._arrivals)
        third = len(arr) // 3
        every = max(1, third // _SAMPLE)          # at most ~64 of each third: cheap at 1 kHz
        p = self.period

        def anchor(part: list[tuple[int, int, int]]) -> tuple[float, float]:
            u = sorted(t - p * c for c, t, _ in part)
            return sum(c for c, _, _ in part) / len(part), u[len(u) // 4]

        ca, ua = anchor(arr[:third:every])
        cb, ub = anchor(arr[len(arr) - third::every])
        return p + (ub - ua) / (cb - ca)

    def _rounded(self, interval: float, tol: float) -> int:
        """The period for a mean ``interval``: whole steps within ``tol`` steps, else ns."""
        steps = interval / self.h_ns
        if steps < 1.5:
            return self.h_ns                       # one step: at or faster than the model
        if abs(steps - round(steps)) <= tol:
            return round(steps) * self.h_ns
        return int(round(interval))

    def stamp(self, now_ns: int) -> int:
        """The stamp of a message received at ``now_ns``."""
        if self.reset_ns > 0 and self.last_received is not None and \
                now_ns < self.last_received - self.reset_ns:       # the clock restarted
            self._start()
            self.resyncs += 1
        self._count += 1
        previous, self.last_received = self.last_received, now_ns
        if self.last is None:
            self._estimate(now_ns, now_ns)
            self.last = now_ns
            return now_ns
        if self._count <= 9:                                  # start-up: period unknown
            self._burst = self._burst or (previous is not None and self.last > previous)
            queued = self._free is not None and now_ns - self._free < self.h_ns
            t = self.last + (1 if self._burst or queued
                             else max(1, (now_ns - self.last) // self.h_ns)) * self.h_ns
        else:
            t = self._sequence(now_ns, previous)
        self._estimate(now_ns, t)
        if self._count == 9 and len(self._arrivals) > 1:
            t = self._end_start_up(t)
        self.last = t
        return t

    def _end_start_up(self, stamp_ns: int) -> int:
        """The period fitted to the start-up arrivals, and the 9th's stamp on that sequence.

        A sender of 2 steps or more goes on from the whole step (after the 8th stamp) nearest
        the fitted sequence, the median of the arrivals moved along it to the 9th: not from
        the 9th's own reception, which may be a few steps off (the first phase check, at the
        17th array, corrected that).
        """
        self.period = self._rounded(self._fitted_slope(), _START_TOL)
        if self.period < 2 * self.h_ns or self.last is None:
            return stamp_ns
        arr = self._arrivals
        c9, now_ns, _ = arr[-1]
        on_line = _median([t + (c9 - c) * self.period for c, t, _ in arr])
        t = self.last + max(1, round((on_line - self.last) / self.h_ns)) * self.h_ns
        arr[-1] = (c9, now_ns, t)
        return t

    def taken(self, now_ns: int) -> None:
        """The node finished taking the last message at ``now_ns`` (reception clock)."""
        self._free = int(now_ns)

    def _sequence(self, now_ns: int, previous: int | None) -> int:
        assert self.last is not None
        candidate = self.last + self.period
        if self._shift:         # a phase step, spread so that stamps stay a step apart
            moved = max(self.last + self.h_ns, candidate + self._shift)
            self._shift -= moved - candidate
            candidate = moved
        lag = now_ns - candidate
        # taken at once after the node finished the previous one and less than a step after
        # the previous arrival: it waited behind the node, so its reception says nothing of
        # when it was sent (a live 1 kHz array comes a step after the previous one, also
        # when the node's work takes nearly the step and it is taken at once)
        queued = (self._free is not None and previous is not None
                  and now_ns - self._free < min(self.h_ns // 4, _QUEUED_NS)
                  and now_ns - previous < self.h_ns)
        if lag < -self.resync_ns:       # far ahead of the reception clock: never backwards;
            # the next step while that stays within the bound, else join the current step
            # (a sender faster than the model)
            t = (self.last + self.h_ns if self.last + self.h_ns <= now_ns + self.resync_ns
                 else self.last)
            self.resyncs += 1
            self._joined = self._count
            self._late = False
        elif lag > self.resync_ns:
            t = self._after_a_pause(candidate, lag, queued)
            self._late = t == candidate
        else:
            t = self._after_a_pause(candidate, lag, queued)
            self._late = False
        return t

    def _after_a_pause(self, candidate: int, lag: int, queued: bool) -> int:
        """The stamp when ``_PAUSE_MESSAGES`` arrivals in a row trail it by 2 steps or more.

        A sender that paused for less than ``resync_ns`` (a controller's GC pause) comes
        back late by the pause, and stays so: the sequence is moved by the least of their
        lags, to the sender's phase after the pause. A burst after a stall of the node
        catches up by a step or more a message, and is not moved. The same rule, beyond
        ``resync_ns``, ends a longer pause. A ``queued`` arrival (it waited behind the node)
        is not counted: a backlog taken while another process has the CPU now and then
        catches up unevenly, and its first 16 arrivals after a slice could trail without
        catching up by 2 steps.
        """
        if lag < 2 * self.h_ns:
            self._behind = None
            return candidate
        if queued:                      # no evidence of the sender's pace (a backlog) ...
            if self._behind is not None and self._behind[1] - lag >= 2 * self.h_ns:
                self._behind = None     # ... but of catching up
            return candidate
        if self._behind is None or self._behind[1] - lag >= 2 * self.h_ns:
            self._behind = (1, lag, lag, lag)                 # first late one, or catching up
            return candidate
        n, first, least, most = self._behind
        self._behind = (n + 1, first, min(least, lag), max(most, lag))
        if n + 1 < _PAUSE_MESSAGES:
            return candidate
        _, _, least, most = self._behind
        self._behind = None
        self.resyncs += 1
        self._shift = 0
        if first >= 3 * self.h_ns and most - least < 2 * self.h_ns:
            # a jump that stayed (not a drift, which crosses 2 steps slowly): the window
            # across a pause is no evidence of the rate
            self._arrivals.clear()
        return candidate + least           # the sender's phase after the pause
