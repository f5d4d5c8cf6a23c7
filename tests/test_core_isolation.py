"""The core imports without ROS; rclpy and rosbags are imported only where allowed."""

from __future__ import annotations

from pathlib import Path
import subprocess
import sys

from _source import top_level_imports

PKG = Path(__file__).resolve().parents[1] / 'soft_rom'
ROS_MODULES = ('rclpy', 'std_msgs', 'sensor_msgs', 'geometry_msgs', 'visualization_msgs',
               'diagnostic_msgs', 'std_srvs', 'builtin_interfaces', 'launch', 'launch_ros',
               'rcl_interfaces')


def test_ros_and_rosbags_imports_stay_in_their_packages() -> None:
    offenders = []
    for path in PKG.rglob('*.py'):
        rel = path.relative_to(PKG).as_posix()
        found = top_level_imports(path)
        if not rel.startswith('ros/') and found & set(ROS_MODULES):
            offenders.append(f'{rel}: {sorted(found & set(ROS_MODULES))}')
        if not rel.startswith('bags/') and 'rosbags' in found:
            offenders.append(f'{rel}: rosbags')
    assert not offenders, offenders


def test_every_core_module_imports_with_rclpy_blocked() -> None:
    code = (
        'import sys, pkgutil, importlib\n'
        f'for name in {ROS_MODULES!r}:\n'
        '    sys.modules[name] = None\n'
        'import soft_rom\n'
        'mods = [m.name for m in pkgutil.walk_packages(soft_rom.__path__, "soft_rom.")\n'
        '        if not m.name.startswith("soft_rom.ros")]\n'
        'for m in mods:\n'
        '    importlib.import_module(m)\n'
        'print(len(mods))\n'
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stderr
    assert int(out.stdout.strip()) >= 5


def test_no_pickle_loading_anywhere() -> None:
    # The needles are assembled so that this file itself does not contain them.
    enable_pickle = 'allow_pickle' + '=True'
    load_calls = ('pickle' + '.load', 'joblib' + '.load')
    for path in PKG.rglob('*.py'):
        text = path.read_text(encoding='utf-8')
        assert enable_pickle not in text.replace(' ', ''), path
        assert not any(call in text for call in load_calls), path
