"""Start kpi_calib_node with the package's parameter file (or params_file:=...).

    ros2 launch kpi_calib_ros kpi_calib.launch.py [params_file:=/path/params.yaml]

launch_ros is part of every ROS 2 install; without one, run the same executable
with the same file: ``kpi_calib_node --ros-args --params-file config/kpi_calib.params.yaml``.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description() -> LaunchDescription:
    default_params = os.path.join(get_package_share_directory('kpi_calib_ros'), 'config',
                                  'kpi_calib.params.yaml')
    params_file = LaunchConfiguration('params_file')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='kpi_calib_node parameter file'),
        Node(package='kpi_calib_ros', executable='kpi_calib_node', name='kpi_calib_node',
             parameters=[params_file], output='screen', emulate_tty=True),
    ])
