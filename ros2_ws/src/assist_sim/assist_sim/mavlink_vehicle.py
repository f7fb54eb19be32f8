"""The sim as a Pixhawk: an ArduCopter 4.x stand-in speaking MAVLink 2 over a pymavlink link.

Wraps a LandingWorld and behaves, as far as a companion computer can tell, like ArduCopter in
GUIDED flight: HEARTBEAT with ArduCopter custom_mode numbers, SET_MODE / MAV_CMD_DO_SET_MODE,
arming with pre-arm refusal until the EKF has a position estimate, MAV_CMD_NAV_TAKEOFF in GUIDED,
LAND mode with disarm on touchdown, SET_POSITION_TARGET_LOCAL_NED velocity targets (LOCAL_NED and
BODY_(OFFSET_)NED frames) that expire after GUID_TIMEOUT, WP_YAW_BEHAVIOR (face the direction of
travel when yaw and yaw rate are left free), COMMAND_ACK with honest results, STATUSTEXT, and the
telemetry a bridge needs at rates set by MAV_CMD_SET_MESSAGE_INTERVAL or REQUEST_DATA_STREAM
(DISTANCE_SENSOR: a downward rangefinder reading the world's height_above_surface, as RNGFND1 does in
our SITL parameter file), and MAVLink 2 signing with a key file (the bridge's format: 32 raw bytes or
64 hex characters).

Telemetry goes out from `step`, so no message is sent faster than the step rate: sim_node steps at
its physics control rate (20 Hz), and a request for 30 Hz gets 20 Hz (ArduPilot likewise caps
streams at its scheduler rate); this is said once in the log when it happens.

Without an RC transmitter the manual modes (STABILIZE, ALT_HOLD, LOITER, POSHOLD) behave as
with centred sticks: the vehicle holds its position. Position setpoints are not emulated
(velocity only). Pure Python (numpy + pymavlink), no rclpy.

Frames: the world is ENU/FLU; LOCAL_NED's origin is the world origin (x_ned = y_enu,
y_ned = x_enu, z_ned = -z_enu); the world's yaw 0 (facing +x, East) is heading 90 deg.
"""
from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass, field
from struct import error as struct_error   # pymavlink can raise it on truncated frames
from typing import Any
from collections.abc import Callable

import numpy as np

os.environ['MAVLINK20'] = '1'  # MAVLink 2 framing; must be set before mavutil is imported
from pymavlink import mavutil

from assist_common.settings import check_named, setting
from assist_common.frames import (attitude_enu_flu_to_ned_frd, enu_to_ned, flu_to_frd, ned_to_enu,
                                  quat_to_matrix, yaw_rotation)
from assist_common.mavlink_io import (COPTER_MODE_NAMES, COPTER_MODES, FORCE_ARM_DISARM_MAGIC,
                                      enable_signing, load_signing_key, next_message, open_connection,
                                      refresh_signing_timestamp)

_LOG = logging.getLogger(__name__)
mavlink = mavutil.mavlink

# Modes this stand-in flies; the others exist on ArduCopter but are refused here.
SUPPORTED_MODES = frozenset({'STABILIZE', 'ALT_HOLD', 'GUIDED', 'LOITER', 'LAND', 'POSHOLD', 'BRAKE'})
ARMABLE_MODES = frozenset({'STABILIZE', 'ALT_HOLD', 'GUIDED', 'LOITER', 'POSHOLD'})
POSITION_MODES = frozenset({'GUIDED', 'LOITER', 'POSHOLD', 'BRAKE'})   # need an EKF position
GUIDED_FLAG_MODES = frozenset({'GUIDED', 'LOITER', 'POSHOLD', 'BRAKE', 'AUTO', 'RTL', 'CIRCLE'})

# SET_POSITION_TARGET_*.type_mask bits
POS_IGNORE = 0b0000_0000_0111
VEL_IGNORE = 0b0000_0011_1000
ACC_IGNORE = 0b0001_1100_0000
FORCE_SET = 0b0010_0000_0000
YAW_IGNORE = 0b0100_0000_0000
YAW_RATE_IGNORE = 0b1000_0000_0000
VELOCITY_FRAMES = frozenset({mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
                             mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED})
BODY_FRAMES = frozenset({mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED})

# Telemetry messages this vehicle can stream (id -> name) and ArduCopter's stream groups.
TELEMETRY = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 'HEARTBEAT',
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 'SYS_STATUS',
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 'ATTITUDE',
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 'LOCAL_POSITION_NED',
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 'GLOBAL_POSITION_INT',
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 'EXTENDED_SYS_STATE',
    mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR: 'DISTANCE_SENSOR',
}
STREAM_GROUPS = {
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: (mavlink.MAVLINK_MSG_ID_SYS_STATUS,),
    mavlink.MAV_DATA_STREAM_POSITION: (mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                                       mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED),
    mavlink.MAV_DATA_STREAM_EXTRA1: (mavlink.MAVLINK_MSG_ID_ATTITUDE,),
    mavlink.MAV_DATA_STREAM_EXTRA3: (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR),
}
STREAM_GROUPS[mavlink.MAV_DATA_STREAM_ALL] = tuple(m for g in list(STREAM_GROUPS.values()) for m in g)

EARTH_RADIUS_M = 6378137.0


def _wrap_pi(a: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass
class MavlinkVehicleConfig:
    """ArduCopter-like behaviour of the stand-in (parameter names in comments are ArduCopter's)."""

    system_id: int = setting(1, ge=1, le=255)                # SYSID_THISMAV
    component_id: int = setting(1, ge=1, le=255)             # MAV_COMP_ID_AUTOPILOT1
    heartbeat_interval_s: float = setting(1.0, gt=0.0, le=60.0)
    ekf_ready_delay_s: float = setting(3.0, ge=0.0, le=600.0)   # arming / GUIDED refused until the EKF has a position
    guid_timeout_s: float = setting(3.0, gt=0.0, le=60.0)     # GUID_TIMEOUT: velocity targets expire after this
    takeoff_speed_mps: float = setting(1.0, gt=0.0, le=10.0)  # WPNAV_SPEED_UP
    takeoff_alt_tolerance_m: float = setting(0.1, gt=0.0, le=10.0)   # takeoff complete within this of the target
    land_speed_mps: float = setting(0.5, gt=0.0, le=5.0)      # LAND_SPEED
    disarm_delay_s: float = setting(10.0, ge=0.0, le=600.0)   # DISARM_DELAY: auto-disarm after landed this long
    yaw_follow_min_speed_mps: float = setting(0.5, ge=0.0, le=10.0)   # 5 % of WPNAV_SPEED: slower keeps the heading
    yaw_slew_rate_rad_s: float = setting(1.05, gt=0.0, le=20.0)   # ATC_SLEW_YAW (60 deg/s) for auto-yaw
    hold_kp: float = setting(1.0, ge=0.0, le=20.0)            # 1/s, position hold (post-takeoff, timeout, BRAKE)
    hold_max_speed_mps: float = setting(1.0, gt=0.0, le=20.0)
    initial_mode: str = setting('STABILIZE', choices=tuple(sorted(SUPPORTED_MODES)))
    home_lat_deg: float = setting(-35.363261, ge=-90.0, le=90.0)     # SITL's CMAC field, for GLOBAL_POSITION_INT
    home_lon_deg: float = setting(149.165230, ge=-180.0, le=180.0)
    home_alt_m: float = setting(584.0, ge=-500.0, le=10_000.0)
    battery_voltage_v: float = setting(16.2, ge=0.0, le=100.0)
    # RNGFND1_MIN / _MAX of the downward rangefinder (DISTANCE_SENSOR)
    rangefinder_min_m: float = setting(0.05, ge=0.0, le=100.0)
    rangefinder_max_m: float = setting(15.0, gt=0.0, le=700.0)
    # Streams sent without being asked (message name -> interval s); ArduPilot's default is none.
    default_intervals_s: dict[str, float] = field(default_factory=dict)
    max_messages_per_step: int = setting(1000, ge=1, le=1_000_000)   # bound on incoming messages handled per step
    signing_key_file: str = ''               # MAVLink 2 signing key file; '' = unsigned

    def __post_init__(self) -> None:
        """ValueError (one line) for a setting outside its range or an unknown telemetry stream."""
        check_named(self, type(self).__name__)

    def check_relations(self) -> None:
        """Rules between fields, and the streams' names and intervals."""
        for name, interval in self.default_intervals_s.items():
            if name not in TELEMETRY.values():
                raise ValueError(f'default_intervals_s: unknown message {name!r}')
            if isinstance(interval, bool) or not isinstance(interval, (int, float)) or not interval > 0.0:
                raise ValueError(f'default_intervals_s: {name} interval must be a number > 0, got {interval!r}')
        if self.rangefinder_min_m >= self.rangefinder_max_m:
            raise ValueError(f'rangefinder_min_m must be < rangefinder_max_m ({self.rangefinder_max_m:g}), got '
                             f'{self.rangefinder_min_m:g}')


@dataclass
class _VelocityTarget:
    """A live GUIDED velocity target (NED) with its yaw directive."""

    vel_ned: np.ndarray
    received: float
    yaw_mode: str              # 'fixed' | 'rate' | 'follow'
    yaw_rate: float = 0.0      # rad/s, NED (clockwise positive)


class MavlinkVehicle:
    """ArduCopter 4.x stand-in on a pymavlink endpoint, flying a LandingWorld."""

    def __init__(self, world: Any, url: str, config: MavlinkVehicleConfig | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.world = world
        self.url = url
        self.cfg = config or MavlinkVehicleConfig()
        self._clock = clock
        self._boot = clock()
        key = load_signing_key(self.cfg.signing_key_file) if self.cfg.signing_key_file else None
        try:
            self._conn = open_connection(url, source_system=self.cfg.system_id,
                                         source_component=self.cfg.component_id)
        except (OSError, ValueError) as exc:
            raise ConnectionError(f'cannot open MAVLink endpoint {url!r}: {exc}') from exc
        if key is not None:
            enable_signing(self._conn, key)
        self._rate_capped_warned = False
        self._muted = False
        self.counters: dict[str, int] = {}
        self._intervals: dict[int, float] = {mavlink.MAVLINK_MSG_ID_HEARTBEAT: self.cfg.heartbeat_interval_s}
        name_to_id = {v: k for k, v in TELEMETRY.items()}
        for name, interval in self.cfg.default_intervals_s.items():
            self._intervals[name_to_id[name]] = float(interval)
        self._next_due: dict[int, float] = {}
        self.mode = self.cfg.initial_mode
        self._episode = None
        self._reset_flight_state()
        if getattr(world, 'scene', None) is None or not world.landed:
            world.reset(airborne=False)   # a vehicle powers up on the ground
        self._sync_episode()

    # ------------------------------------------------------------------ public API
    @property
    def armed(self) -> bool:
        """Motors armed."""
        return self._armed

    @property
    def ekf_ready(self) -> bool:
        """The emulated EKF has a position estimate (arming and GUIDED allowed)."""
        return self._clock() - self._boot >= self.cfg.ekf_ready_delay_s

    @property
    def guided_submode(self) -> str:
        """'idle' | 'takeoff' | 'velocity' | 'hold' (meaningful in GUIDED)."""
        return self._submode

    def reset(self, seed: int | None = None, **kwargs: Any):
        """Start a new episode landed and disarmed at the start pose; returns the world state."""
        state = self.world.reset(seed, airborne=False, **kwargs)
        self._sync_episode()
        return state

    def step(self, dt: float) -> None:
        """Handle pending MAVLink, fly the world for dt seconds, send telemetry that is due."""
        if not (dt > 0.0 and math.isfinite(dt)):
            raise ValueError(f'dt must be positive and finite, got {dt!r}')
        self._sync_episode()
        self._receive()
        refresh_signing_timestamp(self._conn)
        self._note_rate_cap(dt)
        now = self._clock()
        state = self.world.state
        cmd_enu = self._control(now, dt, state)
        self.world.set_yaw_target(_wrap_pi(math.pi / 2.0 - self._yaw_target_ned))
        cmd_flu = yaw_rotation(float(state.yaw)).T @ cmd_enu
        self.world.step(cmd_flu, dt)
        self._after_step(self._clock())
        self._send_telemetry(self._clock())

    def _note_rate_cap(self, dt: float) -> None:
        if self._rate_capped_warned:
            return
        capped = sorted(TELEMETRY[m] for m, interval in self._intervals.items() if interval < dt * 0.999)
        if capped:
            self._rate_capped_warned = True
            _LOG.info('%s requested faster than this vehicle steps (%.0f Hz): sent once per step',
                      ', '.join(capped), 1.0 / dt)

    def set_telemetry_muted(self, muted: bool) -> None:
        """Fault injection: stop (or resume) the telemetry streams, HEARTBEAT included, while still
        receiving and flying: a link lost in the vehicle -> companion direction only."""
        self._muted = bool(muted)

    def close(self) -> None:
        """Close the MAVLink endpoint."""
        self._conn.close()

    # ------------------------------------------------------------------ state helpers
    def _count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + n

    def _reset_flight_state(self) -> None:
        self._armed = False
        self._submode = 'idle'
        self._target: _VelocityTarget | None = None
        self._takeoff_alt = 0.0
        self._home = np.zeros(3)
        self._hold = np.zeros(3)
        self._landed_since: float | None = None
        self._yaw_target_ned = math.pi / 2.0

    def _sync_episode(self) -> None:
        """A new world episode (reset by us or by sim_node): landed, disarmed, heading as placed."""
        ep = getattr(self.world, 'episode', None)
        if ep == self._episode:
            return
        self._episode = ep
        self._reset_flight_state()
        self.world.set_armed(False)
        st = self.world.state
        self._yaw_target_ned = _wrap_pi(math.pi / 2.0 - float(st.yaw))
        self._hold = np.array(st.position, dtype=float)

    def _heading_ned(self, state) -> float:
        return _wrap_pi(math.pi / 2.0 - float(state.yaw))

    def _landed(self) -> bool:
        return bool(self.world.landed)

    def _time_boot_ms(self, now: float) -> int:
        return int(max(0.0, now - self._boot) * 1000.0) & 0xFFFFFFFF

    # ------------------------------------------------------------------ incoming
    def _next_message(self):
        """Next parsed message or None (UDP: a datagram's truncated tail is dropped and counted)."""
        return next_message(self._conn, lambda: self._count('rx_truncated'))

    def _receive(self) -> None:
        for _ in range(self.cfg.max_messages_per_step):
            try:
                msg = self._next_message()
            except (mavlink.MAVError, OSError, ValueError, IndexError, struct_error) as exc:
                self._count('rx_errors')
                _LOG.warning('MAVLink receive error on %s: %s', self.url, exc)
                continue
            if msg is None:
                return
            mtype = msg.get_type()
            if mtype == 'BAD_DATA':
                self._count('rx_bad_data')
                if 'signature' in str(getattr(msg, 'reason', '')):
                    self._count('rx_bad_signature')
                continue
            self._count('rx_messages')
            try:
                self._dispatch(msg, mtype)
            except (ValueError, TypeError, OverflowError) as exc:
                self._count('rx_rejected')
                _LOG.warning('rejected %s: %s', mtype, exc)

    def _for_us(self, msg) -> bool:
        ts = getattr(msg, 'target_system', 0)
        tc = getattr(msg, 'target_component', 0)
        return ts in (0, self.cfg.system_id) and tc in (0, self.cfg.component_id)

    def _dispatch(self, msg, mtype: str) -> None:
        if mtype in ('COMMAND_LONG', 'COMMAND_INT') and self._for_us(msg):
            self._handle_command(msg)
        elif mtype == 'SET_MODE' and msg.target_system in (0, self.cfg.system_id):
            result = self._set_mode_number(int(msg.custom_mode))
            self._ack(msg, mavlink.MAVLINK_MSG_ID_SET_MODE, result)
        elif mtype == 'SET_POSITION_TARGET_LOCAL_NED' and self._for_us(msg):
            self._handle_setpoint(msg)
        elif mtype == 'REQUEST_DATA_STREAM' and self._for_us(msg):
            self._handle_request_data_stream(msg)

    def _ack(self, msg, command: int, result: int) -> None:
        self._count(f'ack_{command}_{result}')    # counted first: a peer that sees the ACK sees the count
        self._conn.mav.command_ack_send(command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def _statustext(self, severity: int, text: str) -> None:
        self._conn.mav.statustext_send(severity, text.encode('ascii', 'replace')[:50])
        _LOG.info('STATUSTEXT %s', text)

    # ------------------------------------------------------------------ commands
    def _handle_command(self, msg) -> None:
        cmd = int(msg.command)
        params = [msg.param1, msg.param2, msg.param3, msg.param4]
        p7 = float(msg.z) if msg.get_type() == 'COMMAND_INT' else float(msg.param7)
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            result = self._arm_disarm(params[0], params[1])
        elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
            if not math.isfinite(params[1]):
                result = mavlink.MAV_RESULT_DENIED
            else:
                result = self._set_mode_number(int(params[1]))
        elif cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
            result = self._takeoff(p7)
        elif cmd == mavlink.MAV_CMD_NAV_LAND:
            result = self._set_mode_name('LAND')
        elif cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self._set_interval(params[0], params[1])
        elif cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            result = self._request_message(params[0])
        elif cmd == mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            result = self._reboot(params[0])
        else:
            result = mavlink.MAV_RESULT_UNSUPPORTED
        self._ack(msg, cmd, result)

    def _reboot(self, p1: float) -> int:
        """param1 1: reboot the autopilot (ArduPilot: only while disarmed); boot time and EKF start over."""
        if p1 != 1.0:
            return mavlink.MAV_RESULT_UNSUPPORTED
        if self._armed:
            return mavlink.MAV_RESULT_DENIED
        self._boot = self._clock()
        self._set_mode_name('STABILIZE')
        self._statustext(mavlink.MAV_SEVERITY_INFO, 'Rebooting')
        return mavlink.MAV_RESULT_ACCEPTED

    def _arm_disarm(self, p1: float, p2: float) -> int:
        forced = p2 == FORCE_ARM_DISARM_MAGIC
        if p1 == 1.0:
            if self._armed:
                return mavlink.MAV_RESULT_ACCEPTED
            if self.mode not in ARMABLE_MODES:
                self._statustext(mavlink.MAV_SEVERITY_CRITICAL, 'Arm: Mode not armable')
                return mavlink.MAV_RESULT_FAILED
            if not forced and not self.ekf_ready:
                self._statustext(mavlink.MAV_SEVERITY_CRITICAL, 'PreArm: Need Position Estimate')
                return mavlink.MAV_RESULT_FAILED
            st = self.world.state
            self._armed = True
            self.world.set_armed(True)
            self._home = np.array(st.position, dtype=float)
            self._hold = self._home.copy()
            self._landed_since = self._clock()
            self._submode = 'idle'
            self._target = None
            _LOG.info('armed in %s', self.mode)
            return mavlink.MAV_RESULT_ACCEPTED
        if p1 == 0.0:
            if not self._armed:
                return mavlink.MAV_RESULT_ACCEPTED
            if not forced and not self._landed():
                self._statustext(mavlink.MAV_SEVERITY_CRITICAL, 'Disarm: vehicle is flying')
                return mavlink.MAV_RESULT_FAILED
            self._disarm('command')
            return mavlink.MAV_RESULT_ACCEPTED
        return mavlink.MAV_RESULT_DENIED

    def _disarm(self, why: str) -> None:
        self._armed = False
        self.world.set_armed(False)
        self._submode = 'idle'
        self._target = None
        self._landed_since = None
        _LOG.info('disarmed (%s)', why)

    def _set_mode_number(self, number: int) -> int:
        name = COPTER_MODE_NAMES.get(number)
        if name is None:
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f'Mode change to {number} failed: unknown mode')
            return mavlink.MAV_RESULT_FAILED
        return self._set_mode_name(name)

    def _set_mode_name(self, name: str) -> int:
        if name not in SUPPORTED_MODES:
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f'Mode change to {name} failed: not supported')
            return mavlink.MAV_RESULT_FAILED
        if name in POSITION_MODES and not self.ekf_ready:
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f'Mode change to {name} failed: requires position')
            return mavlink.MAV_RESULT_FAILED
        if name == self.mode:
            return mavlink.MAV_RESULT_ACCEPTED
        self.mode = name
        self._target = None
        self._submode = 'idle'
        self._hold = np.array(self.world.state.position, dtype=float)
        _LOG.info('mode %s', name)
        return mavlink.MAV_RESULT_ACCEPTED

    def _takeoff(self, alt: float) -> int:
        if self.mode != 'GUIDED' or not self._armed or not self._landed():
            return mavlink.MAV_RESULT_FAILED
        if not (math.isfinite(alt) and alt > 0.0):
            return mavlink.MAV_RESULT_DENIED
        self._takeoff_alt = float(alt)
        self._hold = np.array(self.world.state.position, dtype=float)
        self._submode = 'takeoff'
        self._target = None
        return mavlink.MAV_RESULT_ACCEPTED

    def _set_interval(self, msg_id: float, interval_us: float) -> int:
        if not (math.isfinite(msg_id) and math.isfinite(interval_us)):
            return mavlink.MAV_RESULT_DENIED
        mid = int(msg_id)
        if mid not in TELEMETRY:
            return mavlink.MAV_RESULT_FAILED
        if interval_us < 0:
            self._intervals.pop(mid, None)
        elif interval_us == 0:
            default = {v: k for k, v in TELEMETRY.items()}
            name = TELEMETRY[mid]
            if mid == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
                self._intervals[mid] = self.cfg.heartbeat_interval_s
            elif name in self.cfg.default_intervals_s:
                self._intervals[default[name]] = self.cfg.default_intervals_s[name]
            else:
                self._intervals.pop(mid, None)
        else:
            self._intervals[mid] = interval_us * 1e-6
        self._next_due.pop(mid, None)
        return mavlink.MAV_RESULT_ACCEPTED

    def _request_message(self, msg_id: float) -> int:
        if not math.isfinite(msg_id) or int(msg_id) not in TELEMETRY:
            return mavlink.MAV_RESULT_FAILED
        self._send_one(int(msg_id), self._clock())
        return mavlink.MAV_RESULT_ACCEPTED

    def _handle_request_data_stream(self, msg) -> None:
        group = STREAM_GROUPS.get(int(msg.req_stream_id))
        if group is None:
            return
        for mid in group:
            if msg.start_stop == 0 or msg.req_message_rate == 0:
                self._intervals.pop(mid, None)
            else:
                self._intervals[mid] = 1.0 / float(msg.req_message_rate)
            self._next_due.pop(mid, None)

    # ------------------------------------------------------------------ setpoints
    def _handle_setpoint(self, msg) -> None:
        mask = int(msg.type_mask)
        if self.mode != 'GUIDED':
            self._count('setpoints_ignored_not_guided')
            return
        if (mask & VEL_IGNORE) or not (mask & POS_IGNORE) == POS_IGNORE or (mask & ACC_IGNORE) != ACC_IGNORE:
            self._count('setpoints_unsupported')
            return
        if int(msg.coordinate_frame) not in VELOCITY_FRAMES:
            self._count('setpoints_bad_frame')
            return
        vel = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        if not np.all(np.isfinite(vel)):
            self._count('setpoints_non_finite')
            return
        if not self._armed or (self._landed() and self._submode != 'takeoff'):
            self._count('setpoints_ignored_landed_or_disarmed')
            return
        heading = self._heading_ned(self.world.state)
        if int(msg.coordinate_frame) in BODY_FRAMES:   # ArduCopter's rotate_body_frame_to_NE
            vel = yaw_rotation(heading) @ vel
        if not (mask & YAW_IGNORE) and math.isfinite(msg.yaw):
            relative = int(msg.coordinate_frame) in BODY_FRAMES
            self._yaw_target_ned = _wrap_pi(float(msg.yaw) + (heading if relative else 0.0))
            target = _VelocityTarget(vel, self._clock(), 'fixed')
        elif not (mask & YAW_RATE_IGNORE) and math.isfinite(msg.yaw_rate):
            target = _VelocityTarget(vel, self._clock(), 'rate', float(msg.yaw_rate))
        else:
            target = _VelocityTarget(vel, self._clock(), 'follow')
        self._target = target
        self._submode = 'velocity'   # a velocity target cancels a takeoff in progress, as on ArduCopter
        self._count('setpoints_accepted')

    # ------------------------------------------------------------------ control
    def _hold_velocity(self, pos: np.ndarray) -> np.ndarray:
        err = self._hold - pos
        v = self.cfg.hold_kp * err
        n = float(np.linalg.norm(v))
        if n > self.cfg.hold_max_speed_mps:
            v *= self.cfg.hold_max_speed_mps / n
        return v

    def _control(self, now: float, dt: float, state) -> np.ndarray:
        """Velocity (world ENU) the emulated ArduCopter flies this step."""
        pos = np.array(state.position, dtype=float)
        if not self._armed:
            return np.zeros(3)
        if self.mode == 'LAND':
            v = self._hold_velocity(pos)
            v[2] = -self.cfg.land_speed_mps
            return v
        if self.mode != 'GUIDED':
            return np.zeros(3) if self._landed() else self._hold_velocity(pos)
        if self._submode == 'takeoff':
            v = self._hold_velocity(pos)
            v[2] = self.cfg.takeoff_speed_mps
            return v
        if self._submode == 'velocity' and self._target is not None:
            if now - self._target.received > self.cfg.guid_timeout_s:
                # GUID_TIMEOUT: ArduCopter zeroes the velocity target and stops
                self._submode = 'hold'
                self._hold = pos.copy()
                self._target = None
                self._count('guid_timeouts')
                _LOG.info('GUIDED velocity target timed out after %.1f s', self.cfg.guid_timeout_s)
                return np.zeros(3)
            self._update_yaw(dt)
            return ned_to_enu(self._target.vel_ned)
        if self._landed():
            return np.zeros(3)
        if self._submode == 'idle':
            self._submode = 'hold'
            self._hold = pos.copy()
        return self._hold_velocity(pos)

    def _update_yaw(self, dt: float) -> None:
        t = self._target
        if t.yaw_mode == 'rate':
            self._yaw_target_ned = _wrap_pi(self._yaw_target_ned + t.yaw_rate * dt)
        elif t.yaw_mode == 'follow':
            vn, ve = float(t.vel_ned[0]), float(t.vel_ned[1])
            if math.hypot(vn, ve) > self.cfg.yaw_follow_min_speed_mps:
                err = _wrap_pi(math.atan2(ve, vn) - self._yaw_target_ned)
                step = self.cfg.yaw_slew_rate_rad_s * dt
                self._yaw_target_ned = _wrap_pi(self._yaw_target_ned + max(-step, min(step, err)))

    def _after_step(self, now: float) -> None:
        if not self._armed:
            return
        state = self.world.state
        if self._submode == 'takeoff':
            if state.position[2] - self._home[2] >= self._takeoff_alt - self.cfg.takeoff_alt_tolerance_m:
                self._submode = 'hold'
                self._hold = np.array(state.position, dtype=float)
                _LOG.info('takeoff complete at %.2f m', state.position[2] - self._home[2])
            return
        if self._landed():
            if self.mode == 'LAND':
                self._disarm('LAND touchdown')
                return
            if self._landed_since is None:
                self._landed_since = now
            elif now - self._landed_since >= self.cfg.disarm_delay_s:
                self._disarm(f'landed for {self.cfg.disarm_delay_s:.0f} s (DISARM_DELAY)')
        else:
            self._landed_since = None

    # ------------------------------------------------------------------ telemetry
    def _send_telemetry(self, now: float) -> None:
        if self._muted:
            return
        for mid, interval in list(self._intervals.items()):
            due = self._next_due.get(mid)
            if due is None or now >= due:
                self._send_one(mid, now)
                # keep the schedule without drifting, but never burst after a stall
                late = due is None or now - due >= interval
                self._next_due[mid] = now + interval if late else due + interval

    def landed_state(self) -> int:
        """MAV_LANDED_STATE as EXTENDED_SYS_STATE reports it."""
        if not self._armed or (self._landed() and self._submode != 'takeoff'):
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self._submode == 'takeoff':
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if self.mode == 'LAND':
            return mavlink.MAV_LANDED_STATE_LANDING
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def _send_one(self, mid: int, now: float) -> None:
        mav = self._conn.mav
        st = self.world.state
        tb = self._time_boot_ms(now)
        if mid == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED \
                | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
            if self.mode in GUIDED_FLAG_MODES:
                base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
            if self._armed:
                base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            status = mavlink.MAV_STATE_ACTIVE if self._armed and not self._landed() else mavlink.MAV_STATE_STANDBY
            mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, base,
                               COPTER_MODES[self.mode], status)
        elif mid == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            sensors = (mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                       | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
                       | mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_AHRS)
            health = sensors if self.ekf_ready else sensors & ~mavlink.MAV_SYS_STATUS_AHRS
            mav.sys_status_send(sensors, sensors, health, 200, int(self.cfg.battery_voltage_v * 1000),
                                -1, -1, 0, 0, 0, 0, 0, 0)
        elif mid == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            roll, pitch, yaw = attitude_enu_flu_to_ned_frd(quat_to_matrix(st.quaternion))
            rates = flu_to_frd(st.angular_velocity)
            mav.attitude_send(tb, roll, pitch, yaw, *(float(x) for x in rates))
        elif mid == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            if not self.ekf_ready:
                return   # ArduPilot sends no local position before the EKF has an origin
            p = enu_to_ned(st.position)
            v = enu_to_ned(st.velocity)
            mav.local_position_ned_send(tb, *(float(x) for x in p), *(float(x) for x in v))
        elif mid == mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            if not self.ekf_ready:
                return
            p = enu_to_ned(st.position)
            v = enu_to_ned(st.velocity)
            lat = self.cfg.home_lat_deg + math.degrees(p[0] / EARTH_RADIUS_M)
            lon = self.cfg.home_lon_deg + math.degrees(
                p[1] / (EARTH_RADIUS_M * math.cos(math.radians(self.cfg.home_lat_deg))))
            rel = float(st.position[2] - self._home[2])
            hdg = int(round(math.degrees(self._heading_ned(st)) * 100.0)) % 36000
            mav.global_position_int_send(tb, int(lat * 1e7), int(lon * 1e7),
                                         int((self.cfg.home_alt_m + float(st.position[2])) * 1000),
                                         int(rel * 1000), int(v[0] * 100), int(v[1] * 100), int(v[2] * 100), hdg)
        elif mid == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            mav.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED, self.landed_state())
        elif mid == mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR:
            # ArduPilot sends what the sensor reads, in cm, with its limits (outside them: out of range)
            cm = int(round(min(max(float(st.height_above_surface), 0.0), 655.0) * 100.0))
            mav.distance_sensor_send(tb, int(round(self.cfg.rangefinder_min_m * 100.0)),
                                     int(round(self.cfg.rangefinder_max_m * 100.0)), cm,
                                     mavlink.MAV_DISTANCE_SENSOR_LASER, 0, mavlink.MAV_SENSOR_ROTATION_PITCH_270, 255)
        self._count(f'tx_{TELEMETRY[mid]}')

