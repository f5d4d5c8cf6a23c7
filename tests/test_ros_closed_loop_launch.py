"""``closed_loop.launch.py`` (no ROS needed): run against recording stand-ins of ``launch``."""

from __future__ import annotations

import importlib.util
from pathlib import Path
import py_compile
import sys
import types

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / 'launch' / 'closed_loop.launch.py'


class _Recorder:
    def __init__(self, *args, **kwargs) -> None:
        self.args, self.kwargs = args, kwargs


class _Config:
    def __init__(self, name: str) -> None:
        self.name = name

    def perform(self, context) -> str:
        return context[self.name]


class _Share:
    def __init__(self, package: str) -> None:
        self.package = package

    def perform(self, context) -> str:
        return '/share/soft_rom'


@pytest.fixture
def launch_module(monkeypatch):
    fakes = {
        'launch': types.SimpleNamespace(LaunchDescription=_Recorder),
        'launch.actions': types.SimpleNamespace(DeclareLaunchArgument=_Recorder,
                                                OpaqueFunction=_Recorder),
        'launch.substitutions': types.SimpleNamespace(LaunchConfiguration=_Config),
        'launch_ros': types.SimpleNamespace(),
        'launch_ros.actions': types.SimpleNamespace(Node=_Recorder),
        'launch_ros.substitutions': types.SimpleNamespace(FindPackageShare=_Share),
    }
    for name, mod in fakes.items():
        monkeypatch.setitem(sys.modules, name, mod)
    spec = importlib.util.spec_from_file_location('closed_loop_launch', LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_starts_plant_predictor_controller_in_sim_time(launch_module) -> None:
    py_compile.compile(str(LAUNCH), doraise=True)
    desc = launch_module.generate_launch_description()
    names = [a.args[0] for a in desc.args[0] if a.args and isinstance(a.args[0], str)]
    assert names == ['model_path', 'reference', 'duration_s', 'record_path', 'rviz',
                     'input_mode']
    ctx = {'model_path': '/m.npz', 'reference': 'wave:f=1', 'duration_s': '2',
           'record_path': '/r.npz', 'rviz': 'false', 'input_mode': 'per_chamber'}
    plant, predictor, controller = launch_module._actions(ctx)
    assert [n.kwargs['executable'] for n in (plant, predictor, controller)] == [
        'plant', 'predictor', 'controller']
    assert plant.kwargs['parameters'] == [{'duration_s': 2.0, 'record_path': '/r.npz',
                                           'wait_for_subscribers': 1,
                                           'input_mode': 'per_chamber'}]
    assert predictor.kwargs['parameters'][0]['use_sim_time'] is True
    assert predictor.kwargs['parameters'][0]['kalman'] is False
    assert predictor.kwargs['parameters'][0]['input_qos'] == 'reliable'
    c = controller.kwargs['parameters'][0]
    assert c['use_sim_time'] and c['reference'] == 'wave:f=1' and c['model_path'] == '/m.npz'
    assert c['state_topic'] == '/soft_rom_predictor/state'
    array = launch_module._actions(dict(ctx, input_mode='array'))
    assert [n.kwargs['parameters'][0]['input_mode'] for n in array] == ['array'] * 3
    rviz = launch_module._actions(dict(ctx, rviz='true'))[-1]
    assert rviz.kwargs['executable'] == 'rviz2'
    assert rviz.kwargs['arguments'][1] == '/share/soft_rom/config/predictor.rviz'
