"""The vehicle's onboard computer: camera, image relay, MAVLink bridge (and, on a Jetson-class computer, the networks).

ros2 launch assist_bridge onboard.launch.py [camera:=realsense|sim] [inference:=base|onboard]
    [connection:=/dev/ttyACM0] [baud:=921600] [mocap_topic:=/vrpn_mocap/drone/pose] [signing_key_file:=...]
camera:=realsense : the realsense2_camera driver (aligned depth), its topics remapped to the contract's
                    /camera/color/image_raw and /camera/depth/image_raw, and the bridge on `connection`
                    with config/bridge_real.yaml (velocity_scale 0.5, as the paper flew).
camera:=sim       : sim_node stands in for both the camera and the Pixhawk (a MAVLink vehicle on UDP loopback
                    port `port`); for trying the two-machine split without hardware.
inference:=base   : images go to the base station through image_relay (JPEG + 16-bit PNG at the encoder's
                    size and rate); the base station runs encoder_node and policy_node (base_station.launch.py).
inference:=onboard: encoder_node and policy_node run here on the raw camera topics; nothing image-sized
                    crosses the link.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import EqualsSubstitution, LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from assist_common.launch_tools import shutdown_when_exits

# realsense2_camera (Jazzy) topics -> the interface contract's
REALSENSE_REMAPS = [('/camera/camera/color/image_raw', '/camera/color/image_raw'),
                    ('/camera/camera/aligned_depth_to_color/image_raw', '/camera/depth/image_raw'),
                    ('/camera/camera/color/camera_info', '/camera/color/camera_info')]


def generate_launch_description():
    """Camera (driver or sim), bridge, and the relay or the networks; any of them exiting ends the launch."""
    share = get_package_share_directory
    camera, inference = LaunchConfiguration('camera'), LaunchConfiguration('inference')
    args = [DeclareLaunchArgument('camera', default_value='realsense', choices=['realsense', 'sim'],
                                  description='realsense: the D435i driver and a Pixhawk on `connection`; sim: '
                                              'sim_node as camera and vehicle (no hardware)'),
            DeclareLaunchArgument('inference', default_value='base', choices=['base', 'onboard'],
                                  description='Where encoder_node and policy_node run: base (images relayed to the '
                                              'base station) or onboard (here)'),
            DeclareLaunchArgument('connection', default_value='/dev/ttyACM0',
                                  description="The Pixhawk's MAVLink endpoint (camera:=realsense)"),
            DeclareLaunchArgument('baud', default_value='921600', description='Serial baud rate (SERIALn_BAUD)'),
            DeclareLaunchArgument('port', default_value='14550',
                                  description='UDP port on 127.0.0.1 between the sim vehicle and the bridge '
                                              '(camera:=sim)'),
            DeclareLaunchArgument('mocap_topic', default_value='',
                                  description='PoseStamped (ENU) of a motion-capture driver, forwarded to the '
                                              'autopilot as external navigation; empty: off'),
            DeclareLaunchArgument('signing_key_file', default_value='',
                                  description='MAVLink 2 signing key file (mode 600); empty: unsigned'),
            DeclareLaunchArgument('seed', default_value='0', description='Scene seed (camera:=sim)')]
    sim_mode = EqualsSubstitution(camera, 'sim')
    real_mode = EqualsSubstitution(camera, 'realsense')
    key = ParameterValue(LaunchConfiguration('signing_key_file'), value_type=str)
    mocap = ParameterValue(LaunchConfiguration('mocap_topic'), value_type=str)
    realsense = Node(package='realsense2_camera', executable='realsense2_camera_node', name='camera',
                     namespace='camera', output='screen', remappings=REALSENSE_REMAPS,
                     parameters=[{'align_depth.enable': True, 'enable_color': True, 'enable_depth': True}],
                     condition=IfCondition(real_mode))
    sim = Node(package='assist_sim', executable='sim_node', name='sim_node', output='screen',
               parameters=[os.path.join(share('assist_sim'), 'config', 'sim.yaml'),
                           {'seed': LaunchConfiguration('seed'), 'real_time_factor': 1.0,
                            'mavlink_url': ParameterValue(['udpout:127.0.0.1:', LaunchConfiguration('port')],
                                                          value_type=str),
                            'mavlink_signing_key_file': key}],
               condition=IfCondition(sim_mode))
    bridge_real = Node(package='assist_bridge', executable='mavlink_bridge_node', name='mavlink_bridge_node',
                       output='screen',
                       parameters=[os.path.join(share('assist_bridge'), 'config', 'bridge_real.yaml'),
                                   {'connection': ParameterValue(LaunchConfiguration('connection'), value_type=str),
                                    'baud': ParameterValue(LaunchConfiguration('baud'), value_type=int),
                                    'signing_key_file': key, 'mocap_topic': mocap}],
                       condition=IfCondition(real_mode))
    bridge_sim = Node(package='assist_bridge', executable='mavlink_bridge_node', name='mavlink_bridge_node',
                      output='screen',
                      parameters=[os.path.join(share('assist_bridge'), 'config', 'bridge.yaml'),
                                  {'connection': ParameterValue(['udpin:127.0.0.1:', LaunchConfiguration('port')],
                                                                value_type=str),
                                   'velocity_scale': 0.5, 'signing_key_file': key, 'mocap_topic': mocap}],
                      condition=IfCondition(sim_mode))
    relay = Node(package='assist_bridge', executable='image_relay', name='image_relay', output='screen',
                 condition=IfCondition(EqualsSubstitution(inference, 'base')))
    onboard = IfCondition(EqualsSubstitution(inference, 'onboard'))
    sim_clock = {'use_sim_time': ParameterValue(sim_mode, value_type=bool)}
    encoder = Node(package='assist_perception', executable='encoder_node', name='encoder_node', output='screen',
                   parameters=[sim_clock, {'depth_noise': ParameterValue(sim_mode, value_type=bool)}],
                   condition=onboard)
    policy = Node(package='assist_policy', executable='policy_node', name='policy_node', output='screen',
                  parameters=[os.path.join(share('assist_policy'), 'config', 'assist.yaml'), sim_clock],
                  condition=onboard)
    return LaunchDescription(args + [
        realsense, sim, bridge_real, bridge_sim, relay, encoder, policy,
        *shutdown_when_exits(realsense, 'no images without the camera driver'),
        *shutdown_when_exits(sim, 'the sim is the camera and the vehicle'),
        *shutdown_when_exits(bridge_real, 'no link to the vehicle without the bridge'),
        *shutdown_when_exits(bridge_sim, 'no link to the vehicle without the bridge'),
        *shutdown_when_exits(relay, 'the base station gets no images without the relay'),
        *shutdown_when_exits(encoder, 'the latent assistant needs the encoder'),
        *shutdown_when_exits(policy, 'the pilot would fly unassisted without policy_node'),
    ])
