"""encoder_node alone: ros2 launch assist_perception encoder.launch.py [params:=realsense] [model_path:=...]."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node


def generate_launch_description():
    """encoder_node with a parameter file from config/ (encoder_node.yaml by default)."""
    config_dir = os.path.join(get_package_share_directory('assist_perception'), 'config')
    params = LaunchConfiguration('params')
    args = [
        DeclareLaunchArgument('params', default_value='encoder_node',
                              description='parameter file in config/ without .yaml (encoder_node | realsense)'),
        DeclareLaunchArgument('model_path', default_value='', description='CM-VAE weights; empty = shipped'),
        DeclareLaunchArgument('use_sim_time', default_value='false'),
    ]
    node = Node(package='assist_perception', executable='encoder_node', name='encoder_node', output='screen',
                parameters=[PythonExpression(["'", config_dir, "/' + '", params, "' + '.yaml'"]),
                            {'model_path': LaunchConfiguration('model_path'),
                             'use_sim_time': LaunchConfiguration('use_sim_time')}])
    return LaunchDescription(args + [node])
