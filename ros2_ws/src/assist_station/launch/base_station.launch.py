"""The base station: the networks on the relayed images, the pilot's interface, an optional recorder.

ros2 launch assist_station base_station.launch.py [inference:=base|onboard] [pilot:=station|none]
    [mode:=latent] [port:=8080] [record:=flights/run1] [sim_time:=false]
With the vehicle's onboard.launch.py on the same ROS_DOMAIN_ID (one network):
inference:=base   : image_decoder restores the relayed camera pair on /link/camera/... (never the vehicle's raw
                    topics, which would then cross the radio too), and encoder_node and policy_node run here on
                    it; policy_node's /cmd_vel goes to the vehicle's bridge.
inference:=onboard: the vehicle runs the networks; this side only flies and watches.
pilot:=station    : the browser pilot station (/pilot/cmd_vel); none: bring your own (teleop_keyboard in a
                    terminal: `ros2 run assist_bridge teleop_keyboard`).
sim_time:=true    : the vehicle side is onboard.launch.py camera:=sim (its /clock).
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import AndSubstitution, EqualsSubstitution, LaunchConfiguration, NotEqualsSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from assist_common.launch_tools import BOOL_CHOICES, shutdown_when_exits

# where image_decoder puts the relayed pair, and what encoder_node and policy_node read instead of the camera
LINK_COLOR, LINK_DEPTH = '/link/camera/color/image_raw', '/link/camera/depth/image_raw'


def generate_launch_description():
    """image_decoder + encoder_node + policy_node (inference:=base), pilot_station, bag_record."""
    share = get_package_share_directory
    inference, mode = LaunchConfiguration('inference'), LaunchConfiguration('mode')
    args = [DeclareLaunchArgument('inference', default_value='base', choices=['base', 'onboard'],
                                  description='Where encoder_node and policy_node run: base (here, on the relayed '
                                              'images) or onboard (the vehicle)'),
            DeclareLaunchArgument('mode', default_value='latent', choices=['latent', 'end_to_end'],
                                  description="The assistant's observation (policy_node mode; the oracle needs "
                                              'the simulator)'),
            DeclareLaunchArgument('pilot', default_value='station', choices=['station', 'none'],
                                  description='station: the browser pilot station; none: another pilot input'),
            DeclareLaunchArgument('port', default_value='8080',
                                  description='TCP port of the station page on 127.0.0.1 (0: any free port)'),
            DeclareLaunchArgument('record', default_value='',
                                  description='Bag directory to record the flight into (empty: no recording)'),
            DeclareLaunchArgument('sim_time', default_value='false', choices=BOOL_CHOICES,
                                  description='Use the /clock of a simulated vehicle (onboard.launch.py camera:=sim)')]
    here = EqualsSubstitution(inference, 'base')
    clock = {'use_sim_time': ParameterValue(LaunchConfiguration('sim_time'), value_type=bool)}
    link_inputs = [('/camera/color/image_raw', LINK_COLOR), ('/camera/depth/image_raw', LINK_DEPTH)]
    decoder = Node(package='assist_bridge', executable='image_decoder', name='image_decoder', output='screen',
                   remappings=link_inputs, condition=IfCondition(here))
    encoder = Node(package='assist_perception', executable='encoder_node', name='encoder_node', output='screen',
                   parameters=[clock, {'color_topic': LINK_COLOR, 'depth_topic': LINK_DEPTH}],
                   condition=IfCondition(AndSubstitution(here, EqualsSubstitution(mode, 'latent'))))
    policy = Node(package='assist_policy', executable='policy_node', name='policy_node', output='screen',
                  parameters=[os.path.join(share('assist_policy'), 'config', 'assist.yaml'), clock, {'mode': mode}],
                  remappings=link_inputs, condition=IfCondition(here))
    station = Node(package='assist_station', executable='pilot_station', name='pilot_station', output='screen',
                   parameters=[os.path.join(share('assist_station'), 'config', 'station.yaml'), clock,
                               {'mode': 'free', 'port': LaunchConfiguration('port')}],
                   condition=IfCondition(EqualsSubstitution(LaunchConfiguration('pilot'), 'station')))
    record = Node(package='assist_bags', executable='bag_record', name='bag_record', output='screen',
                  parameters=[clock, {'output': ParameterValue(LaunchConfiguration('record'), value_type=str)}],
                  condition=IfCondition(NotEqualsSubstitution(LaunchConfiguration('record'), '')))
    return LaunchDescription(args + [
        decoder, encoder, policy, station, record,
        *shutdown_when_exits(decoder, 'the networks get no images without the decoder'),
        *shutdown_when_exits(encoder, 'the latent assistant needs the encoder'),
        *shutdown_when_exits(policy, 'the pilot would fly unassisted without policy_node'),
        *shutdown_when_exits(station, 'the pilot has no controls without the station'),
        *shutdown_when_exits(record, 'the flight would go unrecorded'),
    ])
