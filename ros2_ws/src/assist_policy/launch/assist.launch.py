"""Assisted landing in simulation: sim_node + encoder_node + sim_pilot_node + policy_node.

ros2 launch assist_policy assist.launch.py mode:=latent beta:=0.3 real_time_factor:=1.0
ros2 launch assist_policy assist.launch.py record:=flights/run1    # also record the flight (bag_record)
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, NotEqualsSubstitution, PythonExpression
from launch_ros.actions import Node


def generate_launch_description():
    """The four nodes on sim time; sim_node publishes /clock."""
    params = os.path.join(get_package_share_directory('assist_policy'), 'config', 'assist.yaml')
    sim_params = os.path.join(get_package_share_directory('assist_sim'), 'config', 'sim.yaml')
    mode = LaunchConfiguration('mode')
    args = [DeclareLaunchArgument('mode', default_value='latent', description='latent | oracle | end_to_end'),
            DeclareLaunchArgument('alpha', default_value='0.5'),
            DeclareLaunchArgument('beta', default_value='0.5'),
            DeclareLaunchArgument('seed', default_value='0'),
            DeclareLaunchArgument('real_time_factor', default_value='1.0'),
            DeclareLaunchArgument('gui', default_value='false'),
            DeclareLaunchArgument('model_path', default_value=''),
            DeclareLaunchArgument('record', default_value='',
                                  description='bag directory to record the flight into (empty: no recording)')]
    sim_time = {'use_sim_time': True}
    sim = Node(package='assist_sim', executable='sim_node', name='sim_node', output='screen',
               parameters=[sim_params, {'seed': LaunchConfiguration('seed'), 'gui': LaunchConfiguration('gui'),
                                        'real_time_factor': LaunchConfiguration('real_time_factor')}])
    encoder = Node(package='assist_perception', executable='encoder_node', name='encoder_node',
                   output='screen', parameters=[sim_time, {'depth_noise': True}],  # sim depth is clean
                   condition=IfCondition(PythonExpression(["'", mode, "' == 'latent'"])))
    pilot = Node(package='assist_sim', executable='sim_pilot_node', name='sim_pilot_node', output='screen',
                 parameters=[params, sim_time, {'alpha': LaunchConfiguration('alpha'),
                                                'beta': LaunchConfiguration('beta'),
                                                'seed': LaunchConfiguration('seed')}])
    policy = Node(package='assist_policy', executable='policy_node', name='policy_node', output='screen',
                  parameters=[params, sim_time, {'mode': mode, 'model_path': LaunchConfiguration('model_path')}])
    record = Node(package='assist_policy', executable='bag_record', name='bag_record', output='screen',
                  parameters=[sim_time, {'output': LaunchConfiguration('record')}],
                  condition=IfCondition(NotEqualsSubstitution(LaunchConfiguration('record'), '')))
    return LaunchDescription(args + [sim, encoder, pilot, policy, record])
