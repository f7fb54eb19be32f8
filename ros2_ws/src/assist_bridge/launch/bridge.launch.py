"""Launch mavlink_bridge_node (ros2 launch assist_bridge bridge.launch.py [real:=true])."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    """The bridge with config/bridge.yaml, or config/bridge_real.yaml when real:=true."""
    share = get_package_share_directory('assist_bridge')
    args = [DeclareLaunchArgument('real', default_value='false', description='use bridge_real.yaml (Pixhawk)')]
    nodes = []
    for cfg, cond in (('bridge.yaml', UnlessCondition), ('bridge_real.yaml', IfCondition)):
        nodes.append(Node(package='assist_bridge', executable='mavlink_bridge_node', name='mavlink_bridge_node',
                          output='screen', parameters=[os.path.join(share, 'config', cfg)],
                          condition=cond(LaunchConfiguration('real'))))
    return LaunchDescription(args + nodes)
