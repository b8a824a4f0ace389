"""Start the twin (twin.launch.py) and the example wave controller in the same namespace.

    ros2 launch dea_array_twin twin_with_controller.launch.py namespace:=left_array

The controller pushes each unit in turn to ``amplitude`` and moves on when the next
unit's capacitance shows the membrane stretching (``dea-twin demo`` runs the same pair
in one process).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, IncludeLaunchDescription
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory('dea_array_twin')
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='', description='namespace of the twin and the controller'),
        DeclareLaunchArgument('params_file', default_value=os.path.join(share, 'config', 'twin.yaml'),
                              description='ROS parameters YAML of the twin'),
        DeclareLaunchArgument('amplitude', default_value='0.008',
                              description='displacement each unit is pushed to [m]'),
        IncludeLaunchDescription(
            PythonLaunchDescriptionSource(os.path.join(share, 'launch', 'twin.launch.py')),
            launch_arguments={'namespace': LaunchConfiguration('namespace'),
                              'params_file': LaunchConfiguration('params_file')}.items()),
        Node(package='dea_array_twin', executable='wave_controller', name='wave_controller',
             namespace=LaunchConfiguration('namespace'),
             parameters=[{'amplitude': LaunchConfiguration('amplitude')}], output='screen'),
    ])
