"""Launch the soft_rom predictor node with its parameter file.

Usage::

    ros2 launch soft_rom predictor.launch.py model_path:=/path/eel_lopinf_r16.npz
    ros2 launch soft_rom predictor.launch.py model_path:=m.npz use_sim_time:=true \\
        params_file:=/path/my_predictor.yaml kalman:=true

``model_path`` and ``kalman`` given here override the parameter file; left empty they keep
its values.
"""

from __future__ import annotations

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def _node(context, *args, **kwargs):
    params_file = LaunchConfiguration('params_file').perform(context)
    overrides = {
        'use_sim_time': LaunchConfiguration('use_sim_time').perform(context).lower()
        in ('true', '1', 'yes'),
    }
    model_path = LaunchConfiguration('model_path').perform(context)
    if model_path:
        overrides['model_path'] = model_path
    kalman = LaunchConfiguration('kalman').perform(context)
    if kalman:
        overrides['kalman'] = kalman.lower() in ('true', '1', 'yes')
    return [Node(
        package='soft_rom',
        executable='predictor',
        name=LaunchConfiguration('node_name').perform(context),
        parameters=[params_file, overrides],
        output='screen',
        emulate_tty=True,
        # small matrices: a threaded BLAS only adds latency to each step
        additional_env={'OPENBLAS_NUM_THREADS': '1', 'OMP_NUM_THREADS': '1'},
    )]


def generate_launch_description() -> LaunchDescription:
    """Arguments: model_path, params_file, use_sim_time, kalman, node_name."""
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
        DeclareLaunchArgument('node_name', default_value='soft_rom_predictor',
                              description='node name (topics are ~/...)'),
        OpaqueFunction(function=_node),
    ])
