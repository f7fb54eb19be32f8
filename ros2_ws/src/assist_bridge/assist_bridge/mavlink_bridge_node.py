"""mavlink_bridge_node: /cmd_vel (FLU) -> ArduCopter GUIDED velocity setpoints; telemetry -> /odom.

A thin rclpy shell over assist_bridge.bridge_core.MavlinkBridge (see that module for the rules).
Timeouts (command, link, ACK) run on the wall clock: the vehicle (real, SITL or the sim's
stand-in) always flies in real time.

Threads: the node spins a SingleThreadedExecutor (rclpy's MultiThreadedExecutor adds milliseconds of
scheduling tail to every /cmd_vel), the core's receive thread owns the MAVLink link, and the
services, which wait up to ack_timeout_s for the vehicle's COMMAND_ACK, are coroutines that await
that wait on a one-thread worker pool, so /cmd_vel is never held up behind a service call.
"""
from __future__ import annotations

import concurrent.futures
import logging
import math
import sys

from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import TwistStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.task import Future
from std_srvs.srv import Trigger

from assist_sim.ros_common import (RELIABLE_QOS, SENSOR_QOS, Diagnostics, Param, StartupError,
                                   declare_parameters, run_node, twist_to_array)

from .bridge_core import BridgeConfig, MavlinkBridge, Odometry as CoreOdometry

PARAMS = {
    'connection': Param('udpin:0.0.0.0:14550', "pymavlink address of the autopilot: 'udpin:HOST:PORT', "
                        "'udpout:HOST:PORT', 'tcp:HOST:PORT' (SITL serves tcp:127.0.0.1:5760), or a serial "
                        "device '/dev/ttyACM0' (baud from 'baud')."),
    'baud': Param(57600, 'Serial baud rate (serial connections only; 115200 for USB, 57600/921600 for TELEM).'),
    'target_system': Param(1, 'MAVLink system id of the autopilot (SYSID_THISMAV).'),
    'target_component': Param(1, 'MAVLink component id of the autopilot.'),
    'source_system': Param(255, 'Our MAVLink system id (ArduPilot accepts commands from SYSID_MYGCS = 255 by default).'),
    'source_component': Param(191, 'Our MAVLink component id (191 = onboard computer).'),
    'velocity_scale': Param(1.0, 'Commanded velocity is multiplied by this (0, 1]; use 0.5 on the real vehicle, '
                            'as in the paper.'),
    'max_speed_x_mps': Param(2.0, 'Clamp of the forward/back speed after scaling (m/s).'),
    'max_speed_y_mps': Param(2.0, 'Clamp of the left/right speed after scaling (m/s).'),
    'max_climb_mps': Param(1.0, 'Clamp of the climb speed (m/s).'),
    'max_descent_mps': Param(1.0, 'Clamp of the descent speed (m/s).'),
    'max_speed_mps': Param(2.5, 'Clamp of the total speed (m/s).'),
    'setpoint_rate_hz': Param(10.0, 'Re-send rate of the current velocity setpoint (ArduCopter GUID_TIMEOUT is 3 s).'),
    'command_timeout_s': Param(0.5, '/cmd_vel older than this counts as absent: zero velocity is sent.'),
    'link_timeout_s': Param(2.0, 'No autopilot HEARTBEAT for this long: link lost, setpoints stop.'),
    'odom_rate_hz': Param(30.0, 'Rate requested for LOCAL_POSITION_NED and ATTITUDE (drives /odom).'),
    'status_rate_hz': Param(2.0, 'Rate requested for EXTENDED_SYS_STATE and SYS_STATUS.'),
    'takeoff_altitude_m': Param(2.0, 'Altitude above the ground for /uav/takeoff (m).'),
    'ack_timeout_s': Param(3.0, 'How long a service waits for the COMMAND_ACK.'),
    'auto_guided': Param(True, 'Request GUIDED when commands arrive while the vehicle is in STABILIZE/ALT_HOLD/'
                         'LOITER/POSHOLD (never out of LAND, RTL, BRAKE or AUTO).'),
    'odom_frame': Param('odom', 'World frame id of /odom (ENU).'),
    'base_frame': Param('base_link', 'Body frame id of /odom and the accepted /cmd_vel frame (FLU).'),
}
ACCEPTED_CMD_FRAMES = ('', 'base_link')
_SEVERITY_LEVEL = {0: logging.ERROR, 1: logging.ERROR, 2: logging.ERROR, 3: logging.ERROR,
                   4: logging.WARNING, 5: logging.INFO, 6: logging.INFO, 7: logging.DEBUG}


class MavlinkBridgeNode(Node):
    """ROS 2 <-> ArduCopter bridge over pymavlink."""

    def __init__(self, **kwargs):
        super().__init__('mavlink_bridge_node', **kwargs)
        self.p = declare_parameters(self, PARAMS)
        self.diag = Diagnostics(self)
        keys = set(BridgeConfig.__dataclass_fields__) & set(self.p)
        try:
            self.cfg = BridgeConfig(**{k: self.p[k] for k in keys})
        except (ValueError, TypeError) as exc:
            raise StartupError(f'mavlink_bridge_node: bad parameter: {exc}') from exc
        try:
            self.bridge = MavlinkBridge(self.cfg, on_odometry=self._on_odometry,
                                        on_statustext=self._on_statustext, on_link=self._on_link)
        except ConnectionError as exc:
            raise StartupError(f'mavlink_bridge_node: {exc}') from exc
        self.pub_odom = self.create_publisher(Odometry, '/odom', SENSOR_QOS)
        self.create_subscription(TwistStamped, '/cmd_vel', self._on_cmd, RELIABLE_QOS)
        # one worker: vehicle commands run one at a time, in the order they were asked for
        self._workers = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix='uav-service')
        # a pending service coroutine holds its callback group until it returns: the services get a
        # reentrant group of their own so /cmd_vel and the timer (default group) run meanwhile
        services = ReentrantCallbackGroup()
        for name, action in (('arm', self.bridge.arm), ('disarm', self.bridge.disarm),
                             ('takeoff', self.bridge.takeoff), ('land', self.bridge.land)):
            self.create_service(Trigger, f'/uav/{name}', self._srv(name, action), callback_group=services)
        self.create_timer(1.0, self._update_diagnostics)
        self.bridge.start()
        self.get_logger().info(f"waiting for the vehicle heartbeat on '{self.cfg.connection}' "
                               f'(system {self.cfg.target_system}) ...')

    # ------------------------------------------------------------------ callbacks from the core
    def _on_odometry(self, o: CoreOdometry) -> None:
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
        self.pub_odom.publish(msg)
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

    def _on_link(self, up: bool, why: str) -> None:
        if up:
            self.get_logger().info(f"vehicle connected on '{self.cfg.connection}': {why}")
        else:
            self.get_logger().error(f"vehicle link lost on '{self.cfg.connection}': {why}; setpoints stopped, "
                                    'waiting for it to return')

    # ------------------------------------------------------------------ ROS inputs
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
            done = Future(executor=self.executor)
            # a done callback makes set_result (from the worker) wake the executor to resume us
            done.add_done_callback(lambda _f: None)

            def work() -> None:
                try:
                    done.set_result(action())
                except Exception as exc:  # noqa: BLE001 - handed to the awaiting service, logged there
                    done.set_exception(exc)
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
        if snap['link'] == 'up':
            self.diag.status(DiagnosticStatus.OK, f"{snap['mode']} {'armed' if snap['armed'] else 'disarmed'}")
        elif snap['link'] == 'lost':
            self.diag.status(DiagnosticStatus.ERROR, f'link lost ({self.cfg.connection})')
        else:
            self.diag.status(DiagnosticStatus.WARN, f'waiting for heartbeat ({self.cfg.connection})')
            self.get_logger().info(f"still waiting for the vehicle heartbeat on '{self.cfg.connection}'",
                                   throttle_duration_sec=10.0)

    def close(self) -> None:
        """Stop the service worker and the receive thread, and close the link."""
        self._workers.shutdown(wait=False, cancel_futures=True)
        self.bridge.close()


def main(args=None):
    """Console entry point."""
    sys.exit(run_node(lambda: MavlinkBridgeNode(), args))


if __name__ == '__main__':
    main()
