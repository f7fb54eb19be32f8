"""The sim as the Pixhawk: sim_node as a MAVLink vehicle + mavlink_bridge_node over UDP loopback.

ros2 launch assist_lab sim_mavlink.launch.py [port:=14550] [seed:=0]
Then arm / take off with `ros2 service call /uav/arm std_srvs/srv/Trigger`, `/uav/takeoff`, and fly
with teleop_keyboard (remap /pilot/cmd_vel to /cmd_vel) or the policy.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from assist_common.launch_tools import shutdown_when_exits


def generate_launch_description():
    """sim_node (mavlink_url=udpout:127.0.0.1:PORT) and the bridge (connection=udpin:127.0.0.1:PORT)."""
    port = LaunchConfiguration('port')
    sim_params = os.path.join(get_package_share_directory('assist_sim'), 'config', 'sim.yaml')
    bridge_params = os.path.join(get_package_share_directory('assist_bridge'), 'config', 'bridge.yaml')
    args = [DeclareLaunchArgument('port', default_value='14550',
                                  description='UDP port on 127.0.0.1 between the sim vehicle and the bridge'),
            DeclareLaunchArgument('seed', default_value='0',
                                  description='Seed of the scene and episode sequence (integer >= 0)'),
            DeclareLaunchArgument('signing_key_file', default_value='',
                                  description='MAVLink 2 signing key file (mode 600) shared by the sim vehicle and '
                                              'the bridge; empty: unsigned link')]
    key = ParameterValue(LaunchConfiguration('signing_key_file'), value_type=str)
    # the URLs are plain text concatenation, kept a string (never evaluated as YAML or code)
    sim = Node(package='assist_sim', executable='sim_node', name='sim_node', output='screen',
               parameters=[sim_params, {'seed': LaunchConfiguration('seed'),
                                        'mavlink_url': ParameterValue(['udpout:127.0.0.1:', port], value_type=str),
                                        'mavlink_signing_key_file': key}])
    bridge = Node(package='assist_bridge', executable='mavlink_bridge_node', name='mavlink_bridge_node',
                  output='screen',
                  parameters=[bridge_params,
                              {'connection': ParameterValue(['udpin:127.0.0.1:', port], value_type=str),
                               'signing_key_file': key}])
    return LaunchDescription(args + [
        sim, bridge,
        *shutdown_when_exits(sim, 'the bridge has no vehicle without the sim'),
        *shutdown_when_exits(bridge, 'the sim vehicle has no ROS side without the bridge')])
