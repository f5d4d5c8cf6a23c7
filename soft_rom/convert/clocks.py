"""Each topic's stamps against its own past and its log time, while a bag is converted.

A stamp is taken when it is within :data:`STAMP_OFFSET_LIMIT_NS` of its log time (after the
topic's offset) and after the topic's previous one; a clock that jumped for good, or was
set back, stops the conversion in one line naming the topic (:class:`BagError`).
"""

from __future__ import annotations

from soft_rom.convert.probe import STAMP_OFFSET_LIMIT_NS
from soft_rom.convert.report import TopicReport
from soft_rom.errors import BagError

#: Rejected stamps in a row, agreeing among themselves, after which a clock jump is followed.
REANCHOR = 8


class TopicClocks:
    """The stamp checks of one bag's conversion, per topic (``path`` names the bag)."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.last_ns: dict[str, int] = {}
        self.last_log: dict[str, int] = {}
        self.offset_ref: dict[str, int] = {}
        self.rejected: dict[str, list[int]] = {}
        self.backwards: dict[str, list[int]] = {}      # stamps in a row before the newest
        self.before_last_ns: dict[str, int] = {}

    def ok(self, topic: str, rep: TopicReport, t: int, log_ns: int, offset_ns: int) -> bool:
        """Stamp consistent with its log time and after the previous one of the topic.

        The offset ``stamp - log`` is compared with that of the last accepted message (at
        first the probe's median), so a slow drift between the two clocks (a simulation
        slower than real time) passes and a single glitch does not; when
        :data:`REANCHOR` rejected messages in a row agree among themselves, the clock
        jumped for good and the topic follows it from the next message on.
        """
        off = t - log_ns
        ref = self.offset_ref.setdefault(topic, offset_ns)
        if abs(off - ref) > STAMP_OFFSET_LIMIT_NS:
            rep.drop('stamp more than 1 s away from its log time', t)
            run = self.rejected.setdefault(topic, [])
            run.append(off)
            if len(run) >= REANCHOR and max(run) - min(run) <= STAMP_OFFSET_LIMIT_NS:
                self._check_clock_jump(topic, t, log_ns)
                self.offset_ref[topic] = run[-1]
                self.last_ns.pop(topic, None)
                self.before_last_ns.pop(topic, None)
                run.clear()
            return False
        self.rejected.pop(topic, None)
        self.offset_ref[topic] = off
        last = self.last_ns.get(topic)
        if last is not None and t <= last:
            rep.drop('duplicated stamp' if t == last else 'stamp going backwards', t)
            if t < self.before_last_ns.get(topic, last):    # before the last two: not a
                back = self.backwards.setdefault(topic, [])  # lone stamp glitched ahead
                back.append(t)
                if len(back) >= REANCHOR:
                    self._refuse_step_back(topic, last, back, log_ns)
            return False
        self.backwards.pop(topic, None)
        if last is not None:
            self.before_last_ns[topic] = last
        self.last_ns[topic] = t
        self.last_log[topic] = log_ns
        return True

    def _check_clock_jump(self, topic: str, t: int, log_ns: int) -> None:
        """Refuse a lasting jump of the topic's own stamps (a sensor clock restarted or set).

        A jump of the log clock alone (the recorder's) leaves the stamps continuous.
        """
        last, last_log = self.last_ns.get(topic), self.last_log.get(topic)
        if last is None or last_log is None:
            return
        step, logged = t - last, log_ns - last_log
        if 0 < step <= logged + STAMP_OFFSET_LIMIT_NS:
            return
        raise BagError(
            f'{topic} in bag {self.path}: its header stamps jumped '
            f'{"back" if step <= 0 else "ahead"} by {abs(step - max(logged, 0)) * 1e-9:.6g} s '
            f'(from {last} ns to {t} ns while the log time advanced {logged * 1e-9:.6g} s; '
            'a sensor clock restarted or set?), so its later messages cannot be aligned with '
            "the other topics: time the bag by log time with 'time: {stamps: log}' in the "
            'mapping (--mapping), or cut the bag at the jump.')

    def _refuse_step_back(self, topic: str, last: int, back: list[int], log_ns: int) -> None:
        """Refuse a clock set back by less than :data:`STAMP_OFFSET_LIMIT_NS` (an NTP step).

        :data:`REANCHOR` stamps in a row before the topic's newest are not a message or two
        delivered out of order: followed once they pass it again, the topic would be shifted
        by the step for the rest of the bag.
        """
        logged = log_ns - self.last_log.get(topic, log_ns)
        raise BagError(
            f'{topic} in bag {self.path}: its header stamps stepped back by '
            f'{(last - back[0]) * 1e-9:.6g} s ({len(back)} messages in a row stamped before '
            f'{last} ns while the log time advanced {logged * 1e-9:.6g} s; a sensor clock set '
            'back?), so its later messages would be shifted by that much against the other '
            "topics: time the bag by log time with 'time: {stamps: log}' in the mapping "
            '(--mapping), or cut the bag at the step.')
