"""Test helper: an episode written as the inputs of the bag contract (rosbags, both storages)."""

from __future__ import annotations

from collections.abc import Callable
import os
from pathlib import Path
from typing import Any

import numpy as np

from soft_rom.bags.prediction_writer import (
    _float64_array,
    _header,
    _open_writer,
    _pose_array,
    _T,
    _TS,
)
from soft_rom.data import Episode
from soft_rom.errors import BagError
from soft_rom.models import SecondOrderModel
from soft_rom.predictor.conversions import check_components, outputs_to_points


def write_input_bag(path: str | os.PathLike[str], episode: Episode, *, storage: str = 'mcap',
                    per_chamber: bool = True,
                    chamber_topics: list[str] | None = None,
                    array_topic: str = '/soft_robot/pressures',
                    centerline_topic: str | None = '/soft_robot/centerline',
                    components: str = 'xz', frame_id: str = 'world',
                    overwrite: bool = False, t0_ns: int = 0, output_every: int = 1,
                    restamp: Callable[[int, int], int] | None = None) -> Path:
    """Write an episode as the inputs of the bag contract (pressures, measured centerline).

    ``output_every``: the centerline on every that-many samples only (a slower camera).

    Pressures go one ``sensor_msgs/FluidPressure`` per chamber (stamped) or one
    ``std_msgs/Float64MultiArray`` per sample (bag time only); the outputs as a stamped
    ``geometry_msgs/PoseArray`` (component-major layout ``components``). Stamps are
    ``t0_ns + round(t * 1e9)`` (int ns; epoch stamps are exact), also the log times;
    ``restamp(j, ns)`` gives sample ``j`` another header stamp (a sensor clock of its own).
    """
    m = episode.U.shape[0]
    topics = chamber_topics or [f'/soft_robot/pressure/chamber_{i + 1}' for i in range(m)]
    if per_chamber and len(topics) != m:
        raise BagError(f'{m} inputs but {len(topics)} chamber topics.')
    writer = _open_writer(path, storage, overwrite)
    try:
        FP = _T['sensor_msgs/msg/FluidPressure']
        if per_chamber:
            conns = [writer.add_connection(tp, FP.__msgtype__, typestore=_TS) for tp in topics]
        else:
            arr_conn = writer.add_connection(array_topic, 'std_msgs/msg/Float64MultiArray',
                                             typestore=_TS)
        c_conn = None
        if centerline_topic:
            check_components(components, episode.Y.shape[0])
            c_conn = writer.add_connection(centerline_topic, 'geometry_msgs/msg/PoseArray',
                                           typestore=_TS)
        for j, t in enumerate(episode.t.tolist()):
            ns = int(t0_ns) + int(round(t * 1e9))
            stamp = ns if restamp is None else int(restamp(j, ns))
            if per_chamber:
                for i, conn in enumerate(conns):
                    msg = FP(header=_header(stamp, ''), fluid_pressure=float(episode.U[i, j]),
                             variance=0.0)
                    writer.write(conn, ns, _TS.serialize_cdr(msg, FP.__msgtype__))
            else:
                msg = _float64_array(episode.U[:, j], 'chambers')
                writer.write(arr_conn, ns, _TS.serialize_cdr(msg, msg.__msgtype__))
            if c_conn is not None and j % output_every == 0:
                pts = outputs_to_points(episode.Y[:, j], components)
                writer.write(c_conn, ns, _TS.serialize_cdr(_pose_array(stamp, frame_id, pts),
                                                           'geometry_msgs/msg/PoseArray'))
    finally:
        writer.close()
    return Path(path)


N_POINTS = 5


def small_model() -> SecondOrderModel:
    """A stable second-order model, 3 inputs, 5 centerline points (xz)."""
    rng = np.random.default_rng(7)
    r, m, p = 4, 3, 2 * N_POINTS
    M = rng.standard_normal((r, r))
    K = (M @ M.T / r + 4.0 * np.eye(r)) * 100.0
    y_ref = np.concatenate([np.linspace(0.0, 0.4, N_POINTS), np.zeros(N_POINTS)])
    return SecondOrderModel(K, 0.5 * np.eye(r) + 0.01 * K, rng.standard_normal((r, m)),
                            0.01 * rng.standard_normal((p, r)), dt=1e-3, y_ref=y_ref)


def small_episode(model: SecondOrderModel, k: int = 120) -> Episode:
    """``k`` samples of held random inputs and the model's exact outputs, from t = 2 s."""
    rng = np.random.default_rng(8)
    U = np.repeat(rng.standard_normal((model.n_inputs, k // 10)), 10, axis=1)
    t = 2.0 + np.arange(k) * model.dt
    return Episode(t=t, U=U, Y=model.simulate(U), name='ep')


def one_line_error(capsys: Any, *words: str) -> str:
    """The CLI's stderr (from pytest's ``capsys``): one line, no traceback, with ``words``."""
    err = capsys.readouterr().err
    assert 'Traceback' not in err and len(err.strip().splitlines()) == 1, err
    for w in words:
        assert w in err, err
    return err
