"""Launch the closed loop in sim time: the eel FOM (plant), the predictor and the controller.

Usage::

    ros2 launch soft_rom closed_loop.launch.py model_path:=/path/eel_lopinf_r16.npz
    ros2 launch soft_rom closed_loop.launch.py model_path:=m.npz \\
        reference:=step:u=20e3/-20e3/0/0/0/0 rviz:=true

The plant (``ros2 run soft_rom plant``) steps the embedded FOM and publishes ``/clock``,
the measured centerline and nothing else, from when the controller publishes and the
predictor listens on the pressure topics (``wait_for_subscribers: 1``); the predictor runs
the model on the controller's pressure commands (open loop: it is the controller's
internal model) and publishes
``~/state``; the controller (``ros2 run soft_rom controller``) tracks ``reference`` (time 0
= sim time 0) and publishes the commands. ``input_mode:=array`` carries the commands in one
``Float64MultiArray`` (``/soft_robot/pressures``) instead of one ``FluidPressure`` topic per
chamber, for all three nodes. ``duration_s`` (0: no end) stops the plant after
that much sim time; ``record_path`` then gets its ``t``, ``U``, ``Y``. ``rviz:=true`` also
starts ``rviz2`` with ``share/soft_rom/config/predictor.rviz`` (predicted and measured
centerlines).
"""

from __future__ import annotations

import os

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

_TRUE = ('true', '1', 'yes', 'on')
_ENV = {'OPENBLAS_NUM_THREADS': '1', 'OMP_NUM_THREADS': '1'}


def _actions(context, *args, **kwargs):
    value = {name: LaunchConfiguration(name).perform(context).strip()
             for name in ('model_path', 'reference', 'duration_s', 'record_path', 'rviz',
                          'input_mode')}
    model = value['model_path']
    mode = {'input_mode': value['input_mode'] or 'per_chamber'}
    plant = {'duration_s': float(value['duration_s'] or 0.0),
             'record_path': value['record_path'], 'wait_for_subscribers': 1, **mode}
    actions = [
        Node(package='soft_rom', executable='plant', name='soft_rom_plant',
             parameters=[plant], output='screen', emulate_tty=True, additional_env=_ENV),
        Node(package='soft_rom', executable='predictor', name='soft_rom_predictor',
             # every command reaches the model it integrates: reliable, as the controller
             # publishes (best effort, depth 10, dropped commands while it lagged)
             parameters=[{'model_path': model, 'use_sim_time': True, 'kalman': False,
                          'input_qos': 'reliable', 'qos_depth': 100, **mode}],
             output='screen', emulate_tty=True, additional_env=_ENV),
        Node(package='soft_rom', executable='controller', name='soft_rom_controller',
             parameters=[{'model_path': model, 'use_sim_time': True,
                          'reference': value['reference'], 'reference_t0_s': 0.0,
                          'state_topic': '/soft_rom_predictor/state', **mode}],
             output='screen', emulate_tty=True, additional_env=_ENV),
    ]
    if value['rviz'].lower() in _TRUE:
        share = FindPackageShare('soft_rom').perform(context)
        actions.append(Node(
            package='rviz2', executable='rviz2', name='soft_rom_rviz',
            arguments=['-d', os.path.join(share, 'config', 'predictor.rviz'), '-f', 'world'],
            parameters=[{'use_sim_time': True}], output='screen'))
    return actions


def generate_launch_description() -> LaunchDescription:
    """The launch arguments and the three nodes (four with RViz)."""
    return LaunchDescription([
        DeclareLaunchArgument('model_path', description='linear model file (.npz)'),
        DeclareLaunchArgument('reference', default_value='wave:f=2',
                              description='wave:..., step:u=..., an .npz or episode:BAG'),
        DeclareLaunchArgument('duration_s', default_value='0.0',
                              description='sim seconds the plant runs (0: no end)'),
        DeclareLaunchArgument('record_path', default_value='',
                              description='.npz the plant writes at the end (t, U, Y)'),
        DeclareLaunchArgument('rviz', default_value='false',
                              description='also start rviz2 (not a dependency)'),
        DeclareLaunchArgument('input_mode', default_value='per_chamber',
                              description='pressure commands: per_chamber (FluidPressure '
                              'topics) or array (one Float64MultiArray)'),
        OpaqueFunction(function=_actions),
    ])
