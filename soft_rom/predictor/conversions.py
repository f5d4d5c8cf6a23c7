"""Array <-> message-field conversions shared by the node and ``soft-rom replay``.

Stamps: ``builtin_interfaces/Time`` is ``(sec, nanosec)``; the predictor takes int
nanoseconds (:func:`stamp_to_ns`, :func:`ns_to_stamp`), exact at any epoch.

Nothing here imports rclpy or a message package: the functions read and write attributes
of whatever message objects they are given (rclpy messages in the node, rosbags
dataclasses in :mod:`soft_rom.bags.replay_io`, plain ``SimpleNamespace`` in tests), so they
are tested and timed without ROS.

Output layout: the model's output vector is *component-major*,
``y = [x_1..x_N, z_1..z_N]`` for components ``'xz'`` (the paper's 40 outputs for 20
centerline points); the components not predicted are filled with a constant.
"""

from __future__ import annotations

import array
from collections.abc import Iterable, Sequence
import json
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.errors import ConfigError, DimensionError

__all__ = [
    'array_to_data',
    'check_components',
    'data_to_array',
    'health_key_values',
    'model_info_json',
    'ns_to_stamp',
    'outputs_to_points',
    'points_to_outputs',
    'poses_to_points',
    'sec_to_stamp',
    'set_points',
    'stamp_to_ns',
    'stamp_to_sec',
]

Array = NDArray[np.float64]
_AXES = {'x': 0, 'y': 1, 'z': 2}


def stamp_to_sec(stamp: Any) -> float:
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) to float seconds."""
    return stamp.sec + stamp.nanosec * 1e-9


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (``sec``, ``nanosec``) to int nanoseconds (exact)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(t_ns: int) -> tuple[int, int]:
    """Int nanoseconds to ``(sec, nanosec)`` with ``0 <= nanosec < 1e9``."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return int(sec), int(nsec)


def sec_to_stamp(t: float) -> tuple[int, int]:
    """Float seconds to ``(sec, nanosec)`` with ``0 <= nanosec < 1e9`` (rounded to 1 ns)."""
    ns = int(round(t * 1e9))
    sec, nsec = divmod(ns, 1_000_000_000)
    return int(sec), int(nsec)


def check_components(components: str, n_outputs: int) -> int:
    """Validate an output layout and return the number of points ``N``."""
    if not components or any(c not in _AXES for c in components) or len(
            set(components)) != len(components):
        raise ConfigError(f'output components must be distinct letters of "xyz", e.g. "xz"; '
                          f'got {components!r}.')
    if n_outputs % len(components):
        raise ConfigError(f'{n_outputs} outputs cannot be split into {len(components)} '
                          f'components {components!r} (component-major layout).')
    return n_outputs // len(components)


def outputs_to_points(y: ArrayLike, components: str = 'xz', fill: float = 0.0,
                      out: Array | None = None) -> Array:
    """Output vector (component-major) to centerline points.

    Parameters
    ----------
    y : ndarray, shape (p,)
    components : str
        Which coordinates ``y`` holds, in order (``'xz'``: ``p = 2 N``).
    fill : float
        Value of the coordinates not in ``components``.
    out : ndarray, shape (N, 3), optional
        Written in place (no allocation).

    Returns
    -------
    points : ndarray, shape (N, 3)
    """
    y = np.asarray(y, dtype=np.float64)
    c = len(components)
    n = y.size // c
    if n * c != y.size:
        raise DimensionError(f'{y.size} outputs do not split into components {components!r}.')
    pts = np.empty((n, 3)) if out is None else out
    if len(components) < 3:
        pts[:] = fill
    blocks = y.reshape(c, n)
    for i, comp in enumerate(components):
        pts[:, _AXES[comp]] = blocks[i]
    return pts


def points_to_outputs(points: ArrayLike, components: str = 'xz') -> Array:
    """Centerline points ``(N, 3)`` to the component-major output vector ``(len(c) N,)``."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise DimensionError(f'points must have shape (N, 3); got {pts.shape}.')
    idx = [_AXES[c] for c in components]
    return np.ascontiguousarray(pts[:, idx].T).reshape(-1)


def poses_to_points(poses: Sequence[Any]) -> Array:
    """``geometry_msgs/Pose`` list (``PoseArray.poses``) to points, shape (N, 3)."""
    n = len(poses)
    flat = np.fromiter((v for p in poses for v in (p.position.x, p.position.y, p.position.z)),
                       dtype=np.float64, count=3 * n)
    return flat.reshape(n, 3)


def set_points(targets: Iterable[Any], points: Array) -> None:
    """Write ``points (N, 3)`` into ``x, y, z`` of ``N`` existing objects, in place.

    Used on preallocated ``Pose.position`` / ``Point`` objects, so that publishing a
    centerline builds no messages; ``tolist`` gives Python floats (the fastest type for
    rclpy's checked setters).
    """
    for obj, (x, y, z) in zip(targets, points.tolist()):
        obj.x = x
        obj.y = y
        obj.z = z


def data_to_array(data: Any) -> Array:
    """``Float64MultiArray.data`` / ``Float32MultiArray.data`` to a float64 vector.

    rclpy gives an ``array.array`` (read through the buffer protocol, no loop); rosbags
    gives a numpy array; lists work too.
    """
    return np.asarray(data, dtype=np.float64).reshape(-1)


def array_to_data(values: Array) -> array.array:
    """A float64 vector to ``array.array('d')``, the type rclpy stores without checking."""
    out = array.array('d')
    out.frombytes(np.ascontiguousarray(values, dtype=np.float64).tobytes())
    return out


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return 'nan' if math.isnan(value) else f'{value:.6g}'
    return str(value)


def health_key_values(health: Any) -> list[tuple[str, str]]:
    """``(key, value)`` strings of a :class:`soft_rom.predictor.Health` for diagnostics."""
    return [(str(k), _fmt(v)) for k, v in health.values.items()]


def model_info_json(info: dict[str, Any]) -> str:
    """The latched ``~/model_info`` payload (``std_msgs/String``): compact sorted JSON."""
    return json.dumps(info, sort_keys=True, separators=(',', ':'), allow_nan=True)
