"""Bags for ``soft-rom replay``: run the predictor node's loop offline and write its topics.

The topics and types are those of the node (:mod:`soft_rom.ros.predictor_node`), written by
:class:`~soft_rom.bags.prediction_writer.PredictionBagWriter` (re-exported here with
:func:`storage_plugin` and :data:`DEFAULT_NODE_NAME`). What is due when is decided by the
node's own :class:`~soft_rom.predictor.loop.RuntimeLoop`, so a replay bag holds what the node
would have published. :func:`replay_to_bag` runs the loop over an episode;
:func:`replay_stream_to_bag` feeds a bag's messages one by one with their own stamps and
the bag time as reception clock (what the node does under ``ros2 bag play --clock`` with
``use_sim_time``); :func:`read_messages` / :func:`read_messages_ns` read any bag back as
deserialized messages.

Both rosbag2 storage formats are supported: ``'sqlite3'`` and ``'mcap'`` (Jazzy's
default). Times are int nanoseconds (exact at epoch stamps); the writer also takes float
seconds.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import replace
import math
import os
from pathlib import Path
from typing import Any

from soft_rom.bags.prediction_writer import (
    _TS,
    DEFAULT_NODE_NAME,
    PredictionBagWriter,
    storage_plugin,
)
from soft_rom.data import Episode
from soft_rom.errors import BagError
from soft_rom.metrics import relative_error_from_squares
from soft_rom.predictor import Predictor, replay_episode, ReplayResult
from soft_rom.predictor.conversions import check_components, poses_to_points, stamp_to_ns
from soft_rom.predictor.loop import LoopSettings, Publish, RuntimeLoop

__all__ = [
    'DEFAULT_NODE_NAME',
    'PredictionBagWriter',
    'read_messages',
    'read_messages_ns',
    'replay_stream_to_bag',
    'replay_to_bag',
    'storage_plugin',
]


def _legacy_rates(predictor: Predictor, publish_every: int) -> float:
    if publish_every < 1:
        raise BagError(f'publish_every must be >= 1; got {publish_every}.')
    return 0.0 if publish_every == 1 else 1.0 / (publish_every * predictor.h)


def _writer_for(loop: RuntimeLoop, writer: PredictionBagWriter
                ) -> Callable[[Publish, int], None]:
    """A ``publish(pub, now_ns)`` that writes what the loop says is due."""

    def publish(pub: Publish, now_ns: int) -> None:
        for t_ns, y in pub.outputs:
            writer.write_output(t_ns, y)
        if pub.centerline is not None:
            t_ns, pts = pub.centerline
            writer.write_centerline(t_ns, pts, pub.measured_points)
            if pub.error is not None:
                writer.write_error(t_ns, pub.error)
        if pub.diagnostics_due:
            writer.write_diagnostics(now_ns, loop.diagnostics(now_ns))

    return publish


def replay_to_bag(predictor: Predictor, episode: Episode, out: str | os.PathLike[str], *,
                  storage: str = 'mcap', publish_every: int | None = None,
                  settings: LoopSettings | None = None, centerline_rate_hz: float = 30.0,
                  diagnostics_period: float = 1.0, measured: bool = True,
                  node_name: str = DEFAULT_NODE_NAME, frame_id: str = 'world',
                  components: str = 'xz', overwrite: bool = False, t0_ns: int | None = None,
                  progress: Callable[[int], Any] | None = None) -> ReplayResult:
    """Run ``predictor`` over ``episode`` through the node's runtime loop; write its topics.

    The loop (:class:`~soft_rom.predictor.loop.RuntimeLoop`) decides what is published:
    ``~/output`` every step (``publish_every=j``: every j-th step), centerline and markers
    at ``centerline_rate_hz`` (0: with every output), diagnostics every
    ``diagnostics_period`` seconds, the model info once; ``settings`` replaces all of
    these. Inputs are taken as they are (the episode is in model units). Stamps are
    ``t0_ns + t`` in ns; ``t0_ns`` defaults to the episode's ``metadata['t0_ns']`` (the
    recording's absolute start), else 0. Returns the :class:`ReplayResult`.
    """
    if settings is None:
        rate = 0.0 if publish_every is None else _legacy_rates(predictor, publish_every)
        settings = LoopSettings(output_rate_hz=rate, centerline_rate_hz=centerline_rate_hz,
                                diagnostics_rate_hz=1.0 / diagnostics_period,
                                components=components)
    if t0_ns is None:
        start = (episode.metadata or {}).get('t0_ns')
        t0_ns = start if isinstance(start, int) and not isinstance(start, bool) else 0
    settings = replace(settings, input_scale=1.0, input_offset=0.0)
    loop = RuntimeLoop(predictor, settings)
    with PredictionBagWriter(out, storage=storage, node_name=node_name, frame_id=frame_id,
                             components=settings.components, fill=settings.fill_value,
                             overwrite=overwrite) as writer:
        t0 = int(t0_ns) + (int(round(float(episode.t[0]) * 1e9)) if episode.t.size else 0)
        writer.write_model_info(t0, predictor.info)
        write = _writer_for(loop, writer)
        if progress is None:
            publish = write
        else:
            count = [0]

            def publish(pub: Publish, now_ns: int) -> None:
                write(pub, now_ns)
                progress(count[0])
                count[0] += 1

        result = replay_episode(predictor, episode, measured=measured, t0_ns=t0_ns, loop=loop,
                                publish=publish)
    return result


def read_messages(path: str | os.PathLike[str],
                  topics: list[str] | None = None) -> Iterator[tuple[str, float, Any]]:
    """Yield ``(topic, bag_time_seconds, message)`` from any rosbag2 bag, in time order."""
    for topic, ns, msg in read_messages_ns(path, topics):
        yield topic, ns * 1e-9, msg


def read_messages_ns(path: str | os.PathLike[str],
                     topics: list[str] | None = None) -> Iterator[tuple[str, int, Any]]:
    """Yield ``(topic, bag_time_ns, message)`` from any rosbag2 bag, in time order.

    ``topics``: only these (none of them in the bag: nothing); ``None``: every topic.
    Through :class:`~soft_rom.bags.reader.BagReader`, so a bag is opened, checked and its
    errors reported as ``convert`` does.
    """
    from soft_rom.bags.reader import BagReader
    with BagReader(Path(path)) as bag:
        names = list(bag.topics) if topics is None else list(topics)
        for topic, msgtype, ns, raw in bag.raw(names):
            try:
                msg = _TS.deserialize_cdr(raw, msgtype)
            except Exception as err:  # noqa: BLE001 - corrupt CDR raises many kinds
                raise BagError(f'{topic} at log time {ns * 1e-9:.9f} s in bag {path}: cannot '
                               f'decode {msgtype} ({type(err).__name__}: {err}).') from err
            yield topic, ns, msg


def replay_stream_to_bag(predictor: Predictor, bag: str | os.PathLike[str],
                         out: str | os.PathLike[str], *, input_mode: str = 'per_chamber',
                         input_topics: list[str] | None = None,
                         array_topic: str = '/soft_robot/pressures', input_scale: float = 1.0,
                         input_offset: float = 0.0,
                         measured_topic: str = '/soft_robot/centerline',
                         components: str = 'xz', publish_rate_hz: float = 0.0,
                         centerline_rate_hz: float = 30.0, fill_value: float = 0.0,
                         diagnostics_period: float = 1.0, storage: str = 'mcap',
                         node_name: str = DEFAULT_NODE_NAME, frame_id: str = 'world',
                         overwrite: bool = False) -> dict[str, Any]:
    """Replay a bag message by message through the node's runtime loop.

    Unlike :func:`replay_to_bag` (which runs over an :class:`Episode`, inputs already
    aligned on the output stamps), this feeds every input and measured message in bag order
    with its own header stamp (bag time for un-stamped arrays and zero stamps) and the bag
    time as the reception clock, as the node sees ``ros2 bag play --clock`` with
    ``use_sim_time``; the loop's timer (``'fixed'`` stepping: the publish period, else the
    diagnostics period) is emulated on the bag clock. Parameters mirror the node's.

    Returns
    -------
    dict
        ``relative_error`` / ``relative_deviation_error`` of the predictions at the
        measurement steps (before any correction), message counts and predictor counters.
    """
    model = predictor.model
    check_components(components, model.n_outputs)
    index, wanted = _input_topics(model.n_inputs, input_mode, input_topics, array_topic)
    if measured_topic:
        wanted.append(measured_topic)
    loop = RuntimeLoop(predictor, LoopSettings(
        output_rate_hz=publish_rate_hz, centerline_rate_hz=centerline_rate_hz,
        diagnostics_rate_hz=1.0 / diagnostics_period, components=components,
        fill_value=fill_value, input_scale=input_scale, input_offset=input_offset))
    counts = {'inputs': 0, 'measured': 0, 'published': 0}
    totals_before = list(predictor.totals)
    with PredictionBagWriter(out, storage=storage, node_name=node_name, frame_id=frame_id,
                             components=components, fill=fill_value,
                             overwrite=overwrite) as writer:
        write = _writer_for(loop, writer)
        next_tick: int | None = None
        period = loop.timer_period_ns()
        for topic, log_ns, msg in read_messages_ns(bag, wanted):
            if next_tick is None:
                next_tick = log_ns
                writer.write_model_info(log_ns, predictor.info)
            while next_tick <= log_ns:
                write(loop.tick(next_tick), next_tick)
                next_tick += period
            if topic == measured_topic:
                pub = loop.on_measured(poses_to_points(msg.poses), stamp_to_ns(msg.header.stamp),
                                       log_ns)
                counts['measured'] += 1
            elif topic in index:
                pub = loop.on_channel(index[topic], float(msg.fluid_pressure),
                                      stamp_to_ns(msg.header.stamp), log_ns)
                counts['inputs'] += 1
            else:
                pub = loop.on_array(msg.data, 0, log_ns)
                counts['inputs'] += 1
            write(pub, log_ns)
    counts['published'] = loop.counts['outputs']
    return _stream_summary(predictor, loop, totals_before, counts)


def _input_topics(n_inputs: int, input_mode: str, input_topics: list[str] | None,
                  array_topic: str) -> tuple[dict[str, int], list[str]]:
    """The input topics a stream replay reads: ``({per-chamber topic: input index}, topics)``."""
    topics = list(input_topics or [f'/soft_robot/pressure/chamber_{i + 1}'
                                   for i in range(n_inputs)])
    if input_mode == 'per_chamber':
        if len(topics) != n_inputs:
            raise BagError(f'the model has {n_inputs} inputs; {len(topics)} input '
                           'topics given.')
        return {tp: i for i, tp in enumerate(topics)}, list(topics)
    if input_mode == 'array':
        return {}, [array_topic]
    raise BagError(f"input_mode must be 'per_chamber' or 'array'; got {input_mode!r}.")


def _stream_summary(predictor: Predictor, loop: RuntimeLoop, totals_before: list[float],
                    counts: dict[str, int]) -> dict[str, Any]:
    """The summary :func:`replay_stream_to_bag` returns (errors since ``totals_before``)."""
    e2, y2, d2 = (a - b for a, b in zip(predictor.totals, totals_before))
    n_meas = predictor.counters['measurements']
    zero = 0.0 if e2 == 0.0 else math.nan   # as replay_episode: not perfect unless exact
    return {
        'relative_error': relative_error_from_squares(e2, y2, if_zero=zero) if n_meas
        else math.nan,
        'relative_deviation_error': relative_error_from_squares(e2, d2, if_zero=zero) if n_meas
        else math.nan,
        'messages': counts,
        'counters': dict(predictor.counters),
        'loop': dict(loop.counts),
        'model': predictor.info,
    }
