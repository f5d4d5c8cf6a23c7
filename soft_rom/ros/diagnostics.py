"""``/diagnostics`` of the predictor node: the prediction, and each input topic.

Status names are stable (``<node name>: <task>``, the convention of diagnostic_updater):

* ``<node>: prediction`` - the core's health (OK / WARN / ERROR / STALE with the reason)
  and its figures (windowed errors, counters, model time, ``callback_errors``);
* ``<node>: input <topic>`` - one per chamber topic (or the array topic): ``rate_hz``
  (messages per second since the previous report), ``stamp_age_s`` (node clock minus the
  newest header stamp, as diagnostic_updater's TimeStampStatus), ``age_s`` (since the last
  message was received), ``stamp_lag_s`` (behind the newest stamp of all inputs),
  ``received`` (taken), ``late``, ``dropped``, ``clipped``, ``timed_out``; STALE when nothing
  was taken yet, nothing for ``input_timeout_s`` or the input timed out, WARN when some were
  dropped or clipped since the previous report (also when none was taken), when the
  newest stamp is more than 10 s from the node's clock (another clock), when messages stamped
  more than 10 s ahead of it were dropped since the previous report (``ahead``: counted, not
  used, so that they do not carry the model's time), or when the topic has more than one
  publisher (``publishers``);
* ``<node>: measured <topic>`` - ``rate_hz``, ``stamp_age_s``, ``received`` (arrived),
  ``dropped`` of the measured centerline; STALE (it is optional: not an error) when none
  arrives within ``input_timeout_s``, WARN when some were dropped since the last report or
  when its ``frame_id`` (if set) is not the node's ``frame_id`` (no transform is applied).

Every status carries the same ``hardware_id`` (parameter ``hardware_id``, default the
node's fully qualified name), as diagnostic_updater's FrequencyStatus / TimeStampStatus do.
The figures come from the ROS-free :meth:`soft_rom.predictor.loop.RuntimeLoop.diagnostics`;
this module only arranges them into statuses.
"""

from __future__ import annotations

import math
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

# CLOCK_APART_S: an input whose newest stamp is further than this from the node's clock (s)
# is on another clock (a future stamp, wall time against sim time): WARN on its topic; one
# stamped that far ahead is dropped by the loop (it would carry the model's event time along)
from soft_rom.predictor.loop import CLOCK_APART_S

__all__ = ['Diagnostics', 'publisher_counts', 'sender_warning', 'TopicMonitor']

_NO_STAMP = -(2 ** 63)



class TopicMonitor:
    """Counts the messages of one topic and keeps the newest stamp (int ns)."""

    __slots__ = ('topic', 'kind', 'count', 'last_stamp_ns', 'frame', 'expected_frame', '_t0',
                 '_n0')

    def __init__(self, topic: str, kind: str, expected_frame: str = '') -> None:
        self.topic = topic
        self.kind = kind
        self.expected_frame = expected_frame
        self.frame = ''         # the newest message's frame_id when not the expected one
        self.count = 0
        self.last_stamp_ns = _NO_STAMP
        self._t0 = _NO_STAMP
        self._n0 = 0

    def seen(self, stamp_ns: int) -> None:
        """One message stamped ``stamp_ns`` arrived (the hot path: two assignments)."""
        self.count += 1
        self.last_stamp_ns = stamp_ns

    def rate(self, now_ns: int) -> float:
        """Messages per second since the previous call (NaN on the first)."""
        t0, n0 = self._t0, self._n0
        self._t0, self._n0 = now_ns, self.count
        if t0 == _NO_STAMP or now_ns <= t0:
            return math.nan
        return (self.count - n0) / ((now_ns - t0) * 1e-9)


def publisher_counts(node: Any, topics: list[str]) -> list[int]:
    """Publishers on each of ``topics`` as ``node``'s graph sees them (its own included)."""
    return [node.count_publishers(t) for t in topics]


def sender_warning(count: int, own: int = 0, where: str = 'this topic') -> str:
    """Why ``count`` publishers on a topic are too many; ``''`` when they are not.

    ``own``: how many of them are the node's own. On a topic the node reads (``own`` 0) a
    second publisher is a second sender; on one it writes (its commands: ``own`` 1) any
    other publisher is a second commander, fighting it.
    """
    if own:
        others = count - own
        return (f'{others} other publisher(s) on {where}, which this node commands (a second '
                'commander fighting it?)') if others > 0 else ''
    return f'{count} publishers on {where} (a second sender?)' if count > 1 else ''


def _ahead_s(values: dict[str, str], names: list[str]) -> float:
    """How far ahead the newest arrival was stamped if dropped so (s; nan if none was)."""
    got = []
    for n in names:
        try:
            got.append(float(values.get(f'input.{n}.ahead_s', 'nan')))
        except ValueError:
            pass
    return max((g for g in got if math.isfinite(g)), default=math.nan)


def _level(level: int) -> bytes:
    return bytes([int(level)])


class Diagnostics:
    """Builds the node's ``DiagnosticArray`` (one status for the core, one per topic).

    Parameters
    ----------
    node_name : str
    hardware_id : str
    input_topics : list of str
        The topics of the model's inputs, in input order (one array topic: one entry).
    """

    def __init__(self, node_name: str, hardware_id: str, input_topics: list[str]) -> None:
        self.node_name = node_name
        self.hardware_id = hardware_id
        self.input_topics = input_topics
        self._dropped: dict[str, int] = {}

    def _status(self, task: str) -> DiagnosticStatus:
        return DiagnosticStatus(name=f'{self.node_name}: {task}', hardware_id=self.hardware_id)

    def _input_statuses(self, values: dict[str, str], names: list[str],
                        stamp_ages: list[float], timeout: float,
                        publishers: list[int] | None = None) -> list[DiagnosticStatus]:
        out = []
        per_topic = len(names) == len(self.input_topics)
        keys = ('rate_hz', 'age_s', 'stamp_lag_s', 'received', 'late', 'dropped', 'clipped',
                'timed_out', 'ahead')
        for i, topic in enumerate(self.input_topics):
            mine = names if not per_topic else [names[i]]
            st = self._status(f'input {topic}')
            fig = {k: values.get(f'input.{mine[0]}.{k}', 'nan') for k in keys}
            stamp_age = stamp_ages[i] if per_topic else min(stamp_ages, default=math.inf)
            try:
                silent = float(fig['age_s']) > timeout
            except ValueError:
                silent = False
            received = int(fig['received']) if fig['received'].isdigit() else 0
            # a whole array dropped counts on each of its channels: the topic's count is
            # the largest of its channels', not their sum
            bad = max((sum(int(values.get(f'input.{n}.{k}', '0') or 0)
                           for k in ('dropped', 'clipped')) for n in mine), default=0)
            new_bad = bad - self._dropped.get(topic, 0)
            self._dropped[topic] = bad
            dropped = (f'; {new_bad} dropped or clipped since the last report (see the '
                       'prediction status)' if new_bad > 0 else '')
            ahead = max((int(values.get(f'input.{n}.ahead', '0') or 0) for n in mine),
                        default=0)
            new_ahead = ahead - self._dropped.get(f'{topic} ahead', 0)
            self._dropped[f'{topic} ahead'] = ahead
            ahead_s = _ahead_s(values, mine)    # finite: the newest arrival was so ahead
            if new_ahead > 0 or math.isfinite(ahead_s):     # the cause of all else here
                st.level = DiagnosticStatus.WARN
                st.message = ((f'stamped {ahead_s:.3g} s' if math.isfinite(ahead_s) else
                               f'{new_ahead} stamped more than {CLOCK_APART_S:g} s')
                              + " ahead of this node's clock (another clock? use_sim_time?): "
                              f'dropped, {ahead} so far')
            elif received == 0:
                st.level, st.message = ((DiagnosticStatus.WARN, f'none taken{dropped}')
                                        if bad else (DiagnosticStatus.STALE, 'no messages yet'))
            elif fig['timed_out'] == 'true' or silent:
                st.level = DiagnosticStatus.STALE
                st.message = (f'nothing taken for {fig["age_s"]} s' if silent else
                              f'timed out: {fig["stamp_lag_s"]} s behind the other inputs'
                              ) + dropped
            elif new_bad > 0:
                st.level = DiagnosticStatus.WARN
                st.message = f'{new_bad} dropped or clipped since the last report'
            else:
                st.level, st.message = DiagnosticStatus.OK, f'{fig["rate_hz"]} Hz'
            if received and math.isfinite(stamp_age) and abs(stamp_age) > CLOCK_APART_S \
                    and st.level == DiagnosticStatus.OK:
                st.level = DiagnosticStatus.WARN
                st.message = (f'stamped {abs(stamp_age):.3g} s '
                              f'{"ahead of" if stamp_age < 0 else "behind"} this node\'s clock '
                              '(another clock? use_sim_time?)')
            senders = publishers[i] if publishers else 0
            if (second := sender_warning(senders)) and st.level == DiagnosticStatus.OK:
                st.level = DiagnosticStatus.WARN
                st.message = second
            st.values = [KeyValue(key='rate_hz', value=fig['rate_hz']),
                         KeyValue(key='publishers', value=str(senders)),
                         KeyValue(key='stamp_age_s', value=f'{stamp_age:.6g}')] + [
                KeyValue(key=k, value=fig[k]) for k in keys[1:]]
            out.append(st)
        return out

    def _measured_status(self, monitor: TopicMonitor, now_ns: int, timeout: float,
                         dropped: int = 0) -> DiagnosticStatus:
        """The measured topic: arriving (``monitor``), and ``dropped`` by the core so far."""
        new_drops = dropped - self._dropped.get(monitor.topic, 0)
        self._dropped[monitor.topic] = dropped
        rate = monitor.rate(now_ns)
        never = monitor.last_stamp_ns == _NO_STAMP
        age = math.inf if never else (now_ns - monitor.last_stamp_ns) * 1e-9
        st = self._status(f'{monitor.kind} {monitor.topic}')
        if never:
            st.level, st.message = DiagnosticStatus.STALE, 'no messages yet (optional)'
        elif not age <= timeout:
            st.level = DiagnosticStatus.STALE
            st.message = f'newest stamp {age:.3g} s old (timeout {timeout:g} s)'
        elif monitor.frame:
            st.level = DiagnosticStatus.WARN
            st.message = (f'frame_id {monitor.frame!r} is not the frame_id of this node '
                          f'({monitor.expected_frame!r}): no transform is applied')
        elif new_drops > 0:
            st.level = DiagnosticStatus.WARN
            st.message = (f'{new_drops} dropped since the last report (see the prediction '
                          'status)')
        else:
            st.level = DiagnosticStatus.OK
            st.message = f'{rate:.4g} Hz' if math.isfinite(rate) else 'receiving'
        st.values = [KeyValue(key='rate_hz', value=f'{rate:.6g}'),
                     KeyValue(key='stamp_age_s', value=f'{age:.6g}'),
                     KeyValue(key='received', value=str(monitor.count)),
                     KeyValue(key='dropped', value=str(dropped))]
        return st

    def message(self, now_ns: int, stamp: Any, report: Any, startup_error: str | None,
                measured: TopicMonitor | None, timeout: float,
                newest_stamps: list[int] | None = None,
                publishers: list[int] | None = None) -> DiagnosticArray:
        """The whole array at node time ``now_ns``, header stamped ``stamp``.

        ``report`` is the loop's :class:`~soft_rom.predictor.loop.Diagnostics` (``None``
        without a model); ``newest_stamps`` the newest stamp (int ns) of each input;
        ``publishers`` the publishers on each input topic.
        """
        msg = DiagnosticArray()
        msg.header.stamp = stamp
        status = self._status('prediction')
        if report is None:
            status.level = DiagnosticStatus.ERROR
            status.message = f'no model: {startup_error}'
            msg.status = [status]
        else:
            status.level = _level(report.level)
            status.message = report.message
            values = dict(report.values)
            status.values = [KeyValue(key=k, value=v) for k, v in report.values
                             if not k.startswith('input.')]
            names = list(report.health.values.get('input_names', ())) or [
                k[len('input.'):-len('.received')] for k in values
                if k.startswith('input.') and k.endswith('.received')]
            ages = [math.inf if t == _NO_STAMP else (now_ns - t) * 1e-9
                    for t in (newest_stamps or [])] or [math.inf] * len(names)
            msg.status = [status] + self._input_statuses(values, names, ages, timeout,
                                                         publishers)
        if measured is not None:
            drops = 0 if report is None else int(dict(report.values).get('measured_dropped', 0))
            msg.status.append(self._measured_status(measured, now_ns, timeout, drops))
        return msg
