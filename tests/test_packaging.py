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

# ROS 2 Jazzy packages: rosdep resolves a package name through the distribution file.
ROS_PACKAGES = {
    'rclpy', 'std_msgs', 'std_srvs', 'sensor_msgs', 'geometry_msgs', 'visualization_msgs',
    'diagnostic_msgs', 'builtin_interfaces', 'rcl_interfaces', 'lifecycle_msgs', 'launch',
    'launch_ros', 'rosgraph_msgs',
}
# System keys checked by hand against rosdistro's rosdep/python.yaml and base.yaml at commit
# 8468e88ccd523427f9131e39d2af0938f1c298b2 (2026-08-22): each exists there, with an ubuntu
# rule. Add a key here only after checking it the same way (a missing key makes
# `rosdep install` fail for everyone).
VERIFIED_ROSDEP_KEYS = {
    'python3-numpy', 'python3-scipy', 'python3-yaml', 'python3-matplotlib', 'python3-tqdm',
    'python3-cvxpy-pip', 'python3-rosbags-pip', 'python3-pytest', 'python3-hypothesis',
}
# Dependencies without any rosdep key (no zarr key of any spelling exists): setup.py
# requires them, package.xml says in a comment how to get them, and so does the README.
NO_ROSDEP_KEY = {'zarr': "pip install 'zarr>=2.16'", 'daqp': "pip install 'daqp>=0.8.7'",
                 'google-crc32c': "pip install 'google-crc32c>=1.5'"}
# Installed with zarr (its codecs), imported for the training-set checksums.
WITH_ZARR = {'numcodecs'}

# Python import name -> the rosdep key / ROS package that provides it (None: NO_ROSDEP_KEY).
ROSDEP_OF = {
    'rclpy': 'rclpy', 'std_msgs': 'std_msgs', 'std_srvs': 'std_srvs',
    'sensor_msgs': 'sensor_msgs', 'geometry_msgs': 'geometry_msgs',
    'visualization_msgs': 'visualization_msgs', 'diagnostic_msgs': 'diagnostic_msgs',
    'builtin_interfaces': 'builtin_interfaces', 'rcl_interfaces': 'rcl_interfaces',
    'lifecycle_msgs': 'lifecycle_msgs', 'launch': 'launch', 'launch_ros': 'launch_ros',
    'rosgraph_msgs': 'rosgraph_msgs',
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib', 'tqdm': 'python3-tqdm',
    'cvxpy': 'python3-cvxpy-pip', 'rosbags': 'python3-rosbags-pip', 'zarr': None,
    'daqp': None, 'osqp': 'python3-cvxpy-pip',      # osqp: a dependency of cvxpy
    'google_crc32c': None,
}
# Imported lazily for extras (dask, mesh, fast: numba and sksparse, with numpy and LAPACK as
# the fallback); clarabel is the cvxpy solver cvxpy installs; threadpoolctl (required by
# setup.py, optional for a rosdep install) limits BLAS threads in the study, the
# simulation's workers and ERA/OKID fits.
OPTIONAL = {'dask', 'distributed', 'gmsh', 'clarabel', 'threadpoolctl', 'numba', 'sksparse'}


def _exec_depends(tags: tuple[str, ...] = ('exec_depend', 'depend')) -> set[str]:
    tree = ET.parse(ROOT / 'package.xml')
    return {e.text.strip() for e in tree.getroot() if e.tag in tags}


def _top_level_imports() -> set[str]:
    paths = list((ROOT / 'soft_rom').rglob('*.py')) + list((ROOT / 'launch').glob('*.py'))
    return set().union(*(top_level_imports(path) for path in paths))


def test_package_xml_declares_what_the_code_imports() -> None:
    deps = _exec_depends()
    stdlib = set(sys.stdlib_module_names) | {'soft_rom', '__future__'}
    missing = []
    for name in sorted(_top_level_imports() - stdlib - OPTIONAL - WITH_ZARR):
        if name not in ROSDEP_OF:
            missing.append(f'{name}: unknown')
            continue
        key = ROSDEP_OF[name]
        if key is None:
            assert name.replace('_', '-') in NO_ROSDEP_KEY, name
        elif key not in deps:
            missing.append(f'{name} -> {key}')
    assert not missing, f'imports without an exec_depend in package.xml: {missing}'


def test_package_xml_declares_nothing_unused() -> None:
    used = {ROSDEP_OF[n] for n in _top_level_imports() if n in ROSDEP_OF}
    used |= {'lifecycle_msgs'}      # the node's lifecycle mode: rclpy.lifecycle imports it
    unused = _exec_depends() - used
    assert not unused, f'exec_depends not imported anywhere: {sorted(unused)}'


def test_every_rosdep_key_is_verified() -> None:
    keys = _exec_depends(('exec_depend', 'depend', 'build_depend', 'test_depend',
                          'build_export_depend', 'buildtool_depend'))
    unknown = sorted(keys - ROS_PACKAGES - VERIFIED_ROSDEP_KEYS)
    assert not unknown, (f'package.xml keys not verified against the rosdep database: '
                         f'{unknown}')
    tests = {e.text.strip() for e in ET.parse(ROOT / 'package.xml').getroot()
             if e.tag == 'test_depend'}
    test_imports = set().union(*(top_level_imports(p) for p in (ROOT / 'tests').glob('*.py')))
    for name in sorted(test_imports & ROS_PACKAGES - _exec_depends()):
        assert name in tests, f'tests import {name}: a test_depend of package.xml'


def test_dependencies_without_a_key_agree() -> None:
    xml = (ROOT / 'package.xml').read_text(encoding='utf-8')
    setup = (ROOT / 'setup.py').read_text(encoding='utf-8')
    readme = (ROOT / 'README.md').read_text(encoding='utf-8')
    for name, command in NO_ROSDEP_KEY.items():
        assert f"'{name}>=" in setup, f'setup.py must require {name}'
        assert command in xml, f'package.xml must say how to get {name}: {command}'
        assert command in readme, f'the README must say how to get {name}: {command}'
    # the code's message when zarr is missing names the same command
    code = ''.join(p.read_text(encoding='utf-8') for p in (ROOT / 'soft_rom').rglob('*.py'))
    assert 'pip install zarr' in code


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
    for exe in ('predictor', 'soft-rom', 'controller', 'plant'):
        assert (install / 'lib' / 'soft_rom' / exe).is_file(), exe
    index = install / 'share' / 'ament_index' / 'resource_index' / 'packages'
    assert (index / 'soft_rom').is_file()
    assert (install / 'share' / 'soft_rom' / 'package.xml').is_file()
    assert list((install / 'share' / 'soft_rom' / 'config').glob('*.yaml'))
    assert (install / 'share' / 'soft_rom' / 'config' / 'predictor.rviz').is_file()
    assert list((install / 'share' / 'soft_rom' / 'launch').glob('*.launch.py'))


def test_every_subpackage_is_a_package() -> None:
    """``find_packages`` skips folders without ``__init__.py``: they would not be installed."""
    missing = [str(d.relative_to(ROOT)) for d in (ROOT / 'soft_rom').rglob('*')
               if d.is_dir() and d.name != '__pycache__' and any(d.glob('*.py'))
               and not (d / '__init__.py').exists()]
    assert not missing
