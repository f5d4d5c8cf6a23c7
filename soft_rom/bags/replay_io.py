"""Bags for ``soft-rom replay``: write the predictor node's topics offline (rosbags).

:class:`PredictionBagWriter` writes exactly the topics and types the node
(:mod:`soft_rom.ros.predictor_node`) publishes, under the node's name
(default ``soft_rom_predictor``):

================================== ====================================== ======================
topic                              type                                   when
================================== ====================================== ======================
``/<node>/output``                 ``std_msgs/msg/Float64MultiArray``     every step (or at the
                                                                          output rate)
``/<node>/centerline``             ``geometry_msgs/msg/PoseArray``        at the centerline rate
``/<node>/centerline_marker``      ``visualization_msgs/msg/Marker``      idem (ns ``predicted``,
                                                                          and ``measured``)
``/<node>/error``                  ``std_msgs/msg/Float64``               idem, with measurements
``/diagnostics``                   ``diagnostic_msgs/msg/DiagnosticArray`` every period
``/<node>/model_info``             ``std_msgs/msg/String`` (JSON)         once, transient local
================================== ====================================== ======================

What is due when is decided by the node's own
:class:`~soft_rom.predictor.loop.RuntimeLoop`, so a replay bag holds what the node would
have published. :func:`replay_to_bag` runs the loop over an episode;
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
import shutil
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

from soft_rom.data import Episode
from soft_rom.errors import BagError
from soft_rom.metrics import relative_error_from_squares
from soft_rom.predictor import Predictor, replay_episode, ReplayResult
from soft_rom.predictor.conversions import (
    check_components,
    model_info_json,
    ns_to_stamp,
    poses_to_points,
    stamp_to_ns,
)
from soft_rom.predictor.loop import Diagnostics, LoopSettings, MARKER_STYLES, Publish, RuntimeLoop

try:  # rosbags >= 0.10
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )
except ImportError:  # pragma: no cover - older rosbags: no QoS metadata
    Qos = None  # type: ignore[assignment,misc]

__all__ = [
    'DEFAULT_NODE_NAME',
    'PredictionBagWriter',
    'read_messages',
    'read_messages_ns',
    'replay_stream_to_bag',
    'replay_to_bag',
    'storage_plugin',
]

DEFAULT_NODE_NAME = 'soft_rom_predictor'
_TS = get_typestore(Stores.ROS2_JAZZY)
_T = _TS.types
Array = NDArray[np.float64]


def storage_plugin(storage: str) -> StoragePlugin:
    """``'sqlite3'`` or ``'mcap'`` to the rosbags plugin."""
    try:
        return {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}[storage]
    except KeyError:
        raise BagError(f"bag storage must be 'sqlite3' or 'mcap'; got {storage!r}.") from None


def _open_writer(path: str | os.PathLike[str], storage: str, overwrite: bool) -> Writer:
    path = Path(path)
    if path.exists():
        if not overwrite:
            raise FileExistsError(f'{path} exists; choose another output or pass overwrite.')
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    writer = Writer(path, version=9, storage_plugin=storage_plugin(storage))
    try:
        writer.open()
    except Exception as err:  # rosbags WriterError and OSError
        raise BagError(f'cannot create bag {path}: {err}') from err
    return writer


def _latched_qos() -> list[Any]:
    if Qos is None:  # pragma: no cover
        return []
    zero = QosTime(0, 0)
    return [Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
                zero, zero, QosLiveliness.AUTOMATIC, zero, False)]


def _ns(t: float | int) -> int:
    """A time as int ns: ints are ns already, floats are seconds."""
    if isinstance(t, (int, np.integer)):
        return int(t)
    return int(round(float(t) * 1e9))


def _header(t: float | int, frame_id: str) -> Any:
    sec, nsec = ns_to_stamp(_ns(t))
    return _T['std_msgs/msg/Header'](stamp=_T['builtin_interfaces/msg/Time'](sec, nsec),
                                     frame_id=frame_id)


def _point(x: float, y: float, z: float) -> Any:
    return _T['geometry_msgs/msg/Point'](x=x, y=y, z=z)


def _pose_array(t: float | int, frame_id: str, points: Array) -> Any:
    Pose, Quat = _T['geometry_msgs/msg/Pose'], _T['geometry_msgs/msg/Quaternion']
    poses = [Pose(position=_point(x, y, z), orientation=Quat(0.0, 0.0, 0.0, 1.0))
             for x, y, z in points.tolist()]
    return _T['geometry_msgs/msg/PoseArray'](header=_header(t, frame_id), poses=poses)


def _marker(t: float | int, frame_id: str, points: Array, ns: str, marker_id: int,
            rgba: tuple[float, float, float, float], width: float) -> Any:
    M: Any = _T['visualization_msgs/msg/Marker']     # its constants are not in the stubs
    empty = np.zeros(0, dtype=np.uint8)
    return M(
        header=_header(t, frame_id), ns=ns, id=marker_id, type=M.LINE_STRIP, action=M.ADD,
        pose=_T['geometry_msgs/msg/Pose'](position=_point(0.0, 0.0, 0.0),
                                          orientation=_T['geometry_msgs/msg/Quaternion'](
                                              0.0, 0.0, 0.0, 1.0)),
        scale=_T['geometry_msgs/msg/Vector3'](x=width, y=0.0, z=0.0),
        color=_T['std_msgs/msg/ColorRGBA'](*rgba),
        lifetime=_T['builtin_interfaces/msg/Duration'](sec=0, nanosec=0), frame_locked=False,
        points=[_point(x, y, z) for x, y, z in points.tolist()], colors=[],
        texture_resource='',
        texture=_T['sensor_msgs/msg/CompressedImage'](header=_header(t, frame_id), format='',
                                                      data=empty),
        uv_coordinates=[], text='', mesh_resource='',
        mesh_file=_T['visualization_msgs/msg/MeshFile'](filename='', data=empty),
        mesh_use_embedded_materials=False)


def _float64_array(values: Array, label: str) -> Any:
    dim = _T['std_msgs/msg/MultiArrayDimension'](label=label, size=values.size,
                                                 stride=values.size)
    layout = _T['std_msgs/msg/MultiArrayLayout'](dim=[dim], data_offset=0)
    return _T['std_msgs/msg/Float64MultiArray'](layout=layout,
                                                data=np.array(values, dtype=np.float64))


def _diagnostics(t: int, diag: Diagnostics, name: str, hardware_id: str) -> Any:
    KV = _T['diagnostic_msgs/msg/KeyValue']
    status = _T['diagnostic_msgs/msg/DiagnosticStatus'](
        level=int(diag.level), name=name, message=diag.message, hardware_id=hardware_id,
        values=[KV(key=k, value=v) for k, v in diag.values])
    return _T['diagnostic_msgs/msg/DiagnosticArray'](header=_header(t, ''), status=[status])


_MARKERS = MARKER_STYLES


def _sentinel(n: int) -> Array:
    """``(n, 3)`` distinctive doubles, located in a serialized template by their bytes."""
    return (np.arange(3 * n, dtype=np.float64).reshape(n, 3) + 0.123456789) * -1.2345e-7 - 7e5


class _CdrTemplate:
    """A serialized message whose stamp and one block of doubles are patched per write.

    The block (``n`` rows of ``stride`` doubles, the first ``values.shape[1]`` of each row
    patched) is found by searching the serialized template for the sentinel values; CDR
    lays out a sequence of fixed-size double structs contiguously, so patching it is exact.
    The header stamp of a message starting with ``std_msgs/Header`` follows the 4-byte
    encapsulation header (``int32 sec`` at byte 4, ``uint32 nanosec`` at byte 8).
    """

    def __init__(self, msg: Any, msgtype: str, sentinel: Array, *, stride: int,
                 header: bool = True) -> None:
        self.buf = bytearray(_TS.serialize_cdr(msg, msgtype))
        if self.buf[:2] != b'\x00\x01':  # little-endian CDR only
            raise BagError('unexpected CDR encapsulation in a message template.')
        first = np.ascontiguousarray(sentinel[0, :1], dtype='<f8').tobytes()
        offset = bytes(self.buf).find(first)
        n, cols = sentinel.shape
        if offset < 0:
            raise BagError(f'cannot locate the data block of a {msgtype} template.')
        self.block = np.frombuffer(self.buf, dtype='<f8', count=n * stride,
                                   offset=offset).reshape(n, stride)
        if not np.array_equal(self.block[:, :cols], sentinel):
            raise BagError(f'the data block of a {msgtype} template is not contiguous.')
        self.cols = cols
        self.header = header
        self.stamp = np.frombuffer(self.buf, dtype='<u4', count=2, offset=4) if header else None

    def render(self, t: float | int, values: Array) -> bytes:
        """Serialized message with stamp ``t`` (int ns, or float s) and ``values`` (n, cols)."""
        if self.stamp is not None:
            self.stamp[:] = ns_to_stamp(_ns(t))
        self.block[:, :self.cols] = values
        return bytes(self.buf)


class PredictionBagWriter:
    """Write the predictor node's topics to a bag (a context manager).

    Parameters
    ----------
    path : path
        Output bag directory (must not exist unless ``overwrite``).
    storage : {'mcap', 'sqlite3'}
    node_name : str
        Topics are ``/<node_name>/...`` (the node's private ``~/`` names).
    frame_id : str
        Frame of the centerline.
    components : str
        Output layout (``'xz'``: ``y = [x_1..x_N, z_1..z_N]``).
    fill : float
        Coordinate value for components the model does not predict.
    """

    def __init__(self, path: str | os.PathLike[str], *, storage: str = 'mcap',
                 node_name: str = DEFAULT_NODE_NAME, frame_id: str = 'world',
                 components: str = 'xz', fill: float = 0.0, overwrite: bool = False) -> None:
        self.path = Path(path)
        self.frame_id, self.components, self.fill = frame_id, components, float(fill)
        self.node_name = node_name.strip('/')
        self._writer = _open_writer(self.path, storage, overwrite)
        base = f'/{self.node_name}'
        self.topics = {
            'centerline': (f'{base}/centerline', 'geometry_msgs/msg/PoseArray'),
            'marker': (f'{base}/centerline_marker', 'visualization_msgs/msg/Marker'),
            'output': (f'{base}/output', 'std_msgs/msg/Float64MultiArray'),
            'error': (f'{base}/error', 'std_msgs/msg/Float64'),
            'diagnostics': ('/diagnostics', 'diagnostic_msgs/msg/DiagnosticArray'),
            'model_info': (f'{base}/model_info', 'std_msgs/msg/String'),
        }
        self._templates: dict[tuple[str, int], _CdrTemplate] = {}
        self._conn = {}
        for key, (topic, msgtype) in self.topics.items():
            qos = _latched_qos() if key == 'model_info' else []
            self._conn[key] = self._writer.add_connection(topic, msgtype, typestore=_TS,
                                                          offered_qos_profiles=qos)

    def _write(self, key: str, t: float | int, msg: Any) -> None:
        data = _TS.serialize_cdr(msg, self.topics[key][1])
        self._writer.write(self._conn[key], _ns(t), data)

    def write_model_info(self, t: float | int, info: dict[str, Any]) -> None:
        """The latched JSON description of the model."""
        self._write('model_info', t, _T['std_msgs/msg/String'](data=model_info_json(info)))

    def _template(self, kind: str, n: int) -> _CdrTemplate:
        key = (kind, n)
        tpl = self._templates.get(key)
        if tpl is None:
            sentinel = _sentinel(n)
            if kind == 'centerline':
                tpl = _CdrTemplate(_pose_array(0.0, self.frame_id, sentinel),
                                   self.topics['centerline'][1], sentinel, stride=7)
            elif kind == 'output':
                flat = sentinel.reshape(-1)[:n]
                tpl = _CdrTemplate(_float64_array(flat, 'outputs'), self.topics['output'][1],
                                   flat.reshape(-1, 1), stride=1, header=False)
            else:
                ns, marker_id, rgba, width = _MARKERS[kind]
                tpl = _CdrTemplate(_marker(0.0, self.frame_id, sentinel, ns, marker_id, rgba,
                                           width), self.topics['marker'][1], sentinel,
                                   stride=3)
            self._templates[key] = tpl
        return tpl

    def _write_raw(self, key: str, t: float | int, data: bytes) -> None:
        self._writer.write(self._conn[key], _ns(t), data)

    def write_output(self, t: float | int, y: Array) -> None:
        """``~/output`` at model time ``t`` (int ns or float s)."""
        y = np.asarray(y, dtype=np.float64)
        self._write_raw('output', t, self._template('output', y.size).render(
            t, y.reshape(-1, 1)))

    def write_centerline(self, t: float | int, points: Array,
                         measured: Array | None = None) -> None:
        """``~/centerline`` and the marker(s) from points ``(N, 3)`` at ``t``."""
        n = points.shape[0]
        self._write_raw('centerline', t, self._template('centerline', n).render(t, points))
        self._write_raw('marker', t, self._template('predicted', n).render(t, points))
        if measured is not None:
            self._write_raw('marker', t, self._template('measured', measured.shape[0]).render(
                t, measured))

    def write_error(self, t: float | int, error: float) -> None:
        """Windowed relative error (``std_msgs/Float64``)."""
        self._write('error', t, _T['std_msgs/msg/Float64'](data=float(error)))

    def write_diagnostics(self, t: float | int, diag: Diagnostics) -> None:
        """One ``DiagnosticArray`` with a loop's :class:`Diagnostics` report."""
        self._write('diagnostics', t, _diagnostics(
            _ns(t), diag, f'{self.node_name}: prediction', f'/{self.node_name}'))

    def close(self) -> None:
        """Finish the bag (writes its metadata)."""
        self._writer.close()

    def __enter__(self) -> PredictionBagWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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
    diagnostics period) is emulated on the bag clock. Parameters mirror the node's. About 85
    lines: the message loop and the node's emulated timer share their state.

    Returns
    -------
    dict
        ``relative_error`` / ``relative_deviation_error`` of the predictions at the
        measurement steps (before any correction), message counts and predictor counters.
    """
    model = predictor.model
    check_components(components, model.n_outputs)
    topics = list(input_topics or [f'/soft_robot/pressure/chamber_{i + 1}'
                                   for i in range(model.n_inputs)])
    if input_mode == 'per_chamber':
        if len(topics) != model.n_inputs:
            raise BagError(f'the model has {model.n_inputs} inputs; {len(topics)} input '
                           'topics given.')
        index = {tp: i for i, tp in enumerate(topics)}
        wanted = list(topics)
    elif input_mode == 'array':
        index, wanted = {}, [array_topic]
    else:
        raise BagError(f"input_mode must be 'per_chamber' or 'array'; got {input_mode!r}.")
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
    e2, y2, d2 = (a - b for a, b in zip(predictor.totals, totals_before))
    n_meas = predictor.counters['measurements']
    return {
        'relative_error': relative_error_from_squares(e2, y2, if_zero=0.0) if n_meas
        else math.nan,
        'relative_deviation_error': relative_error_from_squares(e2, d2, if_zero=0.0) if n_meas
        else math.nan,
        'messages': counts,
        'counters': dict(predictor.counters),
        'loop': dict(loop.counts),
        'model': predictor.info,
    }
