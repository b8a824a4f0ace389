"""Start the twin node with a params file, in a namespace (optionally recording).

    ros2 launch dea_array_twin twin.launch.py
    ros2 launch dea_array_twin twin.launch.py namespace:=left_array params_file:=/path/to/twin.yaml record:=true

The default params file is the package's ``config/twin.yaml``; every parameter of the
node is listed in the README ("As a ROS 2 node").
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory('dea_array_twin')
    return LaunchDescription([
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the twin (its topics are relative), e.g. left_array'),
        DeclareLaunchArgument('params_file', default_value=os.path.join(share, 'config', 'twin.yaml'),
                              description='ROS parameters YAML of the twin (/**: ros__parameters: ...)'),
        DeclareLaunchArgument('record', default_value='false',
                              description='record commands, outputs and diagnostics to MCAP (record_dir)'),
        Node(package='dea_array_twin', executable='twin_node', name='dea_array_twin',
             namespace=LaunchConfiguration('namespace'),
             parameters=[LaunchConfiguration('params_file'), {'record': LaunchConfiguration('record')}],
             output='screen'),
    ])
