"""Real ArduCopter SITL in the loop: the pybullet world as SITL's JSON physics backend.

Start SITL first (README, "ArduPilot SITL with our physics"):
    arducopter --model JSON:127.0.0.1 --defaults <ap>/Tools/autotest/default_params/copter.parm,\
<share>/assist_sim/config/ardupilot_json_quad.parm
then
    ros2 launch assist_bridge ardupilot_sitl.launch.py [assist:=true] [pilot:=sim|none] [mode:=latent]

Nodes: sim_node (physics:=ardupilot_json, UDP json_port 9002: camera, /clock, /sim/goal,
/sim/landing), mavlink_bridge_node (tcp:127.0.0.1:5760: /odom, /cmd_vel -> GUIDED velocity,
/uav/* services); with assist:=true encoder_node + policy_node (the policy blends /pilot/cmd_vel
into /cmd_vel), with pilot:=sim the simulated pilot on /pilot/cmd_vel (pilot:=none: run
teleop_keyboard yourself). Without assist the pilot drives /cmd_vel directly. Everything but
sim_node runs on sim time (/clock from sim_node, which follows SITL's lock-step pace).
The encoder/policy/pilot packages are looked up only when their nodes are enabled.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node


def generate_launch_description():
    """sim_node (ardupilot_json) + bridge to SITL, optionally encoder + policy and the simulated pilot."""
    sim_params = os.path.join(get_package_share_directory('assist_sim'), 'config', 'sim.yaml')
    bridge_params = os.path.join(get_package_share_directory('assist_bridge'), 'config', 'bridge.yaml')
    assist, pilot = LaunchConfiguration('assist'), LaunchConfiguration('pilot')
    args = [DeclareLaunchArgument('connection', default_value='tcp:127.0.0.1:5760',
                                  description="SITL's MAVLink port (SERIAL0)"),
            DeclareLaunchArgument('json_port', default_value='9002', description='UDP port SITL sends servo frames to'),
            DeclareLaunchArgument('seed', default_value='0'),
            DeclareLaunchArgument('gui', default_value='false'),
            DeclareLaunchArgument('assist', default_value='true', description='encoder_node + policy_node'),
            DeclareLaunchArgument('mode', default_value='latent', description='policy mode: latent | oracle | end_to_end'),
            DeclareLaunchArgument('pilot', default_value='sim', description='sim: sim_pilot_node; none: keyboard'),
            DeclareLaunchArgument('alpha', default_value='0.5'),
            DeclareLaunchArgument('beta', default_value='0.5')]
    sim_time = {'use_sim_time': True}
    sim = Node(package='assist_sim', executable='sim_node', name='sim_node', output='screen',
               parameters=[sim_params, {'physics': 'ardupilot_json', 'seed': LaunchConfiguration('seed'),
                                        'gui': LaunchConfiguration('gui'),
                                        'json_port': LaunchConfiguration('json_port')}])
    bridge = Node(package='assist_bridge', executable='mavlink_bridge_node', name='mavlink_bridge_node',
                  output='screen', parameters=[bridge_params, sim_time,
                                               {'connection': LaunchConfiguration('connection')}])
    encoder = Node(package='assist_perception', executable='encoder_node', name='encoder_node', output='screen',
                   parameters=[sim_time, {'depth_noise': True}],
                   condition=IfCondition(PythonExpression(["'", assist, "' == 'true' and '",
                                                           LaunchConfiguration('mode'), "' == 'latent'"])))
    policy = Node(package='assist_policy', executable='policy_node', name='policy_node', output='screen',
                  parameters=[sim_time, {'mode': LaunchConfiguration('mode')}], condition=IfCondition(assist))
    pilot_assisted = Node(package='assist_sim', executable='sim_pilot_node', name='sim_pilot_node', output='screen',
                          parameters=[sim_time, {'alpha': LaunchConfiguration('alpha'),
                                                 'beta': LaunchConfiguration('beta'),
                                                 'seed': LaunchConfiguration('seed')}],
                          condition=IfCondition(PythonExpression(["'", pilot, "' == 'sim' and '", assist, "' == 'true'"])))
    pilot_direct = Node(package='assist_sim', executable='sim_pilot_node', name='sim_pilot_node', output='screen',
                        parameters=[sim_time, {'alpha': LaunchConfiguration('alpha'),
                                               'beta': LaunchConfiguration('beta'),
                                               'seed': LaunchConfiguration('seed')}],
                        remappings=[('/pilot/cmd_vel', '/cmd_vel')],
                        condition=IfCondition(PythonExpression(["'", pilot, "' == 'sim' and '", assist, "' != 'true'"])))
    return LaunchDescription(args + [sim, bridge, encoder, policy, pilot_assisted, pilot_direct])
