"""encoder_node alone: ros2 launch assist_perception encoder.launch.py (params:=realsense, model_path:=FILE)."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from assist_common.launch_tools import BOOL_CHOICES, shutdown_when_exits


def generate_launch_description():
    """encoder_node with a parameter file from config/ (encoder_node.yaml by default)."""
    config_dir = os.path.join(get_package_share_directory('assist_perception'), 'config')
    args = [
        DeclareLaunchArgument('params', default_value='encoder_node', choices=['encoder_node', 'realsense'],
                              description='Parameter file in config/, without .yaml: encoder_node (sim topics) '
                                          'or realsense (realsense2_camera topics, aligned 16UC1 depth)'),
        DeclareLaunchArgument('model_path', default_value='',
                              description='CM-VAE weights file; empty = the shipped models/cmvae.pt'),
        DeclareLaunchArgument('use_sim_time', default_value='false', choices=BOOL_CHOICES,
                              description='Use /clock (true with the simulator or a bag played with --clock)'),
    ]
    node = Node(package='assist_perception', executable='encoder_node', name='encoder_node', output='screen',
                parameters=[[config_dir, '/', LaunchConfiguration('params'), '.yaml'],
                            {'model_path': ParameterValue(LaunchConfiguration('model_path'), value_type=str),
                             'use_sim_time': LaunchConfiguration('use_sim_time')}])
    return LaunchDescription(args + [node, *shutdown_when_exits(node, 'no latent without the encoder')])
