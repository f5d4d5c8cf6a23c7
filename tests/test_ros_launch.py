"""The launch file and the RViz configuration (no ROS needed).

``launch`` and ``launch_ros`` are not on PyPI, so ``ros2 launch`` cannot run here. What is
checked: the launch file compiles; its arguments are the documented ones; run against
minimal stand-ins of the ``launch`` API (recording what it is given), ``rviz:=true`` adds an
``rviz2`` node with the installed ``predictor.rviz`` (topics renamed for another node
name, fixed frame from ``frame_id``) and ``rviz:=false`` does not; the overrides reach the
predictor node. The RViz file is valid YAML whose displays show the node's topics.
"""

from __future__ import annotations

import ast
import importlib.util
import os
from pathlib import Path
import py_compile
import subprocess
import sys
import types

import pytest
import yaml

from soft_rom.predictor.params import PARAMS

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / 'launch' / 'predictor.launch.py'
RVIZ = ROOT / 'config' / 'predictor.rviz'


class _Recorder:
    def __init__(self, *args, **kwargs) -> None:
        self.args, self.kwargs = args, kwargs


class _Config:
    values: dict[str, str] = {}

    def __init__(self, name: str) -> None:
        self.name = name

    def perform(self, context) -> str:
        return context[self.name]


class _Share:
    def __init__(self, package: str) -> None:
        self.package = package

    def perform(self, context) -> str:
        return context['__share__']


@pytest.fixture
def launch_module(monkeypatch):
    """The launch file imported against recording stand-ins of launch / launch_ros."""
    fakes = {
        'launch': types.SimpleNamespace(LaunchDescription=_Recorder),
        'launch.actions': types.SimpleNamespace(DeclareLaunchArgument=_Recorder,
                                                OpaqueFunction=_Recorder),
        'launch.substitutions': types.SimpleNamespace(LaunchConfiguration=_Config,
                                                      PathJoinSubstitution=_Recorder),
        'launch_ros': types.SimpleNamespace(),
        'launch_ros.actions': types.SimpleNamespace(Node=_Recorder),
        'launch_ros.substitutions': types.SimpleNamespace(FindPackageShare=_Share),
    }
    for name, mod in fakes.items():
        monkeypatch.setitem(sys.modules, name, mod)
    spec = importlib.util.spec_from_file_location('predictor_launch', LAUNCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _context(tmp_path: Path, **args: str) -> dict[str, str]:
    share = tmp_path / 'share' / 'soft_rom'
    (share / 'config').mkdir(parents=True)
    (share / 'config' / 'predictor.rviz').write_text(RVIZ.read_text(encoding='utf-8'),
                                                      encoding='utf-8')
    ctx = {'params_file': '/p.yaml', 'node_name': 'soft_rom_predictor', 'use_sim_time': 'false',
           'model_path': '', 'kalman': '', 'lifecycle': '', 'frame_id': '', 'rviz': 'false',
           '__share__': str(share)}
    ctx.update(args)
    return ctx


def test_launch_file_compiles_and_declares_the_documented_arguments(launch_module) -> None:
    py_compile.compile(str(LAUNCH), doraise=True)
    ast.parse(LAUNCH.read_text(encoding='utf-8'))
    desc = launch_module.generate_launch_description()
    actions = desc.args[0]
    names = [a.args[0] for a in actions if a.args and isinstance(a.args[0], str)]
    assert names == ['model_path', 'params_file', 'use_sim_time', 'kalman', 'lifecycle',
                     'frame_id', 'rviz', 'node_name']
    assert all(a.kwargs.get('description') for a in actions if a.args)
    assert callable(actions[-1].kwargs['function'])


def test_rviz_true_adds_rviz2_with_the_config(launch_module, tmp_path) -> None:
    ctx = _context(tmp_path, rviz='true', frame_id='base', use_sim_time='true',
                   lifecycle='true', model_path='/m.npz')
    node, rviz = launch_module._actions(ctx)
    assert node.kwargs['executable'] == 'predictor'
    assert node.kwargs['parameters'][1] == {'use_sim_time': True, 'model_path': '/m.npz',
                                            'lifecycle': True, 'frame_id': 'base'}
    assert rviz.kwargs['package'] == 'rviz2' and rviz.kwargs['executable'] == 'rviz2'
    args = rviz.kwargs['arguments']
    assert args[0] == '-d' and Path(args[1]).name == 'predictor.rviz'
    assert args[2:] == ['-f', 'base']
    assert rviz.kwargs['parameters'] == [{'use_sim_time': True}]


def test_rviz_follows_a_renamed_node_and_is_off_by_default(launch_module, tmp_path) -> None:
    assert len(launch_module._actions(_context(tmp_path))) == 1
    ctx = _context(tmp_path / 'b', rviz='true', node_name='eel')
    _, rviz = launch_module._actions(ctx)
    text = Path(rviz.kwargs['arguments'][1]).read_text(encoding='utf-8')
    assert '/eel/centerline_marker' in text and '/soft_rom_predictor/' not in text


def test_rviz_config_shows_the_node_topics() -> None:
    doc = yaml.safe_load(RVIZ.read_text(encoding='utf-8'))
    manager = doc['Visualization Manager']
    assert manager['Global Options']['Fixed Frame'] == 'world'
    shown = {d['Class']: [] for d in manager['Displays']}
    for d in manager['Displays']:
        if 'Topic' in d:
            shown[d['Class']].append(d['Topic']['Value'])
    measured = next(p.default for p in PARAMS if p.name == 'measured_topic')
    assert shown['rviz_default_plugins/Marker'] == ['/soft_rom_predictor/centerline_marker']
    assert shown['rviz_default_plugins/PoseArray'] == ['/soft_rom_predictor/centerline',
                                                       measured]
    frame = next(p.default for p in PARAMS if p.name == 'frame_id')
    assert frame == 'world'


def test_readme_lists_the_run_time_parameters_and_commands() -> None:
    readme = (ROOT / 'README.md').read_text(encoding='utf-8')
    start = readme.index('Parameters changeable at run time:')
    listed = readme[start:readme.index('All others are read-only', start)]
    names = {w.strip('`,. \n') for w in listed.split('`')[1::2]}
    assert names == {p.name for p in PARAMS if not p.read_only}
    for command in ('ros2 param set /soft_rom_predictor model_path',
                    'ros2 service call /soft_rom_predictor/reset std_srvs/srv/Trigger',
                    'ros2 bag play recording/ --clock', 'use_sim_time:=true',
                    'ros2 lifecycle set /soft_rom_predictor configure',
                    'ros2 lifecycle set /soft_rom_predictor activate', 'rviz:=true'):
        assert command in readme, command


def test_predictor_without_ros_says_so_in_one_line(tmp_path) -> None:
    # rclpy shadowed by a package that is not there, as on a machine without ROS
    fake = tmp_path / 'rclpy'
    fake.mkdir()
    (fake / '__init__.py').write_text(
        "raise ModuleNotFoundError(\"No module named 'rclpy'\", name='rclpy')\n",
        encoding='utf-8')
    exe = Path(sys.executable).parent / 'predictor'
    assert exe.exists(), 'pip install -e . puts predictor beside python'
    env = dict(os.environ, PYTHONPATH=str(tmp_path))
    out = subprocess.run([str(exe), '--ros-args', '-p', 'model_path:=m.npz'], env=env,
                         capture_output=True, text=True, timeout=60, check=False)
    assert out.returncode == 2, out.stdout + out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and 'Traceback' not in out.stderr, out.stderr
    # the first ROS module missing is named: rclpy (shadowed) where the wheels are installed,
    # a message package where nothing of ROS is
    assert 'ROS 2 Jazzy' in lines[0] and 'ros extra' in lines[0]
    assert 'No module named' in lines[0]
    assert out.stdout == ''
