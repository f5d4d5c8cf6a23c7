"""``/diagnostics`` of the controller node: one status, ``<node>: control``.

Level: OK while the last tick's command was computed (``status`` ``ok``) from a trusted
model; WARN when it was held (the reason is the message), the model is not trusted, or the
node's graph is wrong: a second publisher on a topic it reads (the measured centerline, the
reference, the state: ``measured_publishers``, ``reference_publishers``,
``state_publishers``) or any other publisher on a command topic it writes
(``command_publishers``, this node included: a second commander fighting it), counted with
the predictor's :func:`~soft_rom.ros.diagnostics.publisher_counts`; ERROR when the QP failed
or was infeasible.

Values: the command's status, solve / step / tick times (the previous tick and the longest
since the last message), tracking error, saturation, counters, ``last_problem`` (the last
reason anything was held or dropped: a held command overwrites it at every tick) and
``last_dropped`` (the last measurement, state or reference dropped, with the reason: kept
until the next one, so a dropped measurement's reason is seen also while commands are held).
"""

from __future__ import annotations

from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from std_msgs.msg import Header

from soft_rom.ros.diagnostics import publisher_counts, sender_warning

__all__ = ['control_diagnostics']


def _graph(node: Any) -> tuple[dict[str, str], list[str]]:
    """Publisher counts of the topics the node reads and writes, and what is wrong with them."""
    reads = [(key, topic) for key, topic in (('measured', node.measured_topic),
                                             ('reference', node.reference_topic),
                                             ('state', node.state_topic)) if topic]
    writes = [node.array_topic] if node.input_mode == 'array' else list(node.topics)
    counts = publisher_counts(node, [t for _, t in reads] + writes)
    values, problems = {}, []
    for (key, topic), n in zip(reads, counts):
        values[f'{key}_publishers'] = str(n)
        problems.append(sender_warning(n, where=topic))
    own = counts[len(reads):]
    values['command_publishers'] = str(max(own, default=0))
    problems += [sender_warning(n, own=1, where=topic) for topic, n in zip(writes, own)]
    return values, [p for p in problems if p]


def control_diagnostics(node: Any, stamp: Any, cmd: Any) -> DiagnosticArray:
    """The node's ``DiagnosticArray`` for the tick that gave ``cmd`` (header ``stamp``)."""
    c = node.core.counters
    level = DiagnosticStatus.OK if cmd.status == 'ok' and not node.distrust \
        else DiagnosticStatus.WARN
    if cmd.status in ('failed', 'infeasible'):
        level = DiagnosticStatus.ERROR
    last_tick = node.ticks[-1][0] * 1e3 if node.ticks else float('nan')
    # the longest tick since the last message (the last tick if none ran since)
    longest = node.tick_max * 1e3 if node.tick_max > 0 else last_tick
    node.tick_max = 0.0
    graph, problems = _graph(node)
    if problems and level == DiagnosticStatus.OK:
        level = DiagnosticStatus.WARN
    values = {
        'status': cmd.status, 'solve_ms': f'{cmd.solve_s * 1e3:.3f}',
        'step_ms': f'{cmd.step_s * 1e3:.3f}', 'tick_ms': f'{last_tick:.3f}',
        'tick_max_ms': f'{longest:.3f}',
        'tracking_error_m': f'{cmd.tracking_error:.6g}',
        'saturated_inputs': str(cmd.saturated), 'qp_infeasible': str(c.qp_infeasible),
        'qp_failed': str(c.qp_failed), 'held': str(c.held),
        'measurements': str(c.measurements),
        'measurements_dropped': str(c.measurements_dropped),
        'states_dropped': str(c.states_dropped),
        'references_refused': str(c.references_refused),
        'clock_resets': str(c.clock_resets),
        'model_trust': node.distrust or 'trusted',
        'callback_errors': str(node.callback_errors), 'last_problem': c.last_problem,
        'last_dropped': c.last_dropped, **graph,
    }
    message = '; '.join([(cmd.detail or cmd.status)
                         + (' (model not trusted)' if node.distrust else '')] + problems)
    status = DiagnosticStatus(level=level, name=f'{node.get_name()}: control', message=message,
                              hardware_id=node.get_name(),
                              values=[KeyValue(key=k, value=v) for k, v in values.items()])
    return DiagnosticArray(header=Header(stamp=stamp), status=[status])
