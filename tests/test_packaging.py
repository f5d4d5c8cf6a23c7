"""The ament_python layout: colcon installs the executables where ``ros2 run`` finds them."""

from __future__ import annotations

from pathlib import Path
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

from _source import top_level_imports
import pytest

ROOT = Path(__file__).resolve().parents[1]

# Python import name -> the rosdep key / ROS package that provides it.
ROSDEP_OF = {
    'rclpy': 'rclpy', 'std_msgs': 'std_msgs', 'std_srvs': 'std_srvs',
    'sensor_msgs': 'sensor_msgs', 'geometry_msgs': 'geometry_msgs',
    'visualization_msgs': 'visualization_msgs', 'diagnostic_msgs': 'diagnostic_msgs',
    'builtin_interfaces': 'builtin_interfaces', 'rcl_interfaces': 'rcl_interfaces',
    'launch': 'launch', 'launch_ros': 'launch_ros',
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib', 'tqdm': 'python3-tqdm',
    'cvxpy': 'python3-cvxpy-pip', 'rosbags': 'python3-rosbags-pip', 'zarr': 'python3-zarr-pip',
}
OPTIONAL = {'dask', 'distributed', 'gmsh', 'clarabel'}  # imported lazily, extras only


def _exec_depends() -> set[str]:
    tree = ET.parse(ROOT / 'package.xml')
    return {e.text.strip() for e in tree.getroot() if e.tag in ('exec_depend', 'depend')}


def _top_level_imports() -> set[str]:
    paths = list((ROOT / 'soft_rom').rglob('*.py')) + list((ROOT / 'launch').glob('*.py'))
    return set().union(*(top_level_imports(path) for path in paths))


def test_package_xml_declares_what_the_code_imports() -> None:
    deps = _exec_depends()
    stdlib = set(sys.stdlib_module_names) | {'soft_rom', '__future__'}
    missing = []
    for name in sorted(_top_level_imports() - stdlib - OPTIONAL):
        key = ROSDEP_OF.get(name)
        if key is None or key not in deps:
            missing.append(f'{name} -> {key}')
    assert not missing, f'imports without an exec_depend in package.xml: {missing}'


def test_package_xml_declares_nothing_unused() -> None:
    used = {ROSDEP_OF[n] for n in _top_level_imports() if n in ROSDEP_OF}
    unused = _exec_depends() - used
    assert not unused, f'exec_depends not imported anywhere: {sorted(unused)}'


@pytest.mark.skipif(shutil.which('colcon') is None and not (Path(sys.executable).parent / 'colcon')
                    .exists(), reason='colcon is installed with the test extras')
def test_colcon_build_installs_executables_and_marker(tmp_path) -> None:
    colcon = shutil.which('colcon') or str(Path(sys.executable).parent / 'colcon')
    src = tmp_path / 'src' / 'soft_rom'
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        '.venv', '.git', 'build', 'install', 'log', '*.egg-info', '__pycache__', '.pytest_cache'))
    out = subprocess.run([colcon, 'build', '--base-paths', 'src'], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
    install = tmp_path / 'install' / 'soft_rom'
    for exe in ('predictor', 'soft-rom'):
        assert (install / 'lib' / 'soft_rom' / exe).is_file(), exe
    index = install / 'share' / 'ament_index' / 'resource_index' / 'packages'
    assert (index / 'soft_rom').is_file()
    assert (install / 'share' / 'soft_rom' / 'package.xml').is_file()
    assert list((install / 'share' / 'soft_rom' / 'config').glob('*.yaml'))
    assert list((install / 'share' / 'soft_rom' / 'launch').glob('*.launch.py'))


def test_every_subpackage_is_a_package() -> None:
    """``find_packages`` skips folders without ``__init__.py``: they would not be installed."""
    missing = [str(d.relative_to(ROOT)) for d in (ROOT / 'soft_rom').rglob('*')
               if d.is_dir() and d.name != '__pycache__' and any(d.glob('*.py'))
               and not (d / '__init__.py').exists()]
    assert not missing
