"""The pilot station with the simulated graph.

ros2 launch assist_station station.launch.py [assisted:=true] [mode:=practice|study|free] [assist_mode:=latent]
    [seed:=0] [port:=8080] [sim:=true] [study:=STUDY.yaml] [study_dir:=study_data]
assisted:=true : sim_node + encoder_node (latent mode) + policy_node + pilot_station (the pilot's
                 /pilot/cmd_vel is blended by the policy into /cmd_vel).
assisted:=false: sim_node + pilot_station, /pilot/cmd_vel remapped straight onto /cmd_vel.
sim:=false     : no sim_node (e.g. with assist_lab's sim_mavlink.launch.py or a real vehicle, where
                 /odom comes from mavlink_bridge_node).
study:=FILE    : run the user study of that study file (config/study.yaml is the paper's) from the page;
                 participants' directories go under study_dir. Needs assisted:=true and assist_mode equal
                 to the file's assistant_mode (the station switches the assistant per block itself).
Then open the URL pilot_station prints (http://127.0.0.1:8080/ by default).
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import AndSubstitution, EqualsSubstitution, LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from assist_common.launch_tools import BOOL_CHOICES, shutdown_when_exits


def generate_launch_description():
    """sim_node (+ encoder + policy when assisted) and pilot_station; any of them exiting ends the launch."""
    station_params = os.path.join(get_package_share_directory('assist_station'), 'config', 'station.yaml')
    sim_params = os.path.join(get_package_share_directory('assist_sim'), 'config', 'sim.yaml')
    policy_params = os.path.join(get_package_share_directory('assist_policy'), 'config', 'assist.yaml')
    assisted, assist_mode = LaunchConfiguration('assisted'), LaunchConfiguration('assist_mode')
    args = [DeclareLaunchArgument('assisted', default_value='true', choices=BOOL_CHOICES,
                                  description='Run the assistant (encoder_node + policy_node) between the pilot '
                                              'and the vehicle'),
            DeclareLaunchArgument('assist_mode', default_value='latent', choices=['latent', 'oracle', 'end_to_end'],
                                  description="The assistant's observation (policy_node mode)"),
            DeclareLaunchArgument('mode', default_value='practice', choices=['practice', 'study', 'free'],
                                  description='Station mode: practice, study (the user-study protocol) or free'),
            DeclareLaunchArgument('seed', default_value='0',
                                  description='Seed of the scene and episode sequence (integer >= 0)'),
            DeclareLaunchArgument('port', default_value='8080',
                                  description='TCP port of the station page on 127.0.0.1 (0: any free port)'),
            DeclareLaunchArgument('sim', default_value='true', choices=BOOL_CHOICES,
                                  description='Start sim_node (false: /odom from the bridge or a real vehicle)'),
            DeclareLaunchArgument('study', default_value='',
                                  description='User-study YAML file (empty: no study); see config/study.yaml'),
            DeclareLaunchArgument('study_dir', default_value='study_data',
                                  description='Directory of the participants\' directories (with study:=FILE)')]
    sim_time = {'use_sim_time': LaunchConfiguration('sim')}   # sim time only with sim_node's /clock
    sim = Node(package='assist_sim', executable='sim_node', name='sim_node', output='screen',
               parameters=[sim_params, {'seed': LaunchConfiguration('seed'), 'real_time_factor': 1.0}],
               condition=IfCondition(LaunchConfiguration('sim')))
    latent = AndSubstitution(assisted, EqualsSubstitution(assist_mode, 'latent'))
    encoder = Node(package='assist_perception', executable='encoder_node', name='encoder_node', output='screen',
                   parameters=[sim_time, {'depth_noise': True}], condition=IfCondition(latent))
    policy = Node(package='assist_policy', executable='policy_node', name='policy_node', output='screen',
                  parameters=[policy_params, sim_time, {'mode': assist_mode}], condition=IfCondition(assisted))
    station_args = [station_params, sim_time,
                    {'mode': LaunchConfiguration('mode'), 'port': LaunchConfiguration('port'),
                     'study_config': ParameterValue(LaunchConfiguration('study'), value_type=str),
                     'study_dir': ParameterValue(LaunchConfiguration('study_dir'), value_type=str)}]
    station = Node(package='assist_station', executable='pilot_station', name='pilot_station', output='screen',
                   parameters=station_args, condition=IfCondition(assisted))
    station_direct = Node(package='assist_station', executable='pilot_station', name='pilot_station',
                          output='screen', parameters=station_args, remappings=[('/pilot/cmd_vel', '/cmd_vel')],
                          condition=UnlessCondition(assisted))
    return LaunchDescription(args + [
        sim, encoder, policy, station, station_direct,
        *shutdown_when_exits(sim, 'nothing flies without the simulation'),
        *shutdown_when_exits(encoder, 'the latent assistant needs the encoder'),
        *shutdown_when_exits(policy, 'the pilot would fly unassisted without policy_node'),
        *shutdown_when_exits(station, 'the pilot has no controls without the station'),
        *shutdown_when_exits(station_direct, 'the pilot has no controls without the station'),
    ])
