"""``/diagnostics`` of the predictor node: the prediction, and each input topic.

Status names are stable (``<node name>: <task>``, the convention of diagnostic_updater):

* ``<node>: prediction`` - the core's health (OK / WARN / ERROR / STALE with the reason)
  and its figures (windowed errors, counters, model time);
* ``<node>: input <topic>`` - one per chamber topic (or the array topic): ``rate_hz``
  (messages per second since the previous report), ``stamp_age_s`` (now minus the newest
  header stamp), ``messages``; STALE when nothing arrived within ``input_timeout_s``;
* ``<node>: measured <topic>`` - the same for the measured centerline; STALE (not an error:
  it is optional) when none arrives.

Every status carries the same ``hardware_id`` (parameter ``hardware_id``, default the
node's fully qualified name), as diagnostic_updater's FrequencyStatus / TimeStampStatus do.
"""

from __future__ import annotations

import math
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from soft_rom.ros.conversions import health_key_values

__all__ = ['Diagnostics', 'TopicMonitor']


class TopicMonitor:
    """Counts the messages of one topic and keeps the newest header stamp (seconds)."""

    __slots__ = ('topic', 'kind', 'count', 'last_stamp', '_t0', '_n0')

    def __init__(self, topic: str, kind: str) -> None:
        self.topic = topic
        self.kind = kind
        self.count = 0
        self.last_stamp = math.nan
        self._t0 = math.nan
        self._n0 = 0

    def seen(self, stamp: float) -> None:
        """One message stamped ``stamp`` arrived (the hot path: two assignments)."""
        self.count += 1
        self.last_stamp = stamp

    def rate(self, now: float) -> float:
        """Messages per second since the previous call (NaN on the first)."""
        t0, n0 = self._t0, self._n0
        self._t0, self._n0 = now, self.count
        if not (math.isfinite(t0) and now > t0):
            return math.nan
        return (self.count - n0) / (now - t0)


def _level(level: int) -> bytes:
    return bytes([int(level)])


class Diagnostics:
    """Builds the node's ``DiagnosticArray`` (one status for the core, one per topic)."""

    msg_type = DiagnosticArray

    def __init__(self, node_name: str, hardware_id: str) -> None:
        self.node_name = node_name
        self.hardware_id = hardware_id

    def topic_status(self, monitor: TopicMonitor, now: float, timeout: float
                     ) -> DiagnosticStatus:
        """The status of one input or measured topic."""
        rate = monitor.rate(now)
        age = now - monitor.last_stamp
        status = DiagnosticStatus(name=f'{self.node_name}: {monitor.kind} {monitor.topic}',
                                  hardware_id=self.hardware_id)
        if monitor.count == 0:
            status.level = DiagnosticStatus.STALE
            status.message = 'no messages yet'
        elif not age <= timeout:
            status.level = DiagnosticStatus.STALE
            status.message = f'newest stamp {age:.3g} s old (timeout {timeout:g} s)'
        else:
            status.level = DiagnosticStatus.OK
            status.message = f'{rate:.4g} Hz' if math.isfinite(rate) else 'receiving'
        status.values = [KeyValue(key='rate_hz', value=f'{rate:.6g}'),
                         KeyValue(key='stamp_age_s', value=f'{age:.6g}'),
                         KeyValue(key='messages', value=str(monitor.count))]
        return status

    def message(self, now: float, stamp: Any, predictor: Any, startup_error: str | None,
                monitors: list[TopicMonitor], measured: TopicMonitor | None, timeout: float,
                callback_errors: int) -> DiagnosticArray:
        """The whole array at node time ``now`` (seconds), header stamped ``stamp``."""
        msg = DiagnosticArray()
        msg.header.stamp = stamp
        status = DiagnosticStatus(name=f'{self.node_name}: prediction',
                                  hardware_id=self.hardware_id)
        if predictor is None:
            status.level = DiagnosticStatus.ERROR
            status.message = f'no model: {startup_error}'
        else:
            health = predictor.health(now)
            status.level = _level(health.level)
            status.message = health.message
            values = health_key_values(health)
            values.append(('callback_errors', str(callback_errors)))
            status.values = [KeyValue(key=k, value=v) for k, v in values]
        msg.status = [status] + [self.topic_status(m, now, timeout) for m in monitors]
        if measured is not None:
            msg.status.append(self.topic_status(measured, now, timeout))
        return msg
