"""The predictor node's topics written to a bag offline (rosbags): :class:`PredictionBagWriter`.

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

The messages that repeat (output, centerline, markers) are serialized once per size as a
template (:class:`_CdrTemplate`) whose stamp and data block are patched per write. Both
rosbag2 storage formats are supported: ``'sqlite3'`` and ``'mcap'`` (Jazzy's default).
Times are int nanoseconds (exact at epoch stamps); the writer also takes float seconds.
"""

from __future__ import annotations

import os
from pathlib import Path
import shutil
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

from soft_rom.errors import BagError
from soft_rom.predictor.conversions import model_info_json, ns_to_stamp
from soft_rom.predictor.loop import Diagnostics, MARKER_STYLES

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

__all__ = ['DEFAULT_NODE_NAME', 'PredictionBagWriter', 'storage_plugin']

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
