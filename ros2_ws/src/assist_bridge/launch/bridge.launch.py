"""Launch mavlink_bridge_node (ros2 launch assist_bridge bridge.launch.py [real:=true])."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from assist_common.launch_tools import BOOL_CHOICES, shutdown_when_exits


def generate_launch_description():
    """The bridge with config/bridge.yaml, or config/bridge_real.yaml when real:=true."""
    share = get_package_share_directory('assist_bridge')
    args = [DeclareLaunchArgument('real', default_value='false', choices=BOOL_CHOICES,
                                  description='true: config/bridge_real.yaml (Pixhawk on a serial link); '
                                              'false: config/bridge.yaml (SITL / sim over UDP loopback)')]
    entities = []
    for cfg, cond in (('bridge.yaml', UnlessCondition), ('bridge_real.yaml', IfCondition)):
        node = Node(package='assist_bridge', executable='mavlink_bridge_node', name='mavlink_bridge_node',
                    output='screen', parameters=[os.path.join(share, 'config', cfg)],
                    condition=cond(LaunchConfiguration('real')))
        entities += [node, *shutdown_when_exits(node, 'no link to the vehicle without the bridge')]
    return LaunchDescription(args + entities)
