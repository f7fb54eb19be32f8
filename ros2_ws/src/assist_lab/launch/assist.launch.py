"""Assisted landing in simulation: sim_node + encoder_node + sim_pilot_node + policy_node.

ros2 launch assist_lab assist.launch.py mode:=latent beta:=0.3 real_time_factor:=1.0 [pilot:=keyboard]
ros2 launch assist_lab assist.launch.py record:=flights/run1    # also record the flight (bag_record)
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import EqualsSubstitution, LaunchConfiguration, NotEqualsSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from assist_common.launch_tools import BOOL_CHOICES, shutdown_when_exits


def generate_launch_description():
    """The four nodes on sim time; sim_node publishes /clock. Any of them exiting ends the launch."""
    params = os.path.join(get_package_share_directory('assist_policy'), 'config', 'assist.yaml')
    sim_params = os.path.join(get_package_share_directory('assist_sim'), 'config', 'sim.yaml')
    mode = LaunchConfiguration('mode')
    args = [DeclareLaunchArgument('mode', default_value='latent', choices=['latent', 'oracle', 'end_to_end'],
                                  description='What the assistant observes: latent (CM-VAE of the camera, '
                                              'starts encoder_node), oracle (the true goal, sim only) or '
                                              'end_to_end (the raw image)'),
            DeclareLaunchArgument('alpha', default_value='0.5',
                                  description="Simulated pilot's conformance to the assistant, in [0, 1]"),
            DeclareLaunchArgument('beta', default_value='0.5',
                                  description="Simulated pilot's skill, in [0, 1]"),
            DeclareLaunchArgument('pilot', default_value='paper',
                                  description='Simulated pilot: paper or an assist_sim.pilots family / mix'),
            DeclareLaunchArgument('seed', default_value='0',
                                  description='Seed of the scene, episodes and pilot (integer >= 0)'),
            DeclareLaunchArgument('real_time_factor', default_value='1.0',
                                  description='Sim speed: 1.0 = wall clock, 10 = ten times faster, '
                                              '0 = as fast as possible'),
            DeclareLaunchArgument('gui', default_value='false', choices=BOOL_CHOICES,
                                  description='Open the pybullet GUI window (needs a display)'),
            DeclareLaunchArgument('model_path', default_value='',
                                  description='TD3 actor file; empty = the shipped td3_<mode>_actor.pt'),
            DeclareLaunchArgument('realtime_priority', default_value='0',
                                  description='SCHED_FIFO priority 1-99 of encoder_node and policy_node (the '
                                              'camera-to-command path; needs root or CAP_SYS_NICE); 0 = off'),
            DeclareLaunchArgument('record', default_value='',
                                  description='Bag directory to record the flight into (empty: no recording)')]
    sim_time = {'use_sim_time': True}
    rt = {'realtime_priority': ParameterValue(LaunchConfiguration('realtime_priority'), value_type=int)}
    sim = Node(package='assist_sim', executable='sim_node', name='sim_node', output='screen',
               parameters=[sim_params, {'seed': LaunchConfiguration('seed'), 'gui': LaunchConfiguration('gui'),
                                        'real_time_factor': LaunchConfiguration('real_time_factor')}])
    encoder = Node(package='assist_perception', executable='encoder_node', name='encoder_node',
                   output='screen', parameters=[sim_time, rt, {'depth_noise': True}],  # sim depth is clean
                   condition=IfCondition(EqualsSubstitution(mode, 'latent')))
    pilot = Node(package='assist_sim', executable='sim_pilot_node', name='sim_pilot_node', output='screen',
                 parameters=[params, sim_time, {'alpha': LaunchConfiguration('alpha'),
                                                'beta': LaunchConfiguration('beta'),
                                                'pilot': LaunchConfiguration('pilot'),
                                                'seed': LaunchConfiguration('seed')}])
    policy = Node(package='assist_policy', executable='policy_node', name='policy_node', output='screen',
                  parameters=[params, sim_time, rt, {'mode': mode,
                                                 'model_path': ParameterValue(LaunchConfiguration('model_path'),
                                                                              value_type=str)}])
    record = Node(package='assist_bags', executable='bag_record', name='bag_record', output='screen',
                  parameters=[sim_time, {'output': ParameterValue(LaunchConfiguration('record'), value_type=str)}],
                  condition=IfCondition(NotEqualsSubstitution(LaunchConfiguration('record'), '')))
    return LaunchDescription(args + [
        sim, encoder, pilot, policy, record,
        *shutdown_when_exits(sim, 'nothing flies without the simulation'),
        *shutdown_when_exits(encoder, 'the latent assistant needs the encoder'),
        *shutdown_when_exits(pilot, 'no pilot commands without the simulated pilot'),
        *shutdown_when_exits(policy, 'the pilot would fly unassisted without policy_node'),
        *shutdown_when_exits(record, 'the flight would go unrecorded'),
    ])
