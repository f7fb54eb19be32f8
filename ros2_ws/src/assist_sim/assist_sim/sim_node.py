"""sim_node: the pybullet landing world as a ROS 2 node (thin shell over assist_sim.core)."""
from __future__ import annotations

import math
import os
import sys
import threading
import time

import numpy as np
from geometry_msgs.msg import PointStamped, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from assist_common.constants import ACCEPTED_CMD_FRAMES
from assist_common.frames import quat_to_matrix
from assist_common.ros_io import (LANDING_QOS, LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, Diagnostics, forward_logging,
                                  sec_to_stamp, twist_to_array)
from assist_common.ros_params import Param, StartupError, declare_parameters
from assist_common.ros_run import executor_param, exit_process, run_node

from .core.arducopter import FLIGHT_CONTROLLERS
from .core.config import WorldConfig
from .core.runner import RunnerConfig, SimRunner, StepOutput
from .core.scene_markers import scene_markers
from .core.world import LandingWorld
from .scene_msgs import scene_marker_array

#: close(): how long the sim thread may take to finish its step.
SIM_THREAD_STOP_S = 2.0

PARAMS = {
    'seed': Param(0, 'Seed of the scene and episode sequence; same seed, same episodes.', min=0, max=2**31 - 1),
    'real_time_factor': Param(1.0, 'Sim speed: 1.0 = wall clock, 10.0 = ten times faster, 0 = as fast as possible '
                                   '(settable at run time; fixed at 1.0 as a MAVLink vehicle).',
                              min=0.0, max=1000.0, dynamic=True),
    'camera_width': Param(64, 'Camera image width in pixels.', min=8, max=1024),
    'camera_height': Param(64, 'Camera image height in pixels.', min=8, max=1024),
    'camera_rate_hz': Param(20.0, 'Camera frame rate in sim time, at most the control rate (0 disables the '
                                  'camera; settable at run time).', min=0.0, max=1000.0, dynamic=True),
    'auto_reset': Param(True, 'Start the next episode automatically after a landing (settable at run time).',
                        dynamic=True),
    'reset_delay_s': Param(1.0, 'Sim seconds between a landing and the next episode (auto_reset; settable at '
                                'run time).', min=0.0, max=60.0, dynamic=True),
    'mavlink_url': Param('', 'Empty: driven by /cmd_vel. Else act as a MAVLink vehicle on this pymavlink '
                              'address (e.g. tcpin:127.0.0.1:5760); then the sim runs at wall-clock speed.'),
    'mavlink_signing_key_file': Param('', 'MAVLink 2 signing key file for mavlink_url (32 raw bytes or 64 hex '
                                          'characters, mode 600; the bridge uses the same file); empty = unsigned.'),
    'physics': Param('velocity', 'velocity: the velocity-tracking controller (training/evaluation); ardupilot_json: '
                                 'rigid-body quad flown by ArduPilot SITL motor outputs over its JSON interface.',
                     choices=('velocity', 'ardupilot_json')),
    'flight_controller': Param('ideal', 'physics velocity: the plant that follows /cmd_vel. ideal: the sim\'s own '
                                        'velocity loop; arducopter: ArduCopter GUIDED as the bridge flies it '
                                        '(assist_sim.core.arducopter: shaped, lagged response, leaning airframe, '
                                        'land detector; setpoints through the touchdown envelope). Tuned in '
                                        'world_config (arducopter:, touchdown:).', choices=FLIGHT_CONTROLLERS),
    'json_host': Param('127.0.0.1', 'ardupilot_json: UDP address the physics backend listens on for SITL.'),
    'json_port': Param(9002, 'ardupilot_json: UDP port for SITL (--model JSON:<host> sends to 9002).',
                       min=1, max=65535),
    'json_silence_timeout_s': Param(1.0, 'ardupilot_json: SITL silent this long -> diagnostics error.',
                                    min=0.0, min_exclusive=True),
    'gui': Param(False, 'Open the pybullet GUI window (needs a display).'),
    'world_config': Param('', 'Optional YAML file overriding assist_sim.core.config.WorldConfig fields.'),
    'cmd_timeout_s': Param(0.5, '/cmd_vel older than this (sim time) counts as absent: the vehicle hovers '
                                '(settable at run time).', min=0.0, max=10.0, min_exclusive=True, dynamic=True),
    'max_cmd_speed_mps': Param(5.0, 'Commands faster than this are rejected as out of range (settable at run '
                                    'time).', min=0.0, max=50.0, min_exclusive=True, dynamic=True),
    'turbulence': Param(True, 'Ground-effect turbulence on the target velocity.'),
    'episode_seeds': Param((), 'Scene seed of episode 0, 1, 2, ... in order (every reset, automatic or /sim/reset, '
                               'starts the next; with physics ardupilot_json episode k is the one after k landing '
                               'results, so a SITL restart before the landing flies the same scene again; an '
                               'evaluation plan, e.g. assist_lab.graph_eval); past its end, or empty, the episodes '
                               'follow seed.', min=0, max=2**31 - 1, item_type=int),
    'scene_seed': Param(-1, 'Scene seed of every episode started from now on (-1: episode_seeds, then seed); a user '
                            'study flies one scene throughout (settable at run time).', min=-1, max=2**31 - 1,
                        dynamic=True),
    'goal_index': Param(-1, 'Goal pad of every episode started from now on (-1: drawn from the episode\'s seed); set '
                            'with scene_seed before /sim/reset to fly a predefined sequence (settable at run time).',
                        min=-1, max=63, dynamic=True),
    'episode_timeout_s': Param(0.0, 'An episode with no landing after this many sim seconds ends as a timeout (the '
                                    'evaluation env cuts at 60 s); 0: the world\'s own limit (world_config '
                                    'judge.max_episode_s, 90 s by default).', min=0.0, max=3600.0),
    'executor': executor_param('events'),
    'odom_frame': Param('odom', 'World frame id (ENU).'),
    'base_frame': Param('base_link', 'Body frame id (FLU).'),
    'camera_frame': Param('camera_optical_frame', 'Optical frame id of the camera images.'),
}
# parameters applied to the running SimRunner (RunnerConfig fields of the same name)
RUNNER_PARAMS = ('camera_rate_hz', 'auto_reset', 'reset_delay_s', 'cmd_timeout_s', 'max_cmd_speed_mps', 'scene_seed',
                 'goal_index')
# /sim/reset requests queued before the middleware drops more (each reset takes ~10-50 ms)
RESET_QUEUE_DEPTH = 100


class SimNode(Node):
    """Publishes camera, odometry, clock, goal and landings; flies /cmd_vel."""

    def __init__(self, **kwargs):
        # The node clock is the sim's clock: sim_node publishes /clock and follows it (use_sim_time),
        # so /diagnostics and every stamp are in sim time like the sensor topics.
        overrides = list(kwargs.pop('parameter_overrides', None) or [])
        overrides.append(Parameter('use_sim_time', Parameter.Type.BOOL, True))
        super().__init__('sim_node', parameter_overrides=overrides, **kwargs)
        forward_logging(self)
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params)
        self.diag = Diagnostics(self)
        try:
            cfg = WorldConfig.from_yaml(self.p['world_config']) if self.p['world_config'] else WorldConfig()
        except (OSError, ValueError, TypeError) as exc:
            raise StartupError(f"sim_node: cannot load world_config '{self.p['world_config']}': {exc}") from exc
        self.control_hz = float(cfg.control_hz)
        try:
            self._check_camera_rate(self.p['camera_rate_hz'])
        except ValueError as exc:
            raise StartupError(f'sim_node: {exc}') from exc
        if self.p['gui'] and not (os.environ.get('DISPLAY') or os.environ.get('WAYLAND_DISPLAY')):
            raise StartupError('sim_node: gui:=true needs a display but DISPLAY is not set; run it in a desktop '
                               'session (or ssh -X, or xvfb-run), or leave gui:=false')
        cfg.camera.width, cfg.camera.height = int(self.p['camera_width']), int(self.p['camera_height'])
        cfg.turbulence.enabled = bool(self.p['turbulence'])
        if self.p['episode_timeout_s'] > 0:
            cfg.judge.max_episode_s = float(self.p['episode_timeout_s'])
        self.mavlink = bool(self.p['mavlink_url'])
        if self.mavlink and self.p['real_time_factor'] != 1.0:
            raise StartupError(f"sim_node: real_time_factor {self.p['real_time_factor']:g} cannot apply: as a "
                               'MAVLink vehicle (mavlink_url set) the sim runs at wall-clock speed (1.0)')
        self.json_mode = self.p['physics'] == 'ardupilot_json'
        cfg.flight_controller = str(self.p['flight_controller'])
        if cfg.flight_controller != 'ideal' and (self.json_mode or self.mavlink):
            raise StartupError(f"sim_node: flight_controller {cfg.flight_controller} models the autopilot in "
                               'physics velocity; with physics ardupilot_json or mavlink_url the autopilot is real '
                               '(leave flight_controller ideal)')
        if self.json_mode and self.mavlink:
            raise StartupError('sim_node: physics ardupilot_json and mavlink_url are exclusive (SITL is the vehicle)')
        try:
            self.world = LandingWorld(cfg, seed=int(self.p['seed']), gui=bool(self.p['gui']))
        except ValueError as exc:       # e.g. an ArduCopter-model setting of world_config out of range
            raise StartupError(f'sim_node: {exc}') from exc
        runner_cfg = RunnerConfig(
            camera_rate_hz=float(self.p['camera_rate_hz']), auto_reset=bool(self.p['auto_reset']),
            reset_delay_s=float(self.p['reset_delay_s']), cmd_timeout_s=float(self.p['cmd_timeout_s']),
            max_cmd_speed_mps=float(self.p['max_cmd_speed_mps']), airborne_start=not (self.mavlink or self.json_mode),
            episode_seeds=tuple(self.p['episode_seeds']), scene_seed=int(self.p['scene_seed']))
        self.n_pads = int(cfg.scene.n_pads)
        try:
            self._check_goal_index(int(self.p['goal_index']))
        except ValueError as exc:
            raise StartupError(f'sim_node: {exc}') from exc
        runner_cfg.goal_index = int(self.p['goal_index'])
        if self.json_mode and (runner_cfg.scene_seed >= 0 or runner_cfg.goal_index >= 0):
            raise StartupError('sim_node: scene_seed and goal_index cannot apply with physics ardupilot_json (its '
                               'episodes follow seed); leave them at -1')
        if self.json_mode:   # ArduPilot SITL flies the airframe; the runner serves its JSON physics link
            from .json_backend import make_json_runner
            try:
                self.runner = make_json_runner(self.world, runner_cfg, self.p, self.diag)
            except OSError as exc:
                raise StartupError(f"sim_node: cannot listen for SITL on udp {self.p['json_host']}:"
                                   f"{self.p['json_port']}: {exc}") from exc
            self.get_logger().info(f'physics ardupilot_json: serving SITL on udp {self.runner.server.address}')
            if self.p['real_time_factor'] != 1.0:
                self.get_logger().warning('real_time_factor is not used with ardupilot_json: SITL sets the pace '
                                          '(its --speedup)')
        else:
            self.runner = SimRunner(self.world, runner_cfg)
        self.vehicle = None
        if self.mavlink:
            from .mavlink_vehicle import MavlinkVehicle, MavlinkVehicleConfig
            try:
                self.vehicle = MavlinkVehicle(self.world, self.p['mavlink_url'], MavlinkVehicleConfig(
                    signing_key_file=self.p['mavlink_signing_key_file']))
            except (OSError, ValueError) as exc:
                raise StartupError(f"sim_node: cannot open MAVLink endpoint '{self.p['mavlink_url']}': {exc}") from exc
        self.rtf = 1.0 if self.mavlink else 0.0 if self.json_mode else float(self.p['real_time_factor'])
        self._reanchor = threading.Event()      # the pace changed: the sim loop restarts its wall/sim anchor
        self.lock = threading.Lock()

        self.pub_rgb = self.create_publisher(Image, '/camera/color/image_raw', SENSOR_QOS)
        self.pub_depth = self.create_publisher(Image, '/camera/depth/image_raw', SENSOR_QOS)
        self.pub_info = self.create_publisher(CameraInfo, '/camera/color/camera_info', SENSOR_QOS)
        self.pub_odom = None if self.mavlink or self.json_mode else self.create_publisher(Odometry, '/odom', SENSOR_QOS)
        self.pub_clock = self.create_publisher(Clock, '/clock', 10)
        self.pub_goal = self.create_publisher(PointStamped, '/sim/goal', LATCHED_QOS)
        self.pub_landing = self.create_publisher(String, '/sim/landing', LANDING_QOS)
        self.pub_scene = self.create_publisher(MarkerArray, '/sim/scene', LATCHED_QOS)
        group = MutuallyExclusiveCallbackGroup()
        if not (self.mavlink or self.json_mode):
            self.create_subscription(TwistStamped, '/cmd_vel', self._on_cmd, RELIABLE_QOS, callback_group=group)
        self.create_subscription(TwistStamped, '/assist/agent_cmd', self._on_agent, RELIABLE_QOS,
                                 callback_group=group)
        self.create_service(Trigger, '/sim/reset', self._on_reset, callback_group=group,
                            qos_profile=QoSProfile(depth=RESET_QUEUE_DEPTH,
                                                   reliability=ReliabilityPolicy.RELIABLE))

        with self.lock:
            self.runner.reset()
        self._publish_goal()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name='sim_loop', daemon=True)
        self._thread.start()
        how = ('MAVLink vehicle on ' + self.p['mavlink_url'] if self.mavlink
               else 'flown by ArduPilot SITL (JSON physics)' if self.json_mode else 'driven by /cmd_vel')
        self.get_logger().info(
            f"sim_node up: seed={self.p['seed']} rtf={self.rtf or 'max'} camera="
            f"{cfg.camera.width}x{cfg.camera.height}@{self.p['camera_rate_hz']}Hz {how}")

    # ------------------------------------------------------------------ parameters
    def _check_camera_rate(self, hz: float) -> None:
        if hz > self.control_hz:
            raise ValueError(f'camera_rate_hz {hz:g} is above the sim step rate {self.control_hz:g} Hz '
                             '(one frame per step at most)')

    def _check_goal_index(self, index: int) -> None:
        if index >= self.n_pads:
            raise ValueError(f'goal_index {index} is not a pad: the scene has pads 0..{self.n_pads - 1} (-1: drawn)')

    def _on_params(self, changed: dict) -> None:
        """Apply run-time parameter sets (validated by Param already); ValueError refuses the set."""
        if 'real_time_factor' in changed and self.mavlink:
            raise ValueError('real_time_factor is fixed at 1.0 while sim_node is a MAVLink vehicle')
        if 'real_time_factor' in changed and self.json_mode:
            raise ValueError('real_time_factor is not used with physics ardupilot_json: SITL sets the pace')
        if 'camera_rate_hz' in changed:
            self._check_camera_rate(changed['camera_rate_hz'])
        if 'goal_index' in changed:
            self._check_goal_index(changed['goal_index'])
        if self.json_mode and ('scene_seed' in changed or 'goal_index' in changed):
            raise ValueError('scene_seed and goal_index are not used with physics ardupilot_json')
        with self.lock:
            for key in RUNNER_PARAMS:
                if key in changed:
                    setattr(self.runner.cfg, key, changed[key])
            if 'real_time_factor' in changed:
                self.rtf = float(changed['real_time_factor'])
                self._reanchor.set()

    # ------------------------------------------------------------------ inputs
    def _on_cmd(self, msg: TwistStamped) -> None:
        if msg.header.frame_id not in ACCEPTED_CMD_FRAMES:
            self.diag.count('cmd_rejected_frame')
            self.get_logger().warning(f"/cmd_vel rejected: frame '{msg.header.frame_id}' is not base_link",
                                      throttle_duration_sec=2.0)
            return
        ang = msg.twist.angular
        if not all(math.isfinite(x) for x in (ang.x, ang.y, ang.z)):
            reason = 'non-finite angular component'
        else:
            with self.lock:
                reason = self.runner.set_command(twist_to_array(msg))
        if reason:
            self.diag.count('cmd_rejected')
            self.get_logger().warning(f'/cmd_vel rejected: {reason}', throttle_duration_sec=2.0)

    def _on_agent(self, msg: TwistStamped) -> None:
        with self.lock:
            self.runner.note_agent_command()

    def _on_reset(self, request, response):
        with self.lock:
            self.runner.reset()
            episode, goal = self.world.episode, self.world.goal_index
        response.success = True
        response.message = f'episode {episode}: goal pad {goal}'
        if getattr(self.runner, 'reset_pending', False):   # ardupilot_json: not while the motors spin
            response.message = f'reset deferred until SITL disarms (episode {episode} goes on)'
        else:
            self._publish_goal()
        return response

    # ------------------------------------------------------------------ loop
    def _loop(self) -> None:
        """Sim thread: steps the world at real_time_factor (rendering happens here, off the executor)."""
        dt = 1.0 / self.world.cfg.control_hz
        wall0, sim0 = time.monotonic(), self.world.time
        n_steps = 0
        while not self._stop.is_set():
            if self._reanchor.is_set():
                self._reanchor.clear()
                wall0, sim0 = time.monotonic(), self.world.time
            if self.rtf > 0:
                ahead = (self.world.time - sim0) - (time.monotonic() - wall0) * self.rtf
                if ahead > 0:
                    time.sleep(min(ahead / self.rtf, 0.05))
                    continue
                if -ahead > 1.0 * max(self.rtf, 1.0):  # more than 1 s behind: re-anchor, don't burst
                    wall0, sim0 = time.monotonic(), self.world.time
            try:
                with self.lock:
                    out = self.runner.step(self.vehicle.step if self.vehicle else None)
            except Exception as exc:  # noqa: BLE001 - keep the sim alive, report loudly
                self.diag.count('step_errors')
                self.get_logger().error(f'sim step failed: {exc!r}', throttle_duration_sec=1.0)
                time.sleep(dt)
                continue
            if not self.context.ok():
                break                      # rclpy is shutting down (SIGINT): stop publishing
            try:
                self._publish(out)
            except Exception:
                if not self.context.ok():  # the context went away between the check and publish
                    break
                raise
            n_steps += 1
            if n_steps % 100 == 0:
                wall = time.monotonic() - wall0
                if wall > 0:
                    self.diag.set('measured_real_time_factor', f'{(self.world.time - sim0) / wall:.2f}')
            if self.rtf == 0:
                time.sleep(0)  # yield the GIL to the executor threads

    def _stamp(self, sim_time: float):
        msg = Clock()
        sec_to_stamp(sim_time, msg.clock)
        return msg

    def _publish(self, out: StepOutput) -> None:
        clock = self._stamp(out.state.time)
        self.pub_clock.publish(clock)
        stamp = clock.clock
        if self.pub_odom is not None:
            self.pub_odom.publish(self._odometry(out.state, stamp))
        if out.frame is not None:
            self._publish_frame(out.frame, stamp)
        if out.landing is not None:
            self.pub_landing.publish(String(data=out.landing.to_json()))
            self.diag.count('episodes')
            self.diag.count(f'outcome_{out.landing.outcome}')
            self.get_logger().info(
                f'landing: episode {out.landing.episode} {out.landing.outcome} '
                f'error {out.landing.error_m:.2f} m ({out.landing.reason})')
        if out.new_episode:
            self._publish_goal()

    def _odometry(self, st, stamp) -> Odometry:
        msg = Odometry()
        msg.header.stamp = stamp
        msg.header.frame_id = self.p['odom_frame']
        msg.child_frame_id = self.p['base_frame']
        pp = msg.pose.pose
        pp.position.x, pp.position.y, pp.position.z = (float(x) for x in st.position)
        q = st.quaternion
        pp.orientation.x, pp.orientation.y, pp.orientation.z, pp.orientation.w = (float(x) for x in q)
        rot = quat_to_matrix(q)
        v_body = rot.T @ st.velocity                    # REP-105: twist in child_frame_id
        tw = msg.twist.twist
        tw.linear.x, tw.linear.y, tw.linear.z = (float(x) for x in v_body)
        tw.angular.x, tw.angular.y, tw.angular.z = (float(x) for x in st.angular_velocity)
        return msg

    def _publish_frame(self, frame, stamp) -> None:
        fid = self.p['camera_frame']
        rgb = Image()
        rgb.header.stamp, rgb.header.frame_id = stamp, fid
        rgb.height, rgb.width = frame.rgb.shape[:2]
        rgb.encoding, rgb.is_bigendian, rgb.step = 'rgb8', 0, frame.width * 3
        rgb.data = frame.rgb.tobytes()
        depth = Image()
        depth.header.stamp, depth.header.frame_id = stamp, fid
        depth.height, depth.width = frame.depth.shape
        depth.encoding, depth.is_bigendian, depth.step = '32FC1', int(sys.byteorder == 'big'), frame.width * 4
        depth.data = frame.depth.astype(np.float32).tobytes()
        info = CameraInfo()
        info.header.stamp, info.header.frame_id = stamp, fid
        info.height, info.width = frame.height, frame.width
        info.distortion_model = 'plumb_bob'
        info.d = [0.0] * 5
        info.k = [float(x) for x in frame.K.reshape(-1)]
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        info.p = [float(frame.K[0, 0]), 0.0, float(frame.K[0, 2]), 0.0,
                  0.0, float(frame.K[1, 1]), float(frame.K[1, 2]), 0.0, 0.0, 0.0, 1.0, 0.0]
        self.pub_rgb.publish(rgb)
        self.pub_depth.publish(depth)
        self.pub_info.publish(info)

    def _publish_goal(self) -> None:
        with self.lock:
            g = self.world.goal_position - getattr(self.runner, 'odom_offset', 0.0)   # odom frame
            stamp = self._stamp(self.world.time).clock
            boxes = scene_markers(self.world.scene, self.world.goal_index)
            if self.json_mode:   # the autopilot's odom frame, like /sim/goal
                boxes = self.runner.markers_in_odom(boxes)
        self.pub_scene.publish(scene_marker_array(boxes, self.p['odom_frame'], stamp))  # /sim/scene, every reset
        msg = PointStamped()
        msg.header.stamp, msg.header.frame_id = stamp, self.p['odom_frame']
        msg.point.x, msg.point.y, msg.point.z = (float(x) for x in g)
        self.pub_goal.publish(msg)

    def close(self) -> None:
        """Stop the sim thread and release the world and MAVLink endpoint."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=SIM_THREAD_STOP_S)
            if self._thread.is_alive():
                self.get_logger().warning(f'sim thread still in a step {SIM_THREAD_STOP_S:g} s after the stop; '
                                          'closing the world under it')
        if self.vehicle is not None:
            self.vehicle.close()
        if hasattr(self.runner, 'close'):
            self.runner.close()
        self.world.close()


def main(args=None):
    """Entry point of `ros2 run assist_sim sim_node`."""
    # executor:=multi spins two threads: with the SingleThreadedExecutor, /cmd_vel callbacks queued
    # behind the GIL-heavy sim thread at real_time_factor > 1 and commands went stale (1.75 m instead
    # of 3.5 m flown in 2 s). The default events executor dispatches from C++ (test_sim_graph's
    # flights at 8x and as fast as possible pass) and costs ~6 % of a core at 1x instead of 17-39 %.
    exit_process(run_node(SimNode, args, num_threads=2, params=PARAMS))


if __name__ == '__main__':
    main()
