"""ament_python package setup for soft_rom (also a plain ``pip install .``)."""

from glob import glob

from setuptools import find_packages, setup

package_name = 'soft_rom'

# ros-jazzy-* wheels (CPython 3.11): the ROS packages the node and its tests import.
ROS_WHEELS = [
    'ros-jazzy-rclpy>=7.1',
    'ros-jazzy-rmw-fastrtps-cpp>=8.4',
    'ros-jazzy-ament-index-python>=1.8',
    'ros-jazzy-builtin-interfaces>=2.0',
    'ros-jazzy-rcl-interfaces>=2.0',
    'ros-jazzy-lifecycle-msgs>=2.0',
    'ros-jazzy-std-msgs>=5.3',
    'ros-jazzy-std-srvs>=5.3',
    'ros-jazzy-sensor-msgs>=5.3',
    'ros-jazzy-geometry-msgs>=5.3',
    'ros-jazzy-visualization-msgs>=5.3',
    'ros-jazzy-diagnostic-msgs>=5.3',
    'ros-jazzy-rosgraph-msgs>=2.0',
]

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(include=['soft_rom', 'soft_rom.*']),
    package_data={'soft_rom': ['py.typed']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + glob('config/*.rviz')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    python_requires='>=3.10',
    install_requires=[
        'setuptools',
        'numpy>=1.24',
        'scipy>=1.10',
        'cvxpy>=1.4',
        'clarabel>=0.6',
        'daqp>=0.8.7',
        'rosbags>=0.11',
        'zarr>=2.16',
        # the CRC-32C of every training-set chunk, with the CPU's CRC32 instruction (zarr 3
        # depends on it too)
        'google-crc32c>=1.5',
        'PyYAML>=6.0',
        'matplotlib>=3.6',
        'tqdm>=4.64',
        'threadpoolctl>=3.1',
    ],
    extras_require={
        'test': ['pytest>=7', 'ruff>=0.5', 'mypy>=1.8', 'colcon-common-extensions>=0.3',
                 'hypothesis>=6.0', 'markdown-it-py>=2.2', 'import-linter>=2.7'],
        'dask': ['dask[array]>=2024.1', 'distributed>=2024.1'],
        # The paper-size FOM about 3x faster per step (soft_rom.sim): the element loop compiled
        # by numba, the rest system factored by CHOLMOD. scikit-sparse builds against the
        # system SuiteSparse (apt install libsuitesparse-dev); its 0.5 line needs SuiteSparse
        # >= 7.4, Debian 12 has 5.12. Without the extra: numpy and LAPACK's banded Cholesky.
        'fast': ['numba>=0.59', 'scikit-sparse>=0.4.12,<0.5'],
        # The ROS 2 Jazzy runtime from PyPI, for `predictor` and the node tests without an apt
        # installation. These wheels are built for CPython 3.11 only; on Ubuntu 24.04 (Python
        # 3.12) install ros-jazzy-* with apt and `source /opt/ros/jazzy/setup.bash` instead.
        'ros': ROS_WHEELS,
    },
    zip_safe=False,
    maintainer='soft_rom maintainers',
    maintainer_email='maintainers@users.noreply.example.com',
    description='Linear reduced-order models (LOpInf, DMDc, ERA/OKID) of soft robots from '
                'ROS 2 bags, and a real-time ROM predictor node.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'soft-rom = soft_rom.cli:main',
            'predictor = soft_rom.ros:main',
            'controller = soft_rom.ros:controller_main',
            'plant = soft_rom.ros:plant_main',
        ],
    },
)
