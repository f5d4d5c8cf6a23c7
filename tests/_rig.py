"""A lab rig, recorded the way a live ROS 2 system records it (for the converter tests).

The "robot" is a known damped spring chain ``q'' + C q' + K q = B u`` (6 degrees of
freedom, modes 0.6-2.8 Hz) driven by six pressure chambers. Its centerline (10 points, x and
z) is a fixed linear image of ``q`` around a rest shape. The recording has

* epoch stamps (``T0_NS`` ~ 1.7e18 ns), written as integers;
* six chamber sensors, each on its own 500 Hz clock (own phase, +-50 ppm rate error,
  +-100 us uniform jitter), ``sensor_msgs/FluidPressure``;
* a motion-capture centerline at 120 Hz (+-0.3 ms jitter, about 1 % of frames lost, 0.5 mm
  Gaussian noise per coordinate), ``geometry_msgs/PoseArray``;
* log times a little after the stamps (transport latency), no state topic.

The chain is integrated on a 0.2 ms grid with the exact discretization for inputs held over
each step (commands change only on that grid); a camera sample is the linear interpolation
of that fine trajectory at its stamp.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores
import scipy.linalg as sla

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
T0_NS = 1_700_000_000_123_456_789
H_FINE = 0.0002
N_DOF, M, N_POINTS = 6, 6, 10


@dataclass
class Robot:
    """The true system and its output map."""

    K: np.ndarray
    C: np.ndarray
    B: np.ndarray
    E: np.ndarray          # (2 * N_POINTS, N_DOF): [x_1..x_N, z_1..z_N] deviations
    y_rest: np.ndarray     # (2 * N_POINTS,)

    @classmethod
    def make(cls, seed: int = 7) -> Robot:
        rng = np.random.default_rng(seed)
        K = 80.0 * (2 * np.eye(N_DOF) - np.eye(N_DOF, k=1) - np.eye(N_DOF, k=-1))
        C = 0.02 * K + 0.5 * np.eye(N_DOF)
        B = 5e-6 * np.eye(N_DOF, M)
        E = rng.standard_normal((2 * N_POINTS, N_DOF)) / np.sqrt(N_DOF)
        s = np.linspace(0.0, 0.3, N_POINTS)
        y_rest = np.concatenate([s, np.zeros(N_POINTS)])
        return cls(K, C, B, E, y_rest)

    def discrete(self, h: float) -> tuple[np.ndarray, np.ndarray]:
        n, m = N_DOF, M
        Ac = np.block([[np.zeros((n, n)), np.eye(n)], [-self.K, -self.C]])
        Bc = np.vstack([np.zeros((n, m)), self.B])
        Mx = np.zeros((2 * n + m,) * 2)
        Mx[:2 * n, :2 * n], Mx[:2 * n, 2 * n:] = Ac * h, Bc * h
        F = sla.expm(Mx)
        return F[:2 * n, :2 * n], F[:2 * n, 2 * n:]

    def run(self, duration: float, seed: int, hold: float = 0.25,
            amplitude: float = 5e4) -> tuple[np.ndarray, np.ndarray]:
        """Commands ``(M, k_fine)`` and positions ``q (N_DOF, k_fine)`` on the fine grid."""
        rng = np.random.default_rng(seed)
        k = int(round(duration / H_FINE)) + 1
        per = int(round(hold / H_FINE))
        levels = rng.uniform(0, amplitude, (M, k // per + 1))
        U = np.repeat(levels, per, axis=1)[:, :k]
        A, Bd = self.discrete(H_FINE)
        x, Q = np.zeros(2 * N_DOF), np.empty((N_DOF, k))
        for j in range(k):
            Q[:, j] = x[:N_DOF]
            x = A @ x + Bd @ U[:, j]
        return U, Q

    def outputs(self, q: np.ndarray) -> np.ndarray:
        """Absolute centerline outputs ``(2 N_POINTS, k)``."""
        return self.y_rest[:, None] + self.E @ q


def _header(ns: int) -> object:
    stamp = T['builtin_interfaces/msg/Time'](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    return T['std_msgs/msg/Header'](stamp=stamp, frame_id='world')


def _pose_array(ns: int, pts: np.ndarray) -> object:
    Pose, Point = T['geometry_msgs/msg/Pose'], T['geometry_msgs/msg/Point']
    ident = T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)
    poses = [Pose(position=Point(x=float(a), y=float(b), z=float(c)), orientation=ident)
             for a, b, c in pts.tolist()]
    return T['geometry_msgs/msg/PoseArray'](header=_header(ns), poses=poses)


def write_messages(path: Path, messages: list[tuple[int, str, str, object]],
                   storage: str = 'mcap', compression: str = 'none') -> Path:
    """Write ``(log_ns, topic, msgtype, msg)`` through rosbags, in log-time order.

    ``compression``: rosbag2's zstd compression mode (``'file'``: ``*.mcap.zstd`` /
    ``*.db3.zstd``, as ``ros2 bag record --compression-mode file`` writes; ``'message'``;
    ``'none'``).
    """
    plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
    writer = Writer(path, version=9, storage_plugin=plugin)
    if compression != 'none':
        writer.set_compression(CompressionMode[compression.upper()], CompressionFormat.ZSTD)
    writer.open()
    conns: dict[str, object] = {}
    try:
        for log_ns, topic, msgtype, msg in sorted(messages, key=lambda x: x[0]):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=TS)
            writer.write(conns[topic], int(log_ns), TS.serialize_cdr(msg, msgtype))
    finally:
        writer.close()
    return path


@dataclass
class Recording:
    """What was written, for checks: true positions at the camera stamps, etc."""

    path: Path
    cam_ns: np.ndarray          # stamps of the frames written
    lost: int                   # frames lost
    q_true: np.ndarray          # (N_DOF, frames) true positions at cam_ns


def record(robot: Robot, path: Path, *, duration: float, seed: int, t0_ns: int = T0_NS,
           storage: str = 'mcap', noise: float = 5e-4, lost: float = 0.01,
           compression: str = 'none') -> Recording:
    """Run the robot and record it as the rig does (module docstring)."""
    rng = np.random.default_rng(seed + 1000)
    U, Q = robot.run(duration, seed)
    fine_ns = np.round(np.arange(Q.shape[1]) * H_FINE * 1e9).astype(np.int64)
    msgs: list[tuple[int, str, str, object]] = []
    FP = T['sensor_msgs/msg/FluidPressure']
    for i in range(M):                                     # six independent chamber clocks
        phase = rng.uniform(0, 2e-3)
        rate = 1 + rng.uniform(-50e-6, 50e-6)
        k = int((duration - 0.01) / 2e-3)
        rel = phase + np.arange(k) * 2e-3 * rate + rng.uniform(-1e-4, 1e-4, k)
        rel_ns = np.round(rel * 1e9).astype(np.int64)
        idx = np.searchsorted(fine_ns, rel_ns, side='right') - 1
        for ns, j in zip(rel_ns.tolist(), idx.tolist()):
            stamp = t0_ns + ns
            msgs.append((stamp + int(rng.integers(50_000, 400_000)),
                         f'/soft_robot/pressure/chamber_{i + 1}', FP.__msgtype__,
                         FP(header=_header(stamp), fluid_pressure=float(U[i, j]), variance=0.0)))
    period = 1 / 120
    k = int((duration - 0.02) / period)
    rel = 0.004 + np.arange(k) * period + rng.uniform(-3e-4, 3e-4, k)
    keep = rng.uniform(size=k) >= lost
    rel_ns = np.round(rel * 1e9).astype(np.int64)[keep]
    pos = rel_ns / (H_FINE * 1e9)
    j0 = np.floor(pos).astype(int)
    a = pos - j0
    q_cam = Q[:, j0] * (1 - a) + Q[:, j0 + 1] * a
    Y = robot.outputs(q_cam) + noise * rng.standard_normal((2 * N_POINTS, q_cam.shape[1]))
    for c in range(q_cam.shape[1]):
        pts = np.stack([Y[:N_POINTS, c], np.zeros(N_POINTS), Y[N_POINTS:, c]], axis=1)
        stamp = t0_ns + int(rel_ns[c])
        msgs.append((stamp + int(rng.integers(1_000_000, 3_000_000)), '/soft_robot/centerline',
                     'geometry_msgs/msg/PoseArray', _pose_array(stamp, pts)))
    write_messages(path, msgs, storage, compression)
    return Recording(path, t0_ns + rel_ns, int(np.sum(~keep)), q_cam)
