"""Message conversions and node parameters, tested without ROS (plain attribute objects)."""

from __future__ import annotations

import array
from dataclasses import fields
from pathlib import Path
from types import SimpleNamespace as NS

import numpy as np
import pytest

from soft_rom.errors import ConfigError, DimensionError
from soft_rom.predictor import Health, Level, PredictorConfig
from soft_rom.predictor.conversions import (
    array_to_data,
    check_components,
    data_to_array,
    health_key_values,
    outputs_to_points,
    points_to_outputs,
    poses_to_points,
    sec_to_stamp,
    set_points,
    stamp_to_sec,
)
from soft_rom.predictor.params import load_params_file, PARAMS, predictor_config

ROOT = Path(__file__).resolve().parents[2]


def test_outputs_points_round_trip() -> None:
    y = np.arange(40, dtype=float)
    pts = outputs_to_points(y, 'xz', fill=-1.0)
    assert pts.shape == (20, 3)
    np.testing.assert_array_equal(pts[:, 0], y[:20])
    np.testing.assert_array_equal(pts[:, 2], y[20:])
    np.testing.assert_array_equal(pts[:, 1], -1.0)
    np.testing.assert_array_equal(points_to_outputs(pts, 'xz'), y)
    out = np.empty((20, 3))
    assert outputs_to_points(y, 'xz', out=out) is out
    xyz = np.arange(30.0)
    np.testing.assert_array_equal(points_to_outputs(outputs_to_points(xyz, 'xyz'), 'xyz'), xyz)
    assert check_components('xz', 40) == 20
    with pytest.raises(ConfigError):
        check_components('xz', 41)
    with pytest.raises(ConfigError):
        check_components('xw', 40)
    with pytest.raises(DimensionError):
        points_to_outputs(np.zeros((3, 2)))


def test_pose_and_point_objects() -> None:
    pts = np.random.default_rng(0).standard_normal((7, 3))
    poses = [NS(position=NS(x=a, y=b, z=c)) for a, b, c in pts]
    np.testing.assert_array_equal(poses_to_points(poses), pts)
    assert poses_to_points([]).shape == (0, 3)
    targets = [NS(x=0.0, y=0.0, z=0.0) for _ in range(7)]
    set_points(targets, pts)
    assert all(type(t.x) is float for t in targets)
    np.testing.assert_array_equal([[t.x, t.y, t.z] for t in targets], pts)


def test_array_data_and_stamps() -> None:
    y = np.linspace(0, 1, 9)
    data = array_to_data(y)
    assert isinstance(data, array.array) and data.typecode == 'd'
    np.testing.assert_array_equal(data_to_array(data), y)
    np.testing.assert_array_equal(data_to_array(array.array('f', [1.5, 2.5])), [1.5, 2.5])
    np.testing.assert_array_equal(data_to_array([1, 2]), [1.0, 2.0])
    sec, nsec = sec_to_stamp(12.3456789)
    assert (sec, nsec) == (12, 345678900)
    assert stamp_to_sec(NS(sec=sec, nanosec=nsec)) == pytest.approx(12.3456789, abs=1e-9)
    assert sec_to_stamp(0.9999999999) == (1, 0)


def test_health_key_values_are_strings() -> None:
    h = Health(Level.WARN, 'x', ('x',), {'error_deviation': float('nan'), 'steps': 3,
                                         'e': 0.123456789})
    kv = dict(health_key_values(h))
    assert kv == {'error_deviation': 'nan', 'steps': '3', 'e': '0.123457'}


def test_params_file_matches_declarations_and_core_defaults() -> None:
    from soft_rom.predictor.params import render_params_file

    path = ROOT / 'config' / 'predictor.yaml'
    assert path.read_text(encoding='utf-8') == render_params_file()
    values = load_params_file(path)
    names = {p.name for p in PARAMS}
    assert set(values) == names
    for p in PARAMS:
        assert values[p.name] == p.default, p.name
        assert type(values[p.name]) is type(p.default), p.name
        if p.range is not None:
            assert p.range[0] <= p.default <= p.range[1]
    cfg = predictor_config(values)
    assert cfg == PredictorConfig()
    assert {f.name for f in fields(PredictorConfig)} <= names


def test_params_file_errors(tmp_path) -> None:
    bad = tmp_path / 'p.yaml'
    bad.write_text('soft_rom_predictor:\n  ros__parameters:\n    rate: 3\n')
    with pytest.raises(ConfigError, match='unknown'):
        load_params_file(bad)
    bad.write_text('/**:\n  ros__parameters:\n    kalman: true\n    use_sim_time: true\n')
    assert predictor_config(load_params_file(bad)).kalman is True
    bad.write_text('a: [\n')
    with pytest.raises(ConfigError):
        load_params_file(bad)


def test_params_file_with_node_only_parameters_serves_replay(tmp_path) -> None:
    # one params file for the node and for `soft-rom replay --config`: the node-only
    # parameters (executor, lifecycle, hardware_id) are accepted and ignored by replay
    from soft_rom.errors import ConfigError
    from soft_rom.predictor.params import load_params_file, predictor_config

    path = tmp_path / 'p.yaml'
    path.write_text("/**:\n  ros__parameters:\n    lifecycle: true\n    executor: 'events'\n"
                    "    hardware_id: 'eel-1'\n    kalman: true\n    use_sim_time: true\n")
    values = load_params_file(path)
    assert predictor_config(values).kalman is True
    path.write_text('/**:\n  ros__parameters:\n    lifecycel: true\n')
    with pytest.raises(ConfigError, match='lifecycel'):
        load_params_file(path)
