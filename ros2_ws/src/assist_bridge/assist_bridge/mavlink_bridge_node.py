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

No message ends the node: every timer and subscription callback that packs or sends MAVLink runs
guarded (an exception is counted as `callback_errors` and logged, throttled), and the core counts a
message it cannot pack as `tx_errors` instead of raising. Parameter defaults and ranges come from
the core's config dataclasses (BridgeConfig, VisionConfig, EkfOrigin, and assist_common's TouchdownConfig
as the `touchdown_*` parameters), checked at start-up.
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable

from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy._rclpy_pybind11 import RCLError
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from std_msgs.msg import UInt8
from std_srvs.srv import Trigger

from assist_common.constants import ACCEPTED_CMD_FRAMES
from assist_common.mavlink_io import ThrottledLog
from assist_common.ros_io import (LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, Diagnostics, forward_logging, stamp_to_sec,
                                  twist_to_array)
from assist_common.ros_params import Param, StartupError, declare_parameters
from assist_common.ros_run import exit_process, run_node
from assist_common.settings import RULE_KEY, check_named
from assist_common.touchdown import TouchdownConfig

from .bridge_core import LIMIT_FIELDS, BridgeConfig, EkfOrigin, MavlinkBridge, Odometry as CoreOdometry
from .vision import VisionConfig, VisionForwarder

_LOG = logging.getLogger(__name__)

SERVICE_QUEUE_DEPTH = 100   # requests each /uav/* service holds before DDS drops the oldest
SERVICE_QOS = QoSProfile(depth=SERVICE_QUEUE_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_LAST)

LANDED_STATE_TOPIC = '/uav/landed_state'
# VisionConfig field -> node parameter
VISION_PARAMS = {'rate_hz': 'vision_rate_hz', 'max_age_s': 'vision_max_age_s', 'max_ahead_s': 'vision_max_ahead_s',
                 'position_sigma_m': 'vision_position_sigma_m', 'angle_sigma_rad': 'vision_angle_sigma_rad',
                 'reset_jump_m': 'vision_reset_jump_m', 'max_jump_m': 'vision_max_jump_m',
                 'reset_confirm_poses': 'vision_reset_confirm_poses', 'max_position_m': 'vision_max_position_m',
                 'max_pose_rate_hz': 'vision_max_pose_rate_hz'}
# TouchdownConfig field -> node parameter
TOUCHDOWN_PARAMS = {f.name: f'touchdown_{f.name}' for f in dataclasses.fields(TouchdownConfig)}


def config_param(cls: type, field_name: str, description: str, dynamic: bool = False) -> Param:
    """The node parameter of config field `cls.field_name`: its default and its setting() range, one source."""
    f = next(f for f in dataclasses.fields(cls) if f.name == field_name)
    rule = f.metadata.get(RULE_KEY)
    if rule is None:
        return Param(f.default, description, dynamic=dynamic)
    if rule.lt is not None:
        raise TypeError(f'{cls.__name__}.{field_name}: a node parameter range has no exclusive maximum')
    low = rule.gt if rule.gt is not None else rule.ge
    return Param(f.default, description, min=low, max=rule.le, min_exclusive=rule.gt is not None, dynamic=dynamic)


def _bridge(name: str, description: str, dynamic: bool = False) -> Param:
    return config_param(BridgeConfig, name, description, dynamic)


def _vision(name: str, description: str) -> Param:
    return config_param(VisionConfig, name, description)


def _touchdown(name: str, description: str) -> Param:
    return config_param(TouchdownConfig, name, description)


_ORIGIN_RULES = {f.name: f.metadata[RULE_KEY] for f in dataclasses.fields(EkfOrigin)}

# Parameters marked dynamic can be changed with `ros2 param set` (validated, applied at once);
# the others are read-only (the set is refused).
PARAMS = {
    'connection': _bridge('connection', "Autopilot endpoint: 'udpin:HOST:PORT' (listen; loopback by default), "
                          "'udpout:HOST:PORT', 'tcp:HOST:PORT' (SITL serves tcp:127.0.0.1:5760), 'tcpin:HOST:PORT', "
                          "or a serial device under /dev such as '/dev/ttyACM0' (baud from 'baud'). Anything else is "
                          'refused.'),
    'baud': _bridge('baud', 'Serial baud rate (serial connections only; 115200 for USB, 57600/921600 for TELEM).'),
    'target_system': _bridge('target_system', 'MAVLink system id of the autopilot (SYSID_THISMAV); 0 = lock onto the '
                             'first autopilot heard. Other systems are ignored and counted.'),
    'target_component': _bridge('target_component', 'MAVLink component id of the autopilot; 0 = the first autopilot '
                                'heard.'),
    'source_system': _bridge('source_system', 'Our MAVLink system id (ArduPilot accepts commands from SYSID_MYGCS = '
                             '255 by default).'),
    'source_component': _bridge('source_component', 'Our MAVLink component id (191 = onboard computer).'),
    'signing_key_file': _bridge('signing_key_file', 'MAVLink 2 signing key file (32 raw bytes or 64 hex characters, '
                                'mode 600); empty = unsigned. With a key, unsigned or badly signed frames are dropped '
                                'and counted.'),
    'address_relock': _bridge('address_relock', 'After a declared link loss, accept the same vehicle ids from the '
                              'same host on a new UDP port (a restarted SITL or stand-in gets a new port); false = the '
                              'first address for the life of the node.'),
    'velocity_scale': _bridge('velocity_scale', 'Commanded velocity is multiplied by this; use 0.5 on the real '
                              'vehicle, as in the paper. Changeable at run time.', dynamic=True),
    'max_speed_x_mps': _bridge('max_speed_x_mps', 'Clamp of the forward/back speed after scaling (m/s). Changeable '
                               'at run time.', dynamic=True),
    'max_speed_y_mps': _bridge('max_speed_y_mps', 'Clamp of the left/right speed after scaling (m/s). Changeable at '
                               'run time.', dynamic=True),
    'max_climb_mps': _bridge('max_climb_mps', 'Clamp of the climb speed (m/s). Changeable at run time.', dynamic=True),
    'max_descent_mps': _bridge('max_descent_mps', 'Clamp of the descent speed (m/s). Changeable at run time.',
                               dynamic=True),
    'max_speed_mps': _bridge('max_speed_mps', 'Clamp of the total speed (m/s). Changeable at run time.', dynamic=True),
    'setpoint_rate_hz': _bridge('setpoint_rate_hz', 'Rate of the velocity setpoint (the latest command), plus at most '
                                'one immediate send of a changed command per period (ArduCopter GUID_TIMEOUT is 3 s).'),
    'command_timeout_s': _bridge('command_timeout_s', '/cmd_vel older than this counts as absent: zero velocity is '
                                 'sent.'),
    'link_timeout_s': _bridge('link_timeout_s', 'No autopilot HEARTBEAT for this long: link lost, zero velocity sent.'),
    'link_lost_setpoint_rate_hz': _bridge('link_lost_setpoint_rate_hz', 'Rate of the zero-velocity setpoints sent '
                                          'while the link is lost (it may be lost one way only).'),
    'odom_rate_hz': _bridge('odom_rate_hz', 'Rate requested for LOCAL_POSITION_NED and ATTITUDE (drives /odom; the sim '
                            'stand-in sends at most one per 20 Hz physics step).'),
    'status_rate_hz': _bridge('status_rate_hz', 'Rate requested for EXTENDED_SYS_STATE (drives /uav/landed_state) and '
                              'SYS_STATUS.'),
    'range_rate_hz': _bridge('range_rate_hz', 'Rate requested for DISTANCE_SENSOR: the downward rangefinder '
                             '(RNGFNDn_ORIENT 25) the touchdown envelope uses.'),
    'range_timeout_s': _bridge('range_timeout_s', 'A downward range older than this counts as unknown (so do readings '
                               "outside the sensor's own min/max and sensors not facing down): the touchdown envelope "
                               'then lets the command through.'),
    'touchdown_enabled': _touchdown('enabled', 'Touchdown envelope on every velocity setpoint: once the downward range '
                                    'is below touchdown_engage_range_m and the command descends, the vehicle descends '
                                    'vertically at touchdown_descent_mps, so ArduCopter detects the landing instead of '
                                    'sliding on the pad top.'),
    'touchdown_engage_range_m': _touchdown('engage_range_m', 'Downward range (base_link to the surface below, m) '
                                           'under which a descending command becomes a vertical descent.'),
    'touchdown_release_range_m': _touchdown('release_range_m', 'Downward range (m) above which the envelope lets go '
                                            'again (must exceed touchdown_engage_range_m).'),
    'touchdown_descent_mps': _touchdown('descent_mps', 'Vertical descent speed while the envelope holds the descent '
                                        '(m/s; max_descent_mps still clamps it).'),
    'touchdown_engage_descent_mps': _touchdown('engage_descent_mps', 'A command descending faster than this (m/s) '
                                               'engages the envelope.'),
    'touchdown_abort_climb_mps': _touchdown('abort_climb_mps', 'A command climbing faster than this (m/s) releases '
                                            'the envelope (the pilot takes the vehicle back up).'),
    'touchdown_lateral_max_mps': _touchdown('lateral_max_mps', 'Sideways speed (m/s) left to the command during the '
                                            'final descent (none once the legs are down).'),
    'touchdown_commit_range_m': _touchdown('commit_range_m', 'Downward range (m) at or below which the legs are '
                                           'down (0.12 m landed): the touchdown is committed (below '
                                           'touchdown_engage_range_m).'),
    'touchdown_commit_s': _touchdown('commit_s', 'A committed touchdown holds the vertical descent this long whatever '
                                     'is commanded (ArduCopter declares a landing ~1.65 s after contact); 0: never '
                                     'commits.'),
    'takeoff_altitude_m': _bridge('takeoff_altitude_m', 'Altitude above the ground for /uav/takeoff (m).'),
    'ack_timeout_s': _bridge('ack_timeout_s', 'How long a service waits for the COMMAND_ACK.'),
    'allow_force_disarm': _bridge('allow_force_disarm', 'Let /uav/force_disarm disarm even when the autopilot thinks '
                                  'it is flying (a motor kill): for simulation episodes only (assist_lab\'s '
                                  'ardupilot_sitl.launch.py sets it); otherwise the service refuses.'),
    'max_pending_commands': Param(4, 'Vehicle commands (/uav/* calls) queued at most; further calls are '
                                  "answered at once with success=false, 'busy'.", min=1, max=SERVICE_QUEUE_DEPTH),
    'auto_guided': Param(False, 'Removed: the bridge never changes the flight mode on its own. Call /uav/guided '
                         '(or select GUIDED on the transmitter). true is refused at start-up.'),
    'mocap_topic': Param('', 'geometry_msgs/PoseStamped of the vehicle in an ENU world frame from a motion-capture '
                         'driver, forwarded as VISION_POSITION_ESTIMATE (external navigation); empty = off. One '
                         'source is forwarded at a time (see vision_reset_confirm_poses).'),
    'vision_rate_hz': _vision('rate_hz', 'VISION_POSITION_ESTIMATE rate at most (ArduPilot wants >= 4 Hz).'),
    'vision_max_age_s': _vision('max_age_s', 'Poses older than this (stamp vs wall clock) are not sent; a source '
                                'silent this long may be replaced by another.'),
    'vision_max_ahead_s': _vision('max_ahead_s', 'Pose stamps further in the future than this are refused.'),
    'vision_position_sigma_m': _vision('position_sigma_m', 'Position noise of the mocap (1 sigma, m): the covariance '
                                       'sent.'),
    'vision_angle_sigma_rad': _vision('angle_sigma_rad', 'Attitude noise of the mocap (1 sigma, rad).'),
    'vision_reset_jump_m': _vision('reset_jump_m', 'A confirmed jump larger than this between consecutive poses is a '
                                   're-initialised mocap frame (reset_counter + 1).'),
    'vision_max_jump_m': _vision('max_jump_m', 'A jump larger than this between consecutive poses is refused '
                                 '(until the stream has been refused for vision_max_age_s: then it starts over).'),
    'vision_reset_confirm_poses': _vision('reset_confirm_poses', 'Consecutive poses that must continue from a jump '
                                          'before it counts as a reset; poses before that are held, and dropped if '
                                          'the old track comes back (an outlier or a second publisher).'),
    'vision_max_position_m': _vision('max_position_m', 'Poses farther than this from the mocap origin (m) are '
                                     'refused.'),
    'vision_max_pose_rate_hz': _vision('max_pose_rate_hz', 'Pose stamps closer together than 1/this are refused.'),
    'ekf_origin': Param([0.0], 'EKF origin [latitude deg, longitude deg, altitude m AMSL] sent as '
                        'SET_GPS_GLOBAL_ORIGIN once the link is up (external navigation without GPS needs one); '
                        f"[0.0] = not sent. Accepted: latitude {_ORIGIN_RULES['latitude_deg'].ge:g} to "
                        f"{_ORIGIN_RULES['latitude_deg'].le:g}, longitude {_ORIGIN_RULES['longitude_deg'].ge:g} to "
                        f"{_ORIGIN_RULES['longitude_deg'].le:g}, altitude {_ORIGIN_RULES['altitude_m'].ge:g} to "
                        f"{_ORIGIN_RULES['altitude_m'].le:g} m.", item_type=float),
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
        self._throttled = ThrottledLog(_LOG, 5.0)
        keys = set(BridgeConfig.__dataclass_fields__) & set(self.p)
        try:
            self.cfg = BridgeConfig(**{k: self.p[k] for k in keys})
        except (ValueError, TypeError) as exc:
            raise StartupError(f'mavlink_bridge_node: bad parameter: {exc}') from exc
        try:
            self.ekf_origin = EkfOrigin.from_list(self.p['ekf_origin'])
        except (ValueError, TypeError) as exc:
            raise StartupError(f"mavlink_bridge_node: parameter 'ekf_origin' {exc}") from exc
        try:
            touchdown_cfg = TouchdownConfig(**{f: self.p[name] for f, name in TOUCHDOWN_PARAMS.items()})
            check_named(touchdown_cfg)
        except (ValueError, TypeError) as exc:
            raise StartupError(f'mavlink_bridge_node: bad parameter: touchdown_{exc}') from exc
        vision_cfg = None
        if self.p['mocap_topic']:
            try:
                vision_cfg = VisionConfig(**{f: self.p[name] for f, name in VISION_PARAMS.items()})
            except (ValueError, TypeError) as exc:
                raise StartupError(f'mavlink_bridge_node: bad parameter: vision_{exc}') from exc
        # published from the receive thread: made before the bridge exists, so before it can call back
        self.pub_odom = self.create_publisher(Odometry, '/odom', SENSOR_QOS)
        self.pub_landed = self.create_publisher(UInt8, LANDED_STATE_TOPIC, LATCHED_QOS)
        try:
            self.bridge = MavlinkBridge(self.cfg, on_odometry=self._on_odometry, on_statustext=self._on_statustext,
                                        on_landed_state=self._on_landed_state, touchdown=touchdown_cfg)
        except ValueError as exc:          # signing key file
            raise StartupError(f'mavlink_bridge_node: {exc}') from exc
        except ConnectionError as exc:
            raise StartupError(f'mavlink_bridge_node: {exc}') from exc
        self.create_subscription(TwistStamped, '/cmd_vel', self._guard('/cmd_vel', self._on_cmd), RELIABLE_QOS)
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
        self._mocap_warned: set[str] = set()      # one-time warnings about the mocap stream given
        if vision_cfg is not None:
            self.vision = VisionForwarder(vision_cfg)
            self.vision_lock = threading.Lock()
            self.create_subscription(PoseStamped, self.p['mocap_topic'], self._guard('mocap', self._on_mocap),
                                     SENSOR_QOS)
            self.create_timer(0.5 / vision_cfg.rate_hz, self._guard('vision', self._send_vision))
        self.origin_sent = self.ekf_origin is None
        self.create_timer(1.0, self._guard('diagnostics', self._update_diagnostics))
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

    def _guard(self, what: str, fn: Callable[..., None]) -> Callable[..., None]:
        """`fn` as a timer or subscription callback whose exceptions are counted and logged, never fatal."""
        def guarded(*args) -> None:
            try:
                fn(*args)
            except Exception as exc:  # noqa: BLE001 - nothing between the pilot and the vehicle may end the node
                self.diag.count('callback_errors')
                self._throttled.log(logging.ERROR, f'callback:{what}:{type(exc).__name__}',
                                    '%s callback failed (counted as callback_errors; continuing): %s: %s', what,
                                    type(exc).__name__, exc)
        return guarded

    # ------------------------------------------------------------------ callbacks from the core
    def _on_landed_state(self, state: int) -> None:
        """The vehicle's MAV_LANDED_STATE, at each report (the core refused any other value)."""
        if not self.context.ok():
            return
        try:
            self.pub_landed.publish(UInt8(data=int(state)))
        except RCLError:
            if self.context.ok():
                raise
            return
        self.diag.count('landed_state_published')
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
                                    (q.x, q.y, q.z, q.w), time.time(), source=msg.header.frame_id)
            events = dict(self.vision.events)
            source = self.vision.source
        if why is None:
            self.diag.count('mocap_in')
        else:
            self.diag.count(f'mocap_rejected_{why}')
            self._throttled.log(logging.WARNING, f'mocap:{why}', 'mocap pose refused (%s): frame %r, position '
                                '(%.6g, %.6g, %.6g); counted as mocap_rejected_%s', why, msg.header.frame_id,
                                pos.x, pos.y, pos.z, why)
        for key, value in events.items():
            self.diag.set(f'mocap_{key}', value)
        if why == 'other_source' or events.get('track_returned', 0) >= 2:
            self._warn_mocap('interleaved', f"mocap: poses on {self.p['mocap_topic']} come from more than one "
                             f'source (another frame_id, or jumps away from the track and back): forwarding only '
                             f'the track of frame {source!r}; the others are refused and counted '
                             '(mocap_rejected_other_source, mocap_rejected_jump_unconfirmed, mocap_track_returned)')

    def _warn_mocap(self, key: str, text: str) -> None:
        """Log a mocap problem once and keep it on /diagnostics (`mocap_warning`)."""
        if key in self._mocap_warned:
            return
        self._mocap_warned.add(key)
        self.diag.set('mocap_warning', text)
        self.get_logger().warning(text)

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
        if self.vision is not None:
            publishers = self.count_publishers(self.p['mocap_topic'])
            self.diag.set('mocap_publishers', publishers)
            if publishers > 1:
                self._warn_mocap('publishers', f"mocap: {publishers} publishers on {self.p['mocap_topic']}: only one "
                                 'track is forwarded (the first; see vision_reset_confirm_poses), the other poses are '
                                 'refused and counted')
        if snap['link'] == 'up' and not self.origin_sent:
            o = self.ekf_origin
            self.origin_sent = self.bridge.set_ekf_origin(o.latitude_deg, o.longitude_deg, o.altitude_m)
            if self.origin_sent:
                self.get_logger().info(f'EKF origin sent: {o.latitude_deg:.7f}, {o.longitude_deg:.7f}, '
                                       f'{o.altitude_m:.1f} m')
        if snap['link'] == 'up' and self._mocap_warned:
            self.diag.status(DiagnosticStatus.WARN, f"{snap['mode']} {'armed' if snap['armed'] else 'disarmed'}; "
                             'mocap from more than one source (see mocap_warning)')
        elif snap['link'] == 'up':
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
