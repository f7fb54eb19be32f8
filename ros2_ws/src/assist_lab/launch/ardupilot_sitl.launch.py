"""Real ArduCopter SITL in the loop: the pybullet world as SITL's JSON physics backend.

Start SITL first (README, "ArduPilot SITL with our physics"):
    arducopter --model JSON:127.0.0.1 --defaults <ap>/Tools/autotest/default_params/copter.parm,\
<share>/assist_sim/config/ardupilot_json_quad.parm
then
    ros2 launch assist_lab ardupilot_sitl.launch.py [assist:=true] [pilot:=sim|none] [mode:=latent] \
        [landings:=N results_file:=landings.csv]

Nodes: sim_node (physics:=ardupilot_json, UDP json_port 9002: camera, /clock, /sim/goal,
/sim/landing), mavlink_bridge_node (tcp:127.0.0.1:5760: /odom, /cmd_vel -> GUIDED velocity,
/uav/* services); with assist:=true encoder_node + policy_node (the policy blends /pilot/cmd_vel
into /cmd_vel), with pilot:=sim the simulated pilot on /pilot/cmd_vel (pilot:=none: run
teleop_keyboard yourself). Without assist the pilot drives /cmd_vel directly. Everything but
sim_node runs on sim time (/clock from sim_node, which follows SITL's lock-step pace).
With landings:=N, landing_runner arms, takes off and lands the vehicle for N episodes (the
launch ends when they are flown). The encoder/policy/pilot packages are looked up only when
their nodes are enabled.
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import AndSubstitution, EqualsSubstitution, LaunchConfiguration, NotSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

from assist_common.launch_tools import BOOL_CHOICES, shutdown_when_exits


def generate_launch_description():
    """sim_node (ardupilot_json) + bridge to SITL, optionally encoder + policy and the simulated pilot."""
    sim_params = os.path.join(get_package_share_directory('assist_sim'), 'config', 'sim.yaml')
    bridge_params = os.path.join(get_package_share_directory('assist_bridge'), 'config', 'bridge.yaml')
    assist, pilot = LaunchConfiguration('assist'), LaunchConfiguration('pilot')
    args = [DeclareLaunchArgument('connection', default_value='tcp:127.0.0.1:5760',
                                  description="SITL's MAVLink port (SERIAL0)"),
            DeclareLaunchArgument('signing_key_file', default_value='',
                                  description='MAVLink 2 signing key file (mode 600) for the bridge; the same key '
                                              'must be set up on the autopilot; empty: unsigned link'),
            DeclareLaunchArgument('json_port', default_value='9002', description='UDP port SITL sends servo frames to'),
            DeclareLaunchArgument('seed', default_value='0',
                                  description='Seed of the scene, episodes and pilot (integer >= 0)'),
            DeclareLaunchArgument('gui', default_value='false', choices=BOOL_CHOICES,
                                  description='Open the pybullet GUI window (needs a display)'),
            DeclareLaunchArgument('assist', default_value='true', choices=BOOL_CHOICES,
                                  description='Run encoder_node + policy_node between the pilot and the vehicle'),
            DeclareLaunchArgument('mode', default_value='latent', choices=['latent', 'oracle', 'end_to_end'],
                                  description='policy_node mode (latent also starts encoder_node)'),
            DeclareLaunchArgument('pilot', default_value='sim', choices=['sim', 'none'],
                                  description='sim: sim_pilot_node flies; none: run teleop_keyboard yourself'),
            DeclareLaunchArgument('alpha', default_value='0.5',
                                  description="Simulated pilot's conformance to the assistant, in [0, 1]"),
            DeclareLaunchArgument('beta', default_value='0.5', description="Simulated pilot's skill, in [0, 1]"),
            DeclareLaunchArgument('landings', default_value='0',
                                  description='Landings for landing_runner to fly (GUIDED, arm, takeoff, LAND after '
                                              'each result; the launch ends when they are flown); 0: no runner, '
                                              'call /uav/arm and /uav/takeoff yourself'),
            DeclareLaunchArgument('results_file', default_value='',
                                  description="landing_runner's CSV of landing results (empty: log only)")]
    sim_time = {'use_sim_time': True}
    sim = Node(package='assist_sim', executable='sim_node', name='sim_node', output='screen',
               parameters=[sim_params, {'physics': 'ardupilot_json', 'seed': LaunchConfiguration('seed'),
                                        'gui': LaunchConfiguration('gui'),
                                        'json_port': LaunchConfiguration('json_port')}])
    bridge = Node(package='assist_bridge', executable='mavlink_bridge_node', name='mavlink_bridge_node',
                  output='screen', parameters=[bridge_params, sim_time,
                                               {'connection': ParameterValue(LaunchConfiguration('connection'),
                                                                             value_type=str),
                                                'signing_key_file': ParameterValue(
                                                    LaunchConfiguration('signing_key_file'), value_type=str),
                                                # episodes in simulation: landing_runner ends a landing the
                                                # autopilot never detects (resting on a pad edge) this way
                                                'allow_force_disarm': True}])
    # conditions from substitutions that compare text, never evaluate it
    simulated_pilot = EqualsSubstitution(pilot, 'sim')
    encoder = Node(package='assist_perception', executable='encoder_node', name='encoder_node', output='screen',
                   parameters=[sim_time, {'depth_noise': True, 'level_camera': True}],
                   condition=IfCondition(AndSubstitution(assist, EqualsSubstitution(LaunchConfiguration('mode'),
                                                                                    'latent'))))
    policy = Node(package='assist_policy', executable='policy_node', name='policy_node', output='screen',
                  parameters=[sim_time, {'mode': LaunchConfiguration('mode')}], condition=IfCondition(assist))
    # episodes start on the ground: the simulated pilot starts each landing after the takeoff climb
    pilot_params = {'alpha': LaunchConfiguration('alpha'), 'beta': LaunchConfiguration('beta'),
                    'seed': LaunchConfiguration('seed'), 'start_altitude_m': 1.5}
    pilot_assisted = Node(package='assist_sim', executable='sim_pilot_node', name='sim_pilot_node', output='screen',
                          parameters=[sim_time, pilot_params],
                          condition=IfCondition(AndSubstitution(simulated_pilot, assist)))
    pilot_direct = Node(package='assist_sim', executable='sim_pilot_node', name='sim_pilot_node', output='screen',
                        parameters=[sim_time, pilot_params],
                        remappings=[('/pilot/cmd_vel', '/cmd_vel')],
                        condition=IfCondition(AndSubstitution(simulated_pilot, NotSubstitution(assist))))
    runner = Node(package='assist_bridge', executable='landing_runner', name='landing_runner', output='screen',
                  parameters=[{'reboot_after_crash': True,
                               'episodes': ParameterValue(LaunchConfiguration('landings'), value_type=int),
                               'results_file': ParameterValue(LaunchConfiguration('results_file'), value_type=str)}],
                  condition=IfCondition(NotSubstitution(EqualsSubstitution(LaunchConfiguration('landings'), '0'))))
    return LaunchDescription(args + [
        sim, bridge, encoder, policy, pilot_assisted, pilot_direct, runner,
        *shutdown_when_exits(runner, 'the requested landings are flown'),
        *shutdown_when_exits(sim, 'SITL has no physics without sim_node'),
        *shutdown_when_exits(bridge, 'no link to SITL without the bridge'),
        *shutdown_when_exits(encoder, 'the latent assistant needs the encoder'),
        *shutdown_when_exits(policy, 'the pilot would fly unassisted without policy_node'),
        *shutdown_when_exits(pilot_assisted, 'no pilot commands without the simulated pilot'),
        *shutdown_when_exits(pilot_direct, 'no pilot commands without the simulated pilot'),
    ])
