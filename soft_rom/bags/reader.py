"""Reading ROS 2 bags (sqlite3 or MCAP) as streams of decoded numpy values.

:class:`BagReader` wraps :class:`rosbags.rosbag2.Reader`, translates its errors into
:class:`~soft_rom.errors.BagError` with the bag, topic and time in the message, and turns
the message types of the bag contract into numpy values (:func:`decode`):

=================================== =========================== =======================
type                                value                       stamp
=================================== =========================== =======================
``sensor_msgs/msg/FluidPressure``   ``(1,)`` Pa                 ``header.stamp``
``std_msgs/msg/Float64MultiArray``  ``(len,)`` (layout kept)    none: bag log time
``std_msgs/msg/Float32MultiArray``  ``(len,)`` float32         none: bag log time
``geometry_msgs/msg/PoseArray``     ``(N, 3)`` positions        ``header.stamp``
``geometry_msgs/msg/PoseStamped``   ``(1, 3)``                  ``header.stamp``
``sensor_msgs/msg/PointCloud2``     ``(N, 3)`` x, y, z fields   ``header.stamp``
=================================== =========================== =======================

Time stamps stay integer nanoseconds here (and through :mod:`soft_rom.convert`, which turns
them into seconds from each episode's start only when the episode is written).
Multi-array data are returned as zero-copy views of the message buffer.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
import copy
from dataclasses import dataclass
import heapq
from pathlib import Path
import sqlite3
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.errors import ReaderError

from soft_rom.bags._cdr import FAST, raw_frame_id
from soft_rom.bags.writer import typestore
from soft_rom.errors import BagError

__all__ = ['BagMessage', 'BagReader', 'SUPPORTED_TYPES', 'decode', 'describe_bag', 'is_bag',
           'bag_storage']

#: Message types :func:`decode` understands.
SUPPORTED_TYPES = (
    'sensor_msgs/msg/FluidPressure',
    'std_msgs/msg/Float64MultiArray',
    'std_msgs/msg/Float32MultiArray',
    'geometry_msgs/msg/PoseArray',
    'geometry_msgs/msg/PoseStamped',
    'sensor_msgs/msg/PointCloud2',
)

#: The first bytes of a zstd frame.
_ZSTD_MAGIC = b'\x28\xb5\x2f\xfd'
#: Largest log time of a ROS 2 message (``rcutils_time_point_value_t`` is int64 ns); an MCAP
#: stores log times as uint64, so a damaged or hand-made one can hold more.
INT64_MAX = 2 ** 63 - 1
_PF_DTYPES = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}


@dataclass(frozen=True)
class BagMessage:
    """One decoded message.

    Attributes
    ----------
    topic : str
    msgtype : str
    log_ns : int
        Bag log (receive) time, ns.
    stamp_ns : int or None
        ``header.stamp`` in ns, or ``None`` for header-less types.
    value : ndarray
        See the table in the module docstring.
    layout : tuple of (label, size), optional
        Multi-array layout dimensions.
    frame_id : str or None
        ``header.frame_id``, or ``None`` for header-less types.
    """

    topic: str
    msgtype: str
    log_ns: int
    stamp_ns: int | None
    value: NDArray[Any]
    layout: tuple[tuple[str, int], ...] = ()
    frame_id: str | None = None


def _stamp(msg: Any) -> int:
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


def _pointcloud_xyz(msg: Any) -> NDArray[Any]:
    fields = {f.name: f for f in msg.fields}
    missing = [c for c in 'xyz' if c not in fields]
    if missing:
        raise BagError(f'PointCloud2 has no field(s) {missing}; fields are {sorted(fields)}.')
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    raw = np.asarray(msg.data, dtype=np.uint8)
    if raw.size < n * step:
        raise BagError(f'PointCloud2 data has {raw.size} bytes; expected {n * step} '
                       f'({n} points x {step} bytes).')
    end = '>' if msg.is_bigendian else '<'
    out = np.empty((n, 3), dtype=np.float64)
    f0 = [fields[c] for c in 'xyz']
    dts = {_PF_DTYPES.get(int(f.datatype)) for f in f0}
    offs = [int(f.offset) for f in f0]
    if None in dts:
        raise BagError('PointCloud2 x/y/z fields have an unsupported datatype.')
    kinds = [d for d in dts if d is not None]
    if len(kinds) == 1 and step % np.dtype(kinds[0]).itemsize == 0 and int(
            msg.row_step) == step * int(msg.width):
        dt = np.dtype(end + kinds[0])
        isz = dt.itemsize
        if all(o % isz == 0 for o in offs):
            rows = raw[:n * step].view(dt).reshape(n, step // isz)
            return rows[:, [o // isz for o in offs]].astype(np.float64)
    rows = raw[:n * step].reshape(n, step)
    for j, f in enumerate(f0):
        dt = np.dtype(end + _PF_DTYPES[int(f.datatype)])
        o = int(f.offset)
        out[:, j] = np.ascontiguousarray(rows[:, o:o + dt.itemsize]).view(dt).reshape(n)
    return out


def decode(msgtype: str, msg: Any) -> tuple[int | None, NDArray[Any], tuple[tuple[str, int],
                                                                                ...]]:
    """Return ``(stamp_ns or None, value, layout)`` of a deserialised message."""
    if msgtype == 'sensor_msgs/msg/FluidPressure':
        return _stamp(msg), np.array([msg.fluid_pressure], dtype=np.float64), ()
    if msgtype in ('std_msgs/msg/Float64MultiArray', 'std_msgs/msg/Float32MultiArray'):
        data = np.asarray(msg.data)
        off = int(msg.layout.data_offset)
        layout = tuple((str(d.label), int(d.size)) for d in msg.layout.dim)
        return None, data[off:] if off else data, layout
    if msgtype == 'geometry_msgs/msg/PoseArray':
        pts = np.array([(p.position.x, p.position.y, p.position.z) for p in msg.poses],
                       dtype=np.float64).reshape(-1, 3)
        return _stamp(msg), pts, ()
    if msgtype == 'geometry_msgs/msg/PoseStamped':
        p = msg.pose.position
        return _stamp(msg), np.array([[p.x, p.y, p.z]], dtype=np.float64), ()
    if msgtype == 'sensor_msgs/msg/PointCloud2':
        return _stamp(msg), _pointcloud_xyz(msg), ()
    raise BagError(f'message type {msgtype} is not supported; use one of {SUPPORTED_TYPES}.')


#: Storage of a bag file by the end of its name (``ros2 bag record --compression-mode file``
#: writes ``*.mcap.zstd`` / ``*.db3.zstd``).
_STORAGE_ENDINGS = (('.mcap', 'mcap'), ('.mcap.zstd', 'mcap'), ('.db3', 'sqlite3'),
                    ('.db3.zstd', 'sqlite3'))
#: rosbag2 storage identifiers (``metadata.yaml``) and the storage soft_rom reads for each.
_STORAGE_IDS = {'mcap': 'mcap', 'sqlite3': 'sqlite3'}


def _file_storage(f: Path) -> str | None:
    """``'mcap'`` / ``'sqlite3'`` from the end of a bag file's name; ``None`` otherwise."""
    return next((kind for end, kind in _STORAGE_ENDINGS if f.name.endswith(end)), None)


def is_bag(path: str | Path) -> bool:
    """True if ``path`` looks like a rosbag2 directory or a ``.mcap`` / ``.db3`` file.

    A directory counts when it holds ``metadata.yaml`` or a bag file (also the
    ``.mcap.zstd`` / ``.db3.zstd`` files of a file-compressed recording).
    """
    p = Path(path)
    if p.is_dir():
        return (p / 'metadata.yaml').exists() or any(
            _file_storage(f) is not None for f in p.iterdir())
    return _file_storage(p) is not None and p.exists()


def _metadata_storage(p: Path) -> str | None:
    """The storage named by a bag directory's ``metadata.yaml``; ``None`` if it names none."""
    import yaml
    try:
        with open(p / 'metadata.yaml', 'rb') as fh:
            meta = yaml.safe_load(fh.read(1 << 20))
        ident = meta['rosbag2_bagfile_information']['storage_identifier']
    except (OSError, yaml.YAMLError, TypeError, KeyError, ValueError):
        return None          # unreadable here: the reader reports it when it opens the bag
    if not isinstance(ident, str) or not ident:
        return None
    if ident not in _STORAGE_IDS:
        raise BagError(f'{p} is a rosbag2 bag of storage {ident!r}; soft_rom reads mcap and '
                       'sqlite3 bags (convert it with `ros2 bag convert`).')
    return _STORAGE_IDS[ident]


def bag_storage(path: str | Path) -> str:
    """``'mcap'`` or ``'sqlite3'``: from ``metadata.yaml``, else from the bag's files.

    A file-compressed bag (``*.mcap.zstd``, ``*.db3.zstd``) is read through its directory
    (rosbags decompresses it); given as a single file it is refused with that advice.
    """
    p = Path(path)
    if p.is_file() and p.name.endswith('.zstd') and _file_storage(p) is not None:
        raise BagError(f'{p} is one file of a file-compressed bag: give its folder (the one '
                       'with metadata.yaml), or decompress it (zstd -d).')
    kind = _metadata_storage(p) if p.is_dir() and (p / 'metadata.yaml').is_file() else None
    if kind is not None:
        return kind
    files = [p] if p.is_file() else list(p.iterdir()) if p.is_dir() else []
    kinds = {_file_storage(f) for f in files} - {None}
    for kind in ('mcap', 'sqlite3'):
        if kind in kinds:
            return kind
    raise BagError(f'{p} is not a ROS 2 bag (no .mcap or .db3 file).')


def _open_advice(why: str, storage: str) -> str:
    """What to do about a bag rosbags cannot open, from its reason."""
    low = why.lower()
    if 'not supported' in low or 'profile' in low:
        return ('soft_rom reads bags through the rosbags package, which does not support this '
                'one: update rosbags (pip install -U rosbags), or rewrite the bag with '
                '`ros2 bag convert`.')
    if 'does not exist' in low or 'no such file' in low or 'missing' in low:
        return ('A file the bag lists is missing: copy the whole bag folder, or recreate its '
                'metadata from the files that are there with `ros2 bag reindex`.')
    if storage == 'mcap':
        return ('The bag may be truncated or corrupt (was the recorder killed?); try '
                '`mcap recover` or `ros2 bag reindex` on it.')
    return ('The bag may be truncated or corrupt (was the recorder killed?); try '
            '`ros2 bag reindex` on it.')


class BagReader:
    """Open a ROS 2 bag for reading; use as a context manager.

    Parameters
    ----------
    path : str or Path
        rosbag2 directory (with ``metadata.yaml``) or a single ``.mcap`` / ``.db3`` file.
    storage : {'auto', 'mcap', 'sqlite3'}
        Expected storage; ``'auto'`` accepts either.

    Raises
    ------
    FileNotFoundError
        ``path`` does not exist.
    BagError
        The bag is truncated, corrupt, of another storage than requested, or unreadable.
    """

    def __init__(self, path: str | Path, storage: str = 'auto') -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f'bag {self.path} does not exist.')
        if storage not in ('auto', 'mcap', 'sqlite3'):
            raise BagError(f"storage must be 'auto', 'mcap' or 'sqlite3'; got {storage!r}.")
        self.storage = bag_storage(self.path)
        if storage != 'auto' and storage != self.storage:
            raise BagError(f'{self.path} is a {self.storage} bag, not {storage}.')
        self._reader: Reader | None = None
        self._ts = typestore()

    def _storage_path(self) -> Path:
        """What rosbags opens: the bag, or the one storage file of a folder without metadata.

        ``ros2 bag record`` writes ``metadata.yaml`` when it stops, so a recording whose
        recorder was killed (or a copy of only its data file) is a folder holding the storage
        file alone; with one uncompressed file that file is the bag.
        """
        p = self.path
        if not p.is_dir() or (p / 'metadata.yaml').exists():
            return p
        files = sorted(f.name for f in p.iterdir() if _file_storage(f) is not None)
        plain = [f for f in files if not f.endswith('.zstd')]
        if len(files) == 1 and plain:
            return p / plain[0]
        if len(files) == 1:
            raise BagError(f'bag {p} has no metadata.yaml and its one file {files[0]} is '
                           'compressed: decompress it (zstd -d) and give the file, or recreate '
                           f'the metadata with `ros2 bag reindex {p}`.')
        raise BagError(f'bag {p} has no metadata.yaml and {len(files)} storage files '
                       f'({", ".join(files[:4])}{", ..." if len(files) > 4 else ""}), so '
                       'their order and compression are unknown (was the recorder killed?): '
                       f'recreate it with `ros2 bag reindex {p}`.')

    def open(self) -> BagReader:
        """Open the bag (reads its metadata and index)."""
        target = self._storage_path()
        try:
            reader = Reader(target)
            reader.open()
        except (ReaderError, OSError, ValueError, KeyError, sqlite3.DatabaseError) as err:
            # rosbags 0.11.5 and older let sqlite3's DatabaseError through unwrapped.
            why = str(err).rstrip('.')
            raise BagError(f'cannot open bag {self.path} ({self.storage}): {why}. '
                           f'{_open_advice(why, self.storage)}') from err
        except Exception as err:  # noqa: BLE001 - storage backends raise many kinds
            raise BagError(f'cannot open bag {self.path} ({self.storage}): '
                           f'{type(err).__name__}: {err}') from err
        self._reader = reader
        return self

    def close(self) -> None:
        """Close the bag."""
        if self._reader is not None:
            reader, self._reader = self._reader, None
            try:
                reader.close()
            except Exception:  # noqa: BLE001 - nothing to save at this point
                pass

    def __enter__(self) -> BagReader:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def reader(self) -> Reader:
        """The underlying rosbags reader."""
        if self._reader is None:
            raise BagError('BagReader is not open: use it as a context manager.')
        return self._reader

    def _file_counts(self) -> dict[str, int] | None:
        """Messages per topic counted in the storage files of a bag folder.

        A folder's counts otherwise come from ``metadata.yaml``, which can disagree with the
        files (a hand-edited bag; rosbag2's rewrite with message compression has written
        wrong counts); the files' own indexes are what is read. ``None`` for a
        single file (its counts are the file's) or where the storages are not reachable.
        """
        parts = getattr(getattr(self.reader, 'storage', None), 'storages', None)
        if not isinstance(parts, list):
            return None
        counts: dict[str, int] = {}
        try:
            for part in parts:
                for conn in part.connections:
                    counts[conn.topic] = counts.get(conn.topic, 0) + int(conn.msgcount)
        except (AttributeError, TypeError, ValueError):
            return None
        return counts

    @property
    def topics(self) -> dict[str, tuple[str, int]]:
        """``{topic: (msgtype, message count)}``; counts from the storage files."""
        counts = self._file_counts()
        return {name: (info.msgtype or 'mixed',
                       int(info.msgcount if counts is None else counts.get(name, 0)))
                for name, info in self.reader.topics.items()}

    @property
    def start_ns(self) -> int:
        """Log time of the first message (ns); 0 for an empty bag."""
        return int(self.reader.start_time) if self.reader.message_count else 0

    @property
    def end_ns(self) -> int:
        """Log time of the last message (ns); 0 for an empty bag."""
        # rosbags reports an exclusive end (last stamp + 1 ns).
        return int(self.reader.end_time) - 1 if self.reader.message_count else 0

    @property
    def message_count(self) -> int:
        """Total number of messages (counted in the storage files)."""
        counts = self._file_counts()
        return int(self.reader.message_count) if counts is None else sum(counts.values())

    def raw(self, topics: Sequence[str]) -> Iterator[tuple[str, str, int, bytes]]:
        """Yield ``(topic, msgtype, log_ns, cdr bytes)`` of ``topics`` in log-time order."""
        conns = [c for c in self.reader.connections if c.topic in set(topics)]
        if not conns:
            return
        for conn in conns:
            self._check_definition(conn.topic, conn.msgtype, conn.digest)
        it = self._merged(conns)
        while True:
            try:
                conn, log_ns, data = next(it)
            except StopIteration:
                return
            except Exception as err:  # noqa: BLE001 - storage backends raise many kinds
                raise BagError(f'bag {self.path} is truncated or corrupt while reading '
                               f'{sorted(topics)}: {type(err).__name__}: {err}') from err
            log_ns = int(log_ns)
            if log_ns > INT64_MAX:
                raise BagError(f'{conn.topic} in bag {self.path}: log time {log_ns} ns is beyond '
                               f'the int64 nanoseconds of ROS 2 time (at most {INT64_MAX}); '
                               'the bag is damaged: repair its log times or record it again.')
            yield conn.topic, conn.msgtype, log_ns, data

    def _merged(self, conns: list[Any]) -> Iterator[tuple[Any, int, bytes]]:
        """The messages of ``conns`` in log-time order across the files of a split bag.

        rosbags reads a folder's files one after the other in ``metadata.yaml``'s order; files
        listed out of time order (a hand-made or re-indexed ``metadata.yaml``) or overlapping
        came out with the stamps going back, and the converter kept only the last file's
        messages. Each file's reader (its own connection mapping and decompression) is merged
        by log time; one file, or a single storage file, is read as it is.
        """
        storage: Any = getattr(self.reader, 'storage', None)
        parts = getattr(storage, 'storages', None)
        if not isinstance(parts, list) or len(parts) < 2:
            return iter(self.reader.messages(connections=conns))
        views = []
        for part in parts:
            view = copy.copy(storage)
            view.storages = [part]
            views.append(view.messages(conns, None, None))
        return heapq.merge(*views, key=lambda m: m[1])

    def _check_definition(self, topic: str, msgtype: str, digest: str | None) -> None:
        """Refuse a topic recorded with another definition of its type than the standard one.

        Bags since Iron record each type's hash (``type_description_hash``, RIHS01); a
        message of the same name but another definition would be decoded field by field
        with the wrong layout, so it is refused here instead of being misread.
        """
        if not digest or not str(digest).startswith('RIHS01_') or msgtype not in SUPPORTED_TYPES:
            return
        want = self._ts.hash_rihs01(msgtype)
        if digest != want:
            raise BagError(f'{topic} in bag {self.path} was recorded with another definition '
                           f'of {msgtype} than the standard ROS 2 one (type hash '
                           f'{digest[:20]}..., expected {want[:20]}...); soft_rom decodes the '
                           'standard definitions only.')

    def messages(self, topics: Sequence[str]) -> Iterator[BagMessage]:
        """Yield decoded :class:`BagMessage` of ``topics`` in log-time order."""
        for topic, msgtype, log_ns, data in self.raw(topics):
            fast = FAST.get(msgtype)
            got = None if fast is None else fast(data)
            if got is not None:
                yield BagMessage(topic, msgtype, log_ns, got[0], got[1], (), raw_frame_id(data))
                continue
            try:
                msg = self._ts.deserialize_cdr(data, msgtype)
            except Exception as err:  # noqa: BLE001 - corrupt CDR raises many kinds
                if bytes(data[:4]) == _ZSTD_MAGIC:
                    raise BagError(
                        f'{topic} in bag {self.path}: the messages are zstd-compressed (recorded '
                        'with --compression-mode message) but the bag does not say so (no '
                        f'metadata.yaml?): recreate its metadata with `ros2 bag reindex '
                        f'{self.path}`.') from err
                raise BagError(f'{topic} at log time {log_ns * 1e-9:.9f} s: cannot decode '
                               f'{msgtype} ({type(err).__name__}: {err}); the message is '
                               'corrupt or was recorded with another definition of its '
                               'type.') from err
            stamp, value, layout = decode(msgtype, msg)
            frame = getattr(getattr(msg, 'header', None), 'frame_id', None)
            yield BagMessage(topic, msgtype, log_ns, stamp, value, layout,
                             None if frame is None else str(frame))


def describe_bag(path: str | Path) -> dict[str, Any]:
    """Summary of a bag: storage, duration, and per topic type, count, rate (Hz).

    Returns
    -------
    dict
        ``{'path', 'storage', 'start_s', 'end_s', 'duration_s', 'message_count',
        'topics': {topic: {'type', 'count', 'rate_hz'}}}``.
    """
    with BagReader(path) as bag:
        start, end = bag.start_ns, bag.end_ns
        dur = (end - start) * 1e-9
        topics = {}
        for name, (msgtype, count) in sorted(bag.topics.items()):
            rate = (count - 1) / dur if dur > 0 and count > 1 else float('nan')
            topics[name] = {'type': msgtype, 'count': count, 'rate_hz': rate}
        return {'path': str(path), 'storage': bag.storage, 'start_s': start * 1e-9,
                'end_s': end * 1e-9, 'duration_s': dur, 'message_count': bag.message_count,
                'topics': topics}
