"""Fast paths: small stamped messages parsed straight from little-endian CDR.

rosbags' generic deserialiser builds Python objects field by field (tens of microseconds per
message); the converter reads 6 pressures and a 20-point PoseArray per sample, so these two
types are parsed with struct/numpy. Anything unexpected returns None and the generic path
(which also reports corrupt messages) is used. Offsets follow the CDR rules: alignment is
relative to the byte after the 4-byte encapsulation header.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ['FAST', 'raw_frame_id']

_HDR = struct.Struct('<iII')          # stamp.sec, stamp.nanosec, len(frame_id) incl. NUL


def _fast_header(raw: bytes | memoryview) -> tuple[int, int] | None:
    if len(raw) < 16 or raw[0] != 0 or raw[1] != 1:      # CDR_LE only
        return None
    sec, nsec, n = _HDR.unpack_from(raw, 4)
    pos = 12 + n                                         # after the frame_id string
    if n == 0 or pos > len(raw) - 4 or nsec >= 1_000_000_000:
        return None
    return sec * 1_000_000_000 + nsec, pos


def _fast_fluid_pressure(raw: bytes | memoryview) -> tuple[int, NDArray[Any]] | None:
    head = _fast_header(raw)
    if head is None:
        return None
    stamp, pos = head
    pos = (pos + 7) & ~7                                 # float64 alignment
    if 4 + pos + 16 != len(raw):
        return None
    return stamp, np.frombuffer(raw, dtype='<f8', count=1, offset=4 + pos).astype(np.float64)


def _fast_pose_array(raw: bytes | memoryview) -> tuple[int, NDArray[Any]] | None:
    head = _fast_header(raw)
    if head is None:
        return None
    stamp, pos = head
    pos = (pos + 3) & ~3
    (count,) = struct.unpack_from('<I', raw, 4 + pos)
    if count == 0:                                       # no padding after an empty sequence
        return (stamp, np.empty((0, 3))) if 4 + pos + 4 == len(raw) else None
    pos = (pos + 4 + 7) & ~7
    if 4 + pos + 56 * count != len(raw):
        return None
    poses = np.frombuffer(raw, dtype='<f8', count=7 * count, offset=4 + pos).reshape(count, 7)
    return stamp, poses[:, :3].astype(np.float64)


FAST = {'sensor_msgs/msg/FluidPressure': _fast_fluid_pressure,
         'geometry_msgs/msg/PoseArray': _fast_pose_array}



def raw_frame_id(raw: bytes | memoryview) -> str:
    """``header.frame_id`` of a message a fast path accepted (its header is its first field)."""
    (n,) = struct.unpack_from('<I', raw, 12)
    return bytes(raw[16:15 + n]).decode('utf-8', 'replace')
