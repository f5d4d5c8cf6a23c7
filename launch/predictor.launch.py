"""Launch the soft_rom predictor node with its parameter file (and RViz on request).

Usage::

    ros2 launch soft_rom predictor.launch.py model_path:=/path/eel_lopinf_r16.npz
    ros2 launch soft_rom predictor.launch.py model_path:=m.npz use_sim_time:=true \\
        params_file:=/path/my_predictor.yaml kalman:=true rviz:=true
    ros2 launch soft_rom predictor.launch.py model_path:=m.npz lifecycle:=true

``model_path``, ``kalman``, ``frame_id`` and ``lifecycle`` given here override the
parameter file; left empty they keep its values. ``rviz:=true`` also starts ``rviz2`` with
``share/soft_rom/config/predictor.rviz`` (topics renamed for ``node_name``, fixed frame
``frame_id``); RViz itself is not a dependency of this package.
"""

from __future__ import annotations

import os
import tempfile

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

DEFAULT_NODE = 'soft_rom_predictor'
_TRUE = ('true', '1', 'yes', 'on')


def _flag(context, name: str) -> str:
    return LaunchConfiguration(name).perform(context).strip().lower()


def _rviz_config(context, node_name: str) -> str:
    """The installed RViz file, with the topics of a renamed node."""
    share = FindPackageShare('soft_rom').perform(context)
    path = os.path.join(share, 'config', 'predictor.rviz')
    if node_name == DEFAULT_NODE:
        return path
    with open(path, encoding='utf-8') as f:
        text = f.read().replace(f'/{DEFAULT_NODE}/', f'/{node_name}/')
    fd, renamed = tempfile.mkstemp(prefix=f'{node_name}_', suffix='.rviz')
    with os.fdopen(fd, 'w', encoding='utf-8') as f:
        f.write(text)
    return renamed


def _actions(context, *args, **kwargs):
    params_file = LaunchConfiguration('params_file').perform(context)
    node_name = LaunchConfiguration('node_name').perform(context)
    use_sim_time = _flag(context, 'use_sim_time') in _TRUE
    overrides: dict[str, object] = {'use_sim_time': use_sim_time}
    model_path = LaunchConfiguration('model_path').perform(context)
    if model_path:
        overrides['model_path'] = model_path
    for name in ('kalman', 'lifecycle'):
        value = _flag(context, name)
        if value:
            overrides[name] = value in _TRUE
    frame_id = LaunchConfiguration('frame_id').perform(context)
    if frame_id:
        overrides['frame_id'] = frame_id
    actions = [Node(
        package='soft_rom',
        executable='predictor',
        name=node_name,
        parameters=[params_file, overrides],
        output='screen',
        emulate_tty=True,
        # small matrices: a threaded BLAS only adds latency to each step
        additional_env={'OPENBLAS_NUM_THREADS': '1', 'OMP_NUM_THREADS': '1'},
    )]
    if _flag(context, 'rviz') in _TRUE:
        actions.append(Node(
            package='rviz2',
            executable='rviz2',
            name=f'{node_name}_rviz',
            arguments=['-d', _rviz_config(context, node_name), '-f', frame_id or 'world'],
            parameters=[{'use_sim_time': use_sim_time}],
            output='log',
        ))
    return actions


def generate_launch_description() -> LaunchDescription:
    """The arguments (see the module docstring) and the actions they decide."""
    default_params = PathJoinSubstitution([FindPackageShare('soft_rom'), 'config',
                                           'predictor.yaml'])
    return LaunchDescription([
        DeclareLaunchArgument('model_path', default_value='',
                              description='model file (.npz); empty: the params file value'),
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='predictor parameter file'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='follow /clock (bag playback, simulation)'),
        DeclareLaunchArgument('kalman', default_value='',
                              description='true/false: Kalman state correction; empty: the '
                                          'params file value'),
        DeclareLaunchArgument('lifecycle', default_value='',
                              description='true: a managed (lifecycle) node; empty: the '
                                          'params file value (default false)'),
        DeclareLaunchArgument('frame_id', default_value='',
                              description="frame of the centerline and RViz's fixed frame; "
                                          "empty: the params file value ('world')"),
        DeclareLaunchArgument('rviz', default_value='false',
                              description='true: also start rviz2 with predictor.rviz'),
        DeclareLaunchArgument('node_name', default_value=DEFAULT_NODE,
                              description='node name (topics are ~/...)'),
        OpaqueFunction(function=_actions),
    ])
