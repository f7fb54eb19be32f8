"""Launch sim_node with the package's parameter file (ros2 launch assist_sim sim.launch.py)."""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

from assist_common.launch_tools import BOOL_CHOICES, shutdown_when_exits


def generate_launch_description():
    """sim_node with config/sim.yaml; `gui:=true`, `seed:=N`, `real_time_factor:=X` override it."""
    params = os.path.join(get_package_share_directory('assist_sim'), 'config', 'sim.yaml')
    args = [DeclareLaunchArgument('gui', default_value='false', choices=BOOL_CHOICES,
                                  description='Open the pybullet GUI window (needs a display)'),
            DeclareLaunchArgument('seed', default_value='0',
                                  description='Seed of the scene and episode sequence (integer >= 0)'),
            DeclareLaunchArgument('real_time_factor', default_value='1.0',
                                  description='Sim speed: 1.0 = wall clock, 10 = ten times faster, '
                                              '0 = as fast as possible')]
    sim = Node(package='assist_sim', executable='sim_node', name='sim_node', output='screen',
               parameters=[params, {'gui': LaunchConfiguration('gui'), 'seed': LaunchConfiguration('seed'),
                                    'real_time_factor': LaunchConfiguration('real_time_factor')}])
    return LaunchDescription(args + [sim, *shutdown_when_exits(sim, 'the simulation is gone')])
