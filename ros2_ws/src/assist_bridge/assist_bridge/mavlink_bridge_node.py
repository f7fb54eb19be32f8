"""mavlink_bridge_node: /cmd_vel (FLU) -> ArduCopter GUIDED velocity setpoints; telemetry -> /odom.

A thin rclpy shell over assist_bridge.bridge_core.MavlinkBridge (see that module for the rules).
Timeouts (command, link, ACK) run on the wall clock: the vehicle (real, SITL or the sim's
stand-in) always flies in real time. The core logs through Python logging; a handler forwards
those records to this node's logger, so vehicle events (link up/lost, mode and arming changes,
takeoff complete) reach /rosout with timestamps.

Threads: the node spins a SingleThreadedExecutor (rclpy's MultiThreadedExecutor adds milliseconds of
scheduling tail to every /cmd_vel), the core's receive thread owns the MAVLink link, and the
services, which wait up to ack_timeout_s for the vehicle's COMMAND_ACK, are coroutines that await
that wait on a one-thread worker pool, so /cmd_vel is never held up behind a service call.
Service queues: each /uav/* service takes up to SERVICE_QUEUE_DEPTH requests at once; at most
max_pending_commands vehicle commands wait for the worker, and any call beyond that is answered
at once with success=false ('busy'), so every request gets an answer.
"""
from __future__ import annotations

import concurrent.futures
import logging
import math
import threading
import time

from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy._rclpy_pybind11 import RCLError
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from std_srvs.srv import Trigger

from assist_common.constants import ACCEPTED_CMD_FRAMES
from assist_common.ros_common import (RELIABLE_QOS, SENSOR_QOS, Diagnostics, Param, StartupError, declare_parameters,
                                      exit_process, forward_logging, run_node, stamp_to_sec, twist_to_array)

from .bridge_core import LIMIT_FIELDS, BridgeConfig, MavlinkBridge, Odometry as CoreOdometry
from .vision import VisionConfig, VisionForwarder

SERVICE_QUEUE_DEPTH = 100   # requests each /uav/* service holds before DDS drops the oldest
SERVICE_QOS = QoSProfile(depth=SERVICE_QUEUE_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_LAST)

# Parameters marked dynamic can be changed with `ros2 param set` (validated, applied at once);
# the others are read-only (the set is refused).
_SPEED = dict(min=0.0, min_exclusive=True, dynamic=True)
_V = VisionConfig()
PARAMS = {
    'connection': Param('udpin:127.0.0.1:14550', "Autopilot endpoint: 'udpin:HOST:PORT' (listen; loopback by "
                        "default), 'udpout:HOST:PORT', 'tcp:HOST:PORT' (SITL serves tcp:127.0.0.1:5760), "
                        "'tcpin:HOST:PORT', or a serial device under /dev such as '/dev/ttyACM0' (baud from "
                        "'baud'). Anything else is refused."),
    'baud': Param(57600, 'Serial baud rate (serial connections only; 115200 for USB, 57600/921600 for TELEM).',
                  min=1200, max=12000000),
    'target_system': Param(1, 'MAVLink system id of the autopilot (SYSID_THISMAV); 0 = lock onto the first '
                           "autopilot heard. Other systems are ignored and counted.", min=0, max=255),
    'target_component': Param(1, 'MAVLink component id of the autopilot; 0 = the first autopilot heard.',
                              min=0, max=255),
    'source_system': Param(255, 'Our MAVLink system id (ArduPilot accepts commands from SYSID_MYGCS = 255 by '
                           'default).', min=1, max=255),
    'source_component': Param(191, 'Our MAVLink component id (191 = onboard computer).', min=1, max=255),
    'signing_key_file': Param('', 'MAVLink 2 signing key file (32 raw bytes or 64 hex characters, mode 600); '
                              'empty = unsigned. With a key, unsigned or badly signed frames are dropped and counted.'),
    'address_relock': Param(True, 'After a declared link loss, accept the same vehicle ids from the same host on '
                            'a new UDP port (a restarted SITL or stand-in gets a new port); false = the first '
                            'address for the life of the node.'),
    'velocity_scale': Param(1.0, 'Commanded velocity is multiplied by this (0, 1]; use 0.5 on the real vehicle, '
                            'as in the paper. Changeable at run time.', min=0.0, max=1.0, min_exclusive=True,
                            dynamic=True),
    'max_speed_x_mps': Param(2.0, 'Clamp of the forward/back speed after scaling (m/s). Changeable at run time.',
                             max=20.0, **_SPEED),
    'max_speed_y_mps': Param(2.0, 'Clamp of the left/right speed after scaling (m/s). Changeable at run time.',
                             max=20.0, **_SPEED),
    'max_climb_mps': Param(1.0, 'Clamp of the climb speed (m/s). Changeable at run time.', max=10.0, **_SPEED),
    'max_descent_mps': Param(1.0, 'Clamp of the descent speed (m/s). Changeable at run time.', max=10.0, **_SPEED),
    'max_speed_mps': Param(2.5, 'Clamp of the total speed (m/s). Changeable at run time.', max=25.0, **_SPEED),
    'setpoint_rate_hz': Param(10.0, 'Rate of the velocity setpoint (the latest command), plus at most one '
                              'immediate send of a changed command per period (ArduCopter GUID_TIMEOUT is 3 s).',
                              min=1.0, max=50.0),
    'command_timeout_s': Param(0.5, '/cmd_vel older than this counts as absent: zero velocity is sent.',
                               min=0.05, max=5.0),
    'link_timeout_s': Param(2.0, 'No autopilot HEARTBEAT for this long: link lost, zero velocity sent.',
                            min=0.5, max=30.0),
    'link_lost_setpoint_rate_hz': Param(2.0, 'Rate of the zero-velocity setpoints sent while the link is lost '
                                        '(it may be lost one way only).', min=0.5, max=10.0),
    'odom_rate_hz': Param(30.0, 'Rate requested for LOCAL_POSITION_NED and ATTITUDE (drives /odom; the sim '
                          'stand-in sends at most one per 20 Hz physics step).', min=1.0, max=200.0),
    'status_rate_hz': Param(2.0, 'Rate requested for EXTENDED_SYS_STATE and SYS_STATUS.', min=0.1, max=50.0),
    'takeoff_altitude_m': Param(2.0, 'Altitude above the ground for /uav/takeoff (m).', min=0.0, max=100.0,
                                min_exclusive=True),
    'ack_timeout_s': Param(3.0, 'How long a service waits for the COMMAND_ACK.', min=0.1, max=60.0),
    'allow_force_disarm': Param(False, 'Let /uav/force_disarm disarm even when the autopilot thinks it is flying '
                                       '(a motor kill): for simulation episodes only (ardupilot_sitl.launch.py '
                                       'sets it); otherwise the service refuses.'),
    'max_pending_commands': Param(4, 'Vehicle commands (/uav/* calls) queued at most; further calls are '
                                  "answered at once with success=false, 'busy'.", min=1, max=SERVICE_QUEUE_DEPTH),
    'auto_guided': Param(False, 'Removed: the bridge never changes the flight mode on its own. Call /uav/guided '
                         '(or select GUIDED on the transmitter). true is refused at start-up.'),
    'mocap_topic': Param('', 'geometry_msgs/PoseStamped of the vehicle in an ENU world frame from a motion-capture '
                         'driver, forwarded as VISION_POSITION_ESTIMATE (external navigation); empty = off.'),
    'vision_rate_hz': Param(_V.rate_hz, 'VISION_POSITION_ESTIMATE rate at most (ArduPilot wants >= 4 Hz).',
                            min=4.0, max=100.0),
    'vision_max_age_s': Param(_V.max_age_s, 'Poses older than this (stamp vs wall clock) are not sent.',
                              min=0.01, max=2.0),
    'vision_max_ahead_s': Param(_V.max_ahead_s, 'Pose stamps further in the future than this are refused.',
                                min=0.0, max=1.0),
    'vision_position_sigma_m': Param(_V.position_sigma_m, 'Position noise of the mocap (1 sigma, m): the '
                                     'covariance sent.', min=0.0, max=10.0, min_exclusive=True),
    'vision_angle_sigma_rad': Param(_V.angle_sigma_rad, 'Attitude noise of the mocap (1 sigma, rad).', min=0.0,
                                    max=1.0, min_exclusive=True),
    'vision_reset_jump_m': Param(_V.reset_jump_m, 'A jump larger than this between consecutive poses counts as a '
                                 'reset (reset_counter + 1).', min=0.01, max=100.0),
    'ekf_origin': Param([0.0], 'EKF origin [latitude deg, longitude deg, altitude m] sent as SET_GPS_GLOBAL_ORIGIN '
                        'once the link is up (external navigation without GPS needs one); [0.0] = not sent.',
                        item_type=float),
    'odom_frame': Param('odom', 'World frame id of /odom (ENU).'),
    'base_frame': Param('base_link', 'Body frame id of /odom and the accepted /cmd_vel frame (FLU).'),
}
_SEVERITY_LEVEL = {0: logging.ERROR, 1: logging.ERROR, 2: logging.ERROR, 3: logging.ERROR,
                   4: logging.WARNING, 5: logging.INFO, 6: logging.INFO, 7: logging.DEBUG}


class MavlinkBridgeNode(Node):
    """ROS 2 <-> ArduCopter bridge over pymavlink."""

    def __init__(self, **kwargs):
        super().__init__('mavlink_bridge_node', **kwargs)
        forward_logging(self)           # the core's vehicle events reach /rosout, stamped
        self.bridge = None
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params)
        if self.p['auto_guided']:
            raise StartupError('mavlink_bridge_node: auto_guided was removed: the bridge never changes the flight '
                               'mode on its own; call /uav/guided instead')
        self.diag = Diagnostics(self)
        keys = set(BridgeConfig.__dataclass_fields__) & set(self.p)
        try:
            self.cfg = BridgeConfig(**{k: self.p[k] for k in keys})
        except (ValueError, TypeError) as exc:
            raise StartupError(f'mavlink_bridge_node: bad parameter: {exc}') from exc
        try:
            self.bridge = MavlinkBridge(self.cfg, on_odometry=self._on_odometry, on_statustext=self._on_statustext)
        except ValueError as exc:          # signing key file
            raise StartupError(f'mavlink_bridge_node: {exc}') from exc
        except ConnectionError as exc:
            raise StartupError(f'mavlink_bridge_node: {exc}') from exc
        self.pub_odom = self.create_publisher(Odometry, '/odom', SENSOR_QOS)
        self.create_subscription(TwistStamped, '/cmd_vel', self._on_cmd, RELIABLE_QOS)
        # one worker: vehicle commands run one at a time, in the order they were asked for
        self._workers = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix='uav-service')
        self._pending = 0
        self._pending_lock = threading.Lock()
        # a pending service coroutine holds its callback group until it returns: the services get a
        # reentrant group of their own so /cmd_vel and the timer (default group) run meanwhile
        services = ReentrantCallbackGroup()
        for name, action in (('arm', self.bridge.arm), ('disarm', self.bridge.disarm),
                             ('takeoff', self.bridge.takeoff), ('land', self.bridge.land),
                             ('guided', self.bridge.guided), ('reboot', self.bridge.reboot),
                             ('force_disarm', self.bridge.force_disarm)):
            self.create_service(Trigger, f'/uav/{name}', self._srv(name, action), qos_profile=SERVICE_QOS,
                                callback_group=services)
        self.vision = None
        if self.p['mocap_topic']:
            self.vision = VisionForwarder(VisionConfig(
                rate_hz=self.p['vision_rate_hz'], max_age_s=self.p['vision_max_age_s'],
                max_ahead_s=self.p['vision_max_ahead_s'], position_sigma_m=self.p['vision_position_sigma_m'],
                angle_sigma_rad=self.p['vision_angle_sigma_rad'], reset_jump_m=self.p['vision_reset_jump_m']))
            self.vision_lock = threading.Lock()
            self.create_subscription(PoseStamped, self.p['mocap_topic'], self._on_mocap, SENSOR_QOS)
            self.create_timer(0.5 / self.p['vision_rate_hz'], self._send_vision)
        origin = list(self.p['ekf_origin'])
        if origin != [0.0] and (len(origin) != 3 or not (-90 <= origin[0] <= 90 and -180 <= origin[1] <= 180)):
            raise StartupError(f'mavlink_bridge_node: ekf_origin must be [latitude, longitude, altitude], got {origin}')
        self.origin_sent = origin == [0.0]
        self.create_timer(1.0, self._update_diagnostics)
        self.bridge.start()
        self.get_logger().info(f"waiting for the vehicle heartbeat on '{self.cfg.connection}' "
                               f"(system {self.cfg.target_system or 'any'}, "
                               f"{'signed' if self.bridge.signing else 'unsigned'})")

    def _on_params(self, changed: dict) -> None:
        """Run-time `ros2 param set` of velocity_scale / speed clamps: validated together, then applied."""
        limits = {k: v for k, v in changed.items() if k in LIMIT_FIELDS}
        if self.bridge is None or not limits:
            return
        self.cfg = self.bridge.set_limits(**limits)   # ValueError refuses the set

    # ------------------------------------------------------------------ callbacks from the core
    def _on_odometry(self, o: CoreOdometry) -> None:
        if not self.context.ok():       # Ctrl-C: the context is gone before close() stops the link thread
            return
        msg = Odometry()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.p['odom_frame']
        msg.child_frame_id = self.p['base_frame']
        pp = msg.pose.pose
        pp.position.x, pp.position.y, pp.position.z = (float(x) for x in o.position)
        pp.orientation.x, pp.orientation.y, pp.orientation.z, pp.orientation.w = (float(x) for x in o.quaternion)
        tw = msg.twist.twist
        tw.linear.x, tw.linear.y, tw.linear.z = (float(x) for x in o.linear_velocity)
        tw.angular.x, tw.angular.y, tw.angular.z = (float(x) for x in o.angular_velocity)
        try:
            self.pub_odom.publish(msg)
        except RCLError:
            if self.context.ok():
                raise
            return                      # shut down between the check above and the publish
        self.diag.count('odom_published')

    def _on_statustext(self, severity: int, text: str) -> None:
        level = _SEVERITY_LEVEL.get(severity, logging.INFO)
        log = self.get_logger()
        line = f'vehicle: {text}'
        if level >= logging.ERROR:
            log.error(line)
        elif level >= logging.WARNING:
            log.warning(line)
        else:
            log.info(line)

    # ------------------------------------------------------------------ ROS inputs
    def _on_mocap(self, msg: PoseStamped) -> None:
        pos, q = msg.pose.position, msg.pose.orientation
        with self.vision_lock:
            why = self.vision.offer(stamp_to_sec(msg.header.stamp), (pos.x, pos.y, pos.z),
                                    (q.x, q.y, q.z, q.w), time.time())
        self.diag.count('mocap_in' if why is None else f'mocap_rejected_{why}')

    def _send_vision(self) -> None:
        with self.vision_lock:
            est = self.vision.due(time.time())
        if est is not None:
            self.diag.count('vision_sent' if self.bridge.send_vision(est) else 'vision_link_down')

    def _on_cmd(self, msg: TwistStamped) -> None:
        if msg.header.frame_id not in ACCEPTED_CMD_FRAMES:
            self._reject(f"frame '{msg.header.frame_id}' is not base_link")
            return
        ang = msg.twist.angular
        if not all(math.isfinite(x) for x in (ang.x, ang.y, ang.z)):
            self._reject('non-finite angular component')
            return
        try:
            self.bridge.set_command(twist_to_array(msg))
        except ValueError as exc:
            self._reject(str(exc))
            return
        self.diag.count('cmd_received')

    def _reject(self, reason: str) -> None:
        self.diag.count('cmd_rejected')
        self.get_logger().warning(f'/cmd_vel rejected: {reason}', throttle_duration_sec=2.0)

    def _srv(self, name: str, action):
        async def handler(request, response):
            with self._pending_lock:
                busy = self._pending >= self.p['max_pending_commands']
                if not busy:
                    self._pending += 1
            if busy:
                self.diag.count('service_busy')
                response.success = False
                response.message = (f"{name}: busy, {self.p['max_pending_commands']} vehicle commands already "
                                    'waiting; try again')
                self.get_logger().warning(f'service: {response.message}', throttle_duration_sec=2.0)
                return response
            done = Future(executor=self.executor)
            # a done callback makes set_result (from the worker) wake the executor to resume us
            done.add_done_callback(lambda _f: None)

            def work() -> None:
                try:
                    done.set_result(action())
                except Exception as exc:  # noqa: BLE001 - handed to the awaiting service, logged there
                    done.set_exception(exc)
                finally:
                    with self._pending_lock:
                        self._pending -= 1
            self._workers.submit(work)
            try:
                ok, message = await done
            except Exception as exc:  # noqa: BLE001 - the caller gets the error; the node keeps serving
                self.get_logger().error(f'service {name} failed: {type(exc).__name__}: {exc}')
                ok, message = False, f'{name} failed: {type(exc).__name__}: {exc}'
            response.success, response.message = bool(ok), message
            if ok:
                self.get_logger().info(f'service: {message}')
            else:
                self.get_logger().warning(f'service: {message}')
            return response
        return handler

    def _update_diagnostics(self) -> None:
        snap = self.bridge.snapshot()
        for k, v in snap.items():
            self.diag.set(k, v)
        for k, v in list(self.bridge.counters.items()):
            self.diag.set(k, v)
        if snap['link'] == 'up' and not self.origin_sent:
            lat, lon, alt = self.p['ekf_origin']
            self.origin_sent = self.bridge.set_ekf_origin(lat, lon, alt)
            if self.origin_sent:
                self.get_logger().info(f'EKF origin sent: {lat:.7f}, {lon:.7f}, {alt:.1f} m')
        if snap['link'] == 'up':
            self.diag.status(DiagnosticStatus.OK, f"{snap['mode']} {'armed' if snap['armed'] else 'disarmed'}")
        elif snap['link'] == 'lost':
            self.diag.status(DiagnosticStatus.ERROR, f'link lost ({self.cfg.connection})')
        else:
            self.diag.status(DiagnosticStatus.WARN, f'waiting for heartbeat ({self.cfg.connection})')
            self.get_logger().info(f"still waiting for the vehicle heartbeat on '{self.cfg.connection}'",
                                   throttle_duration_sec=10.0)

    def close(self) -> None:
        """Stop the service worker and the receive thread, close the link."""
        workers = getattr(self, '_workers', None)
        if workers is not None:
            workers.shutdown(wait=False, cancel_futures=True)
        if self.bridge is not None:
            self.bridge.close()


def main(args=None):
    """Console entry point."""
    exit_process(run_node(lambda: MavlinkBridgeNode(), args, params=PARAMS))


if __name__ == '__main__':
    main()
