"""ROS 2 (Jazzy rclpy) shell around the ROS-free core. The only package that imports rclpy.

Importing this package imports no ROS: :func:`main` (the ``predictor`` entry point) imports
rclpy only when it runs, so that without ROS it can say so in one line.
"""

from __future__ import annotations

import sys

__all__ = ['controller_main', 'main', 'plant_main']

NO_ROS = ('{exe}: the ROS 2 Jazzy Python packages are not importable ({err}); source '
          '/opt/ros/jazzy/setup.bash (apt) or install the ros extra (pip install '
          "'soft_rom[ros]', Python 3.11).")


def main(args: list[str] | None = None) -> int:
    """Entry point of ``predictor`` / ``ros2 run soft_rom predictor``; returns the exit status.

    Exit status 0 after SIGINT/SIGTERM/Ctrl-C, 1 when the model cannot be loaded at start-up
    (without ``wait_for_model``), 2 when ROS 2 is not importable.
    """
    try:
        from soft_rom.ros.predictor_node import main as node_main
    except ImportError as err:
        print(NO_ROS.format(exe='predictor', err=err), file=sys.stderr)
        return 2
    return node_main(args)


def controller_main(args: list[str] | None = None) -> int:
    """Entry point of ``controller`` / ``ros2 run soft_rom controller`` (MPC node)."""
    try:
        from soft_rom.ros.controller_node import main as node_main
    except ImportError as err:
        print(NO_ROS.format(exe='controller', err=err), file=sys.stderr)
        return 2
    return node_main(args)


def plant_main(args: list[str] | None = None) -> int:
    """Entry point of ``plant`` / ``ros2 run soft_rom plant`` (the eel FOM as a node)."""
    try:
        from soft_rom.ros.plant_node import main as node_main
    except ImportError as err:
        print(NO_ROS.format(exe='plant', err=err), file=sys.stderr)
        return 2
    return node_main(args)
