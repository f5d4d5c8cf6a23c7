"""Tests of ``soft-rom info`` (bags, training sets, model files) and ``soft-rom convert``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from soft_rom.bags import EpisodeBagWriter
from soft_rom.cli import main
from soft_rom.dataset import TrainingSet
from soft_rom.models import DiscreteModel


@pytest.fixture()
def bag(tmp_path):
    path = tmp_path / 'ep1'
    with EpisodeBagWriter(path, storage='mcap', n_nodes=2) as w:
        for j in range(11):
            w.write(0.5 + 0.01 * j, np.full(6, float(j)), np.zeros((20, 3)),
                    np.zeros((2, 3)))
    return path


def test_info_bag_text_and_json(bag, capsys):
    assert main(['info', str(bag)]) == 0
    out = capsys.readouterr().out
    assert 'bag ' in out and '(mcap): 88 messages, 0.100 s' in out
    assert '/soft_robot/state' in out and 'std_msgs/msg/Float64MultiArray' in out
    assert main(['info', '--json', str(bag)]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d['kind'] == 'bag' and d['duration_s'] == pytest.approx(0.1, abs=1e-12)
    assert d['topics']['/soft_robot/centerline']['count'] == 11
    assert d['topics']['/soft_robot/centerline']['rate_hz'] == pytest.approx(100.0, rel=1e-9)


def test_convert_cli_then_info_trainingset(bag, tmp_path, capsys):
    out = tmp_path / 'train.zarr'
    assert main(['convert', str(bag), '-o', str(out), '--quiet']) == 0
    assert 'wrote' in capsys.readouterr().out
    assert main(['convert', str(bag), '-o', str(out), '--quiet']) == 2      # exists
    assert 'exists already' in capsys.readouterr().err
    assert main(['convert', str(bag), '-o', str(out), '--overwrite', '--no-state',
                 '--dt', '0.02', '--verbose']) == 0
    captured = capsys.readouterr()
    assert 'output /soft_robot/centerline [PoseArray]: read 11, used 11' in captured.err
    assert 'no states' in captured.out
    assert main(['info', '--json', str(out)]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d['kind'] == 'trainingset' and d['n_states'] is None
    assert d['episodes']['ep1']['n_samples'] == 6
    assert d['episodes']['ep1']['dt_mean'] == pytest.approx(0.02, abs=1e-12)
    t0 = d['episodes']['ep1']['t0_ns']
    assert isinstance(t0, int) and t0 == TrainingSet.open(out).t0_ns('ep1')
    assert main(['info', str(out)]) == 0
    text = capsys.readouterr().out
    assert 'inputs  (m = 6): p1 [Pa]' in text and f'from t0 = {t0} ns' in text


def test_info_model_file(tmp_path, capsys):
    A = np.diag([0.5, 0.9])
    model = DiscreteModel(A, np.ones((2, 1)), np.eye(2), np.zeros((2, 1)), dt=0.001,
                          method='dmdc', y_ref=[1.0, 2.0], metadata={'r_source': 'test'})
    path = model.save(tmp_path / 'm.npz')
    assert main(['info', str(path)]) == 0
    out = capsys.readouterr().out
    assert 'method dmdc' in out and 'r = 2' in out
    assert 'stability margin 1 - max|eig(A)| = 1.000e-01 (stable)' in out
    assert main(['info', '--json', str(path)]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d['kind'] == 'model' and d['stability_margin'] == pytest.approx(0.1)
    assert d['metadata']['r_source'] == 'test'


def test_info_unknown_path(tmp_path, capsys):
    (tmp_path / 'x.txt').write_text('hello')
    assert main(['info', str(tmp_path / 'x.txt')]) == 2
    assert 'neither a ROS 2 bag' in capsys.readouterr().err
    assert main(['info', str(tmp_path / 'missing')]) == 2
