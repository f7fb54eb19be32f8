"""MAVLink bridge core: ROS-side velocity commands (FLU) -> ArduCopter GUIDED velocity setpoints.

Pure Python (numpy + pymavlink), no rclpy: mavlink_bridge_node is a thin shell over MavlinkBridge.
What it does, as ArduCopter needs it:
- opens a pymavlink connection (udpin:/udpout:/tcp:/tcpin:/serial device:baud), MAVLink 2;
- sends its own HEARTBEAT (onboard controller) at 1 Hz and tracks the autopilot's HEARTBEAT
  (mode, armed, link up/down after `link_timeout_s`, automatic recovery);
- asks for telemetry (ArduPilot sends nothing until asked): MAV_CMD_SET_MESSAGE_INTERVAL per
  message plus REQUEST_DATA_STREAM for older firmware, again whenever the link comes back;
- turns each command into SET_POSITION_TARGET_LOCAL_NED (velocity + absolute yaw, so the copter
  holds its heading instead of turning to face its travel), sends it at once and re-sends the
  current one at `setpoint_rate_hz` so GUID_TIMEOUT never fires while a command is live; after
  `command_timeout_s` without a command it sends zero velocity; no setpoints while the link is
  down, while disarmed, during a takeoff climb (a velocity target would cancel it) or outside GUIDED;
- safety: non-finite commands rejected, velocity_scale, per-axis and total speed clamps;
- arm / disarm / takeoff / land / set_mode as COMMAND_LONG, waiting for the honest COMMAND_ACK.
"""
from __future__ import annotations

import collections
import logging
import math
import os
import threading
import time
from dataclasses import dataclass, field
from struct import error as struct_error
from typing import Callable, Sequence

import numpy as np

os.environ['MAVLINK20'] = '1'  # MAVLink 2 framing; must be set before mavutil is imported
from pymavlink import mavutil  # noqa: E402

from assist_sim.mavlink_io import next_message  # noqa: E402

from . import frames  # noqa: E402

_LOG = logging.getLogger(__name__)
mavlink = mavutil.mavlink

COPTER_MODES: dict[str, int] = {
    'STABILIZE': 0, 'ACRO': 1, 'ALT_HOLD': 2, 'AUTO': 3, 'GUIDED': 4, 'LOITER': 5, 'RTL': 6,
    'CIRCLE': 7, 'LAND': 9, 'DRIFT': 11, 'SPORT': 13, 'FLIP': 14, 'AUTOTUNE': 15, 'POSHOLD': 16,
    'BRAKE': 17, 'THROW': 18, 'AVOID_ADSB': 19, 'GUIDED_NOGPS': 20, 'SMART_RTL': 21,
}
MODE_NAMES = {v: k for k, v in COPTER_MODES.items()}
# The bridge switches to GUIDED by itself only from these pilot-flown modes, never out of
# LAND / RTL / BRAKE / AUTO, which a pilot or failsafe chose on purpose.
AUTO_GUIDED_FROM = frozenset({'STABILIZE', 'ALT_HOLD', 'LOITER', 'POSHOLD'})

# SET_POSITION_TARGET_LOCAL_NED.type_mask: use vx, vy, vz and yaw; ignore position,
# acceleration and yaw rate (0x09C7).
TYPE_MASK_VELOCITY_YAW = (
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE)

RESULT_NAMES = {k: v.name.replace('MAV_RESULT_', '') for k, v in mavlink.enums['MAV_RESULT'].items()}


def result_name(result: int | None) -> str:
    """MAV_RESULT number -> short name ('ACCEPTED', 'FAILED', ...)."""
    if result is None:
        return 'NO_ACK'
    return RESULT_NAMES.get(int(result), str(result))


@dataclass
class BridgeConfig:
    """Everything the bridge needs; node parameters map 1:1 onto these fields."""

    connection: str = 'udpin:0.0.0.0:14550'
    baud: int = 57600                      # serial links only
    source_system: int = 255
    source_component: int = 191            # MAV_COMP_ID_ONBOARD_COMPUTER
    target_system: int = 1
    target_component: int = 1
    velocity_scale: float = 1.0            # the paper halves the output on the real vehicle: 0.5
    max_speed_x_mps: float = 2.0           # per-axis clamps (body FLU, after scaling)
    max_speed_y_mps: float = 2.0
    max_climb_mps: float = 1.0
    max_descent_mps: float = 1.0
    max_speed_mps: float = 2.5             # total speed clamp
    command_timeout_s: float = 0.5         # no command for this long -> zero velocity
    setpoint_rate_hz: float = 10.0         # re-send rate of the current setpoint
    link_timeout_s: float = 2.0            # no autopilot HEARTBEAT for this long -> link lost
    heartbeat_rate_hz: float = 1.0         # our own HEARTBEAT
    odom_rate_hz: float = 30.0             # LOCAL_POSITION_NED + ATTITUDE requested at this rate
    status_rate_hz: float = 2.0            # EXTENDED_SYS_STATE, SYS_STATUS
    stream_request_period_s: float = 5.0   # re-ask for streams while no position arrives
    ack_timeout_s: float = 3.0
    takeoff_altitude_m: float = 2.0
    takeoff_done_margin_m: float = 0.15    # climb done within this of the target altitude
    auto_guided: bool = True               # switch to GUIDED when commands arrive in a pilot mode
    mode_request_period_s: float = 1.0
    max_messages_per_poll: int = 1000

    def __post_init__(self) -> None:
        positive = ('max_speed_x_mps', 'max_speed_y_mps', 'max_climb_mps', 'max_descent_mps',
                    'max_speed_mps', 'command_timeout_s', 'setpoint_rate_hz', 'link_timeout_s',
                    'heartbeat_rate_hz', 'odom_rate_hz', 'status_rate_hz', 'ack_timeout_s',
                    'takeoff_altitude_m')
        for name in positive:
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f'{name} must be a positive finite number, got {v!r}')
        if not (math.isfinite(self.velocity_scale) and 0.0 < self.velocity_scale <= 1.0):
            raise ValueError(f'velocity_scale must be in (0, 1], got {self.velocity_scale!r}')
        if not self.connection:
            raise ValueError('connection must not be empty')


def limit_velocity(v_flu: Sequence[float], cfg: BridgeConfig) -> np.ndarray:
    """Scale and clamp a body-FLU velocity command; non-finite input raises ValueError."""
    v = np.asarray(v_flu, dtype=float).reshape(-1)
    if v.shape != (3,):
        raise ValueError(f'velocity must have 3 components, got {v.shape}')
    if not np.all(np.isfinite(v)):
        raise ValueError(f'non-finite velocity {v.tolist()}')
    v = v * cfg.velocity_scale
    v[0] = float(np.clip(v[0], -cfg.max_speed_x_mps, cfg.max_speed_x_mps))
    v[1] = float(np.clip(v[1], -cfg.max_speed_y_mps, cfg.max_speed_y_mps))
    v[2] = float(np.clip(v[2], -cfg.max_descent_mps, cfg.max_climb_mps))
    n = float(np.linalg.norm(v))
    if n > cfg.max_speed_mps:
        v *= cfg.max_speed_mps / n
    return v


def velocity_setpoint(v_flu: Sequence[float], yaw_enu: float) -> dict:
    """Fields of SET_POSITION_TARGET_LOCAL_NED for body-FLU velocity with heading held at yaw_enu."""
    vn, ve, vd = frames.flu_velocity_to_ned(v_flu, yaw_enu)
    return dict(coordinate_frame=mavlink.MAV_FRAME_LOCAL_NED, type_mask=TYPE_MASK_VELOCITY_YAW,
                vx=float(vn), vy=float(ve), vz=float(vd), yaw=frames.yaw_enu_to_ned(yaw_enu))


@dataclass
class Odometry:
    """Vehicle odometry in ROS frames: pose in odom (ENU), twist in base_link (FLU)."""

    position: np.ndarray
    quaternion: np.ndarray          # x, y, z, w (odom -> base_link)
    linear_velocity: np.ndarray     # base_link FLU
    angular_velocity: np.ndarray    # base_link FLU
    yaw: float                      # ROS yaw (ENU)


@dataclass
class VehicleStatus:
    """What the bridge knows about the autopilot (guarded by the bridge lock)."""

    link_up: bool = False
    ever_connected: bool = False
    last_heartbeat: float | None = None
    mode: str = 'UNKNOWN'
    armed: bool = False
    system_status: int = 0
    landed_state: int = 0
    position_ned: np.ndarray | None = None
    velocity_ned: np.ndarray | None = None
    last_position: float | None = None
    attitude: tuple[float, float, float] | None = None     # roll, pitch, yaw (NED/FRD)
    rates_frd: np.ndarray = field(default_factory=lambda: np.zeros(3))


class MavlinkBridge:
    """The bridge: one MAVLink connection, a receive thread, and setpoint/command logic."""

    def __init__(self, cfg: BridgeConfig, clock: Callable[[], float] = time.monotonic,
                 on_odometry: Callable[[Odometry], None] | None = None,
                 on_statustext: Callable[[int, str], None] | None = None,
                 on_link: Callable[[bool, str], None] | None = None):
        self.cfg = cfg
        self._clock = clock
        self._on_odometry = on_odometry
        self._on_statustext = on_statustext
        self._on_link = on_link
        self._boot = clock()
        try:
            self.conn = mavutil.mavlink_connection(
                cfg.connection, baud=cfg.baud, source_system=cfg.source_system,
                source_component=cfg.source_component, dialect='ardupilotmega', autoreconnect=True)
        except Exception as exc:   # pymavlink raises OSError, ValueError or bare Exception
            raise ConnectionError(f'cannot open MAVLink connection {cfg.connection!r}: {exc}') from exc
        self.conn.mav.robust_parsing = True
        self._lock = threading.RLock()
        self._send_lock = threading.Lock()
        self._ack_cond = threading.Condition(self._lock)
        self._acks: dict[int, tuple[int, float]] = {}
        self.status = VehicleStatus()
        self.counters: collections.Counter[str] = collections.Counter()
        self.statustexts: collections.deque[tuple[float, int, str]] = collections.deque(maxlen=50)
        self._cmd = np.zeros(3)
        self._cmd_time: float | None = None
        self._hold_yaw_enu: float | None = None
        self._takeoff_until_alt: float | None = None
        self._takeoff_deadline = 0.0
        self._last_setpoint_time = -math.inf
        self._next_setpoint_due = -math.inf
        self._last_heartbeat_sent = -math.inf
        self._last_stream_request = -math.inf
        self._last_mode_request = -math.inf
        self._mode_warned: str | None = None
        self.last_setpoint: dict | None = None
        self._running = False
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Start the receive thread (it also runs the periodic tick)."""
        self._running = True
        self._thread = threading.Thread(target=self._loop, name='mavlink-rx', daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the receive thread and close the connection."""
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.conn.close()

    def _loop(self) -> None:
        while self._running:
            try:
                now = self._clock()
                wake = min(self._next_setpoint_due, self._last_heartbeat_sent + 1.0 / self.cfg.heartbeat_rate_hz)
                self.conn.select(min(max(wake - now, 0.0), 0.02))
                self.poll()
                self.tick()
            except Exception as exc:   # keep the link alive whatever one message did; counted
                self.counters['loop_errors'] += 1
                _LOG.error('MAVLink loop error (continuing): %s: %s', type(exc).__name__, exc)
                time.sleep(0.01)

    def time_boot_ms(self) -> int:
        """Milliseconds since the bridge started (MAVLink time_boot_ms)."""
        return int((self._clock() - self._boot) * 1000.0) & 0xFFFFFFFF

    # ------------------------------------------------------------------ receiving
    def _next_message(self):
        """Next message or None (UDP: a datagram's truncated tail is dropped and counted)."""
        return next_message(self.conn, self._count_truncated)

    def _count_truncated(self) -> None:
        self.counters['rx_truncated'] += 1

    def poll(self) -> int:
        """Handle every pending incoming message (non-blocking); returns how many were handled."""
        n = 0
        for _ in range(self.cfg.max_messages_per_poll):
            try:
                msg = self._next_message()
            except (mavlink.MAVError, OSError, ValueError, IndexError, struct_error) as exc:
                self.counters['rx_errors'] += 1
                _LOG.warning('MAVLink receive error: %s', exc)
                continue
            if msg is None:
                break
            n += 1
            mtype = msg.get_type()
            if mtype == 'BAD_DATA':
                self.counters['rx_bad_data'] += 1
                continue
            try:
                self._handle(msg, mtype)
            except (ValueError, TypeError, OverflowError, AttributeError) as exc:
                self.counters['rx_rejected'] += 1
                _LOG.warning('rejected %s: %s', mtype, exc)
        return n

    def _handle(self, msg, mtype: str) -> None:
        if msg.get_srcSystem() != self.cfg.target_system:
            self.counters['rx_other_system'] += 1
            return
        now = self._clock()
        if mtype == 'HEARTBEAT':
            if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID or msg.get_srcComponent() != self.cfg.target_component:
                return
            with self._lock:
                st = self.status
                st.last_heartbeat = now
                old_mode = st.mode
                st.mode = MODE_NAMES.get(int(msg.custom_mode), f'MODE_{msg.custom_mode}')
                if old_mode == 'GUIDED' and st.mode != 'GUIDED':
                    self._takeoff_until_alt = None
                was_armed = st.armed
                st.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                st.system_status = int(msg.system_status)
                if was_armed and not st.armed:
                    self._hold_yaw_enu = None
                    self._takeoff_until_alt = None
                came_up = not st.link_up
                st.link_up = True
            if came_up:
                self._link_changed(True, f'vehicle heartbeat (system {msg.get_srcSystem()}, '
                                         f'mode {self.status.mode})')
        elif mtype == 'LOCAL_POSITION_NED':
            odom = None
            with self._lock:
                st = self.status
                st.position_ned = np.array([msg.x, msg.y, msg.z], dtype=float)
                st.velocity_ned = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
                st.last_position = now
                if st.attitude is not None:
                    odom = self._odometry_locked()
                self._check_takeoff_locked(now)
            if odom is not None and self._on_odometry is not None:
                self._on_odometry(odom)
        elif mtype == 'ATTITUDE':
            vals = (msg.roll, msg.pitch, msg.yaw, msg.rollspeed, msg.pitchspeed, msg.yawspeed)
            if not all(math.isfinite(v) for v in vals):
                raise ValueError('non-finite ATTITUDE')
            with self._lock:
                self.status.attitude = (float(msg.roll), float(msg.pitch), float(msg.yaw))
                self.status.rates_frd = np.array(vals[3:], dtype=float)
        elif mtype == 'EXTENDED_SYS_STATE':
            with self._lock:
                self.status.landed_state = int(msg.landed_state)
        elif mtype == 'COMMAND_ACK':
            with self._ack_cond:
                self._acks[int(msg.command)] = (int(msg.result), now)
                self._ack_cond.notify_all()
            self.counters[f'ack_{result_name(msg.result).lower()}'] += 1
        elif mtype == 'STATUSTEXT':
            text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode('ascii', 'replace')
            text = text.rstrip('\x00')
            with self._lock:
                self.statustexts.append((now, int(msg.severity), text))
            if self._on_statustext is not None:
                self._on_statustext(int(msg.severity), text)

    def _odometry_locked(self) -> Odometry:
        st = self.status
        r = frames.attitude_ned_frd_to_enu_flu(*st.attitude)
        v_enu = frames.ned_to_enu(st.velocity_ned)
        return Odometry(position=frames.ned_to_enu(st.position_ned), quaternion=frames.matrix_to_quaternion(r),
                        linear_velocity=r.T @ v_enu, angular_velocity=frames.frd_to_flu(st.rates_frd),
                        yaw=frames.yaw_ned_to_enu(st.attitude[2]))

    def _link_changed(self, up: bool, why: str) -> None:
        if up:
            _LOG.info('MAVLink link up: %s', why)
            self.counters['link_up_events'] += 1
            with self._lock:
                self.status.ever_connected = True
            self.request_streams()
        else:
            _LOG.error('MAVLink link lost: %s; setpoints stopped', why)
            self.counters['link_lost_events'] += 1
        if self._on_link is not None:
            self._on_link(up, why)

    # ------------------------------------------------------------------ sending
    def _send(self, fn_name: str, *args) -> None:
        with self._send_lock:
            getattr(self.conn.mav, fn_name)(*args)

    def request_streams(self) -> None:
        """Ask the autopilot for the telemetry the bridge uses (both ways ArduPilot understands)."""
        self._last_stream_request = self._clock()
        c = self.cfg
        odom_hz = int(max(1, round(c.odom_rate_hz)))
        stat_hz = int(max(1, round(c.status_rate_hz)))
        for stream, hz in ((mavlink.MAV_DATA_STREAM_POSITION, odom_hz), (mavlink.MAV_DATA_STREAM_EXTRA1, odom_hz),
                           (mavlink.MAV_DATA_STREAM_EXTENDED_STATUS, stat_hz),
                           (mavlink.MAV_DATA_STREAM_EXTRA3, stat_hz)):
            self._send('request_data_stream_send', c.target_system, c.target_component, stream, hz, 1)
        for mid, hz in ((mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, c.odom_rate_hz),
                        (mavlink.MAVLINK_MSG_ID_ATTITUDE, c.odom_rate_hz),
                        (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, c.status_rate_hz),
                        (mavlink.MAVLINK_MSG_ID_SYS_STATUS, c.status_rate_hz)):
            self._send('command_long_send', c.target_system, c.target_component,
                       mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, float(mid), 1e6 / hz, 0, 0, 0, 0, 0)
        self.counters['stream_requests'] += 1

    def set_command(self, v_flu: Sequence[float], now: float | None = None) -> np.ndarray:
        """Accept a body-FLU velocity command (ValueError if non-finite); sends a setpoint at once."""
        now = self._clock() if now is None else now
        v = limit_velocity(v_flu, self.cfg)
        with self._lock:
            self._cmd = v
            self._cmd_time = now
            self._maybe_send_setpoint_locked(now, force=True)
        return v

    def command_live(self, now: float | None = None) -> bool:
        """A command younger than command_timeout_s exists."""
        now = self._clock() if now is None else now
        with self._lock:
            return self._cmd_time is not None and now - self._cmd_time <= self.cfg.command_timeout_s

    def current_command(self, now: float | None = None) -> np.ndarray:
        """The velocity the bridge flies now: the last command, or zero after the timeout."""
        return self._cmd.copy() if self.command_live(now) else np.zeros(3)

    def tick(self, now: float | None = None) -> None:
        """Periodic work: own heartbeat, link watchdog, stream re-requests, setpoint re-send."""
        now = self._clock() if now is None else now
        c = self.cfg
        if now - self._last_heartbeat_sent >= 1.0 / c.heartbeat_rate_hz:
            self._last_heartbeat_sent = now
            self._send('heartbeat_send', mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                       mavlink.MAV_STATE_ACTIVE)
        lost = False
        with self._lock:
            st = self.status
            if st.link_up and st.last_heartbeat is not None and now - st.last_heartbeat > c.link_timeout_s:
                st.link_up = False
                lost = True
        if lost:
            self._link_changed(False, f'no heartbeat for {c.link_timeout_s:.1f} s')
            return
        with self._lock:
            if (st.link_up and (st.last_position is None or now - st.last_position > c.stream_request_period_s)
                    and now - self._last_stream_request > c.stream_request_period_s):
                need = True
            else:
                need = False
            self._check_takeoff_locked(now)
            self._maybe_send_setpoint_locked(now, force=False)
        if need:
            self.request_streams()

    def _check_takeoff_locked(self, now: float) -> None:
        if self._takeoff_until_alt is None:
            return
        st = self.status
        alt = -float(st.position_ned[2]) if st.position_ned is not None else -math.inf
        if alt >= self._takeoff_until_alt or now > self._takeoff_deadline:
            _LOG.info('takeoff climb over (altitude %.2f m); velocity setpoints resume', alt)
            self._takeoff_until_alt = None

    def _maybe_send_setpoint_locked(self, now: float, force: bool) -> None:
        c = self.cfg
        period = 1.0 / c.setpoint_rate_hz
        if not force and now < self._next_setpoint_due:
            return
        # fixed-rate schedule (no drift); a late tick or a command re-anchors it
        self._next_setpoint_due = now + period if (force or now - self._next_setpoint_due > period) \
            else self._next_setpoint_due + period
        st = self.status
        if not st.link_up:
            self.counters['setpoints_suppressed_link'] += int(force)
            return
        live = self._cmd_time is not None and now - self._cmd_time <= c.command_timeout_s
        v = self._cmd if live else np.zeros(3)
        if st.mode != 'GUIDED':
            if live and st.armed and np.any(v != 0.0):
                self._handle_not_guided_locked(now)
            return
        self._mode_warned = None
        if not st.armed or self._takeoff_until_alt is not None:
            return
        if self._hold_yaw_enu is None:
            if st.attitude is None:
                return
            self._hold_yaw_enu = frames.yaw_ned_to_enu(st.attitude[2])
            _LOG.info('holding heading %.1f deg (NED) while flying velocity setpoints',
                      math.degrees(frames.yaw_enu_to_ned(self._hold_yaw_enu)))
        sp = velocity_setpoint(v, self._hold_yaw_enu)
        self._send('set_position_target_local_ned_send', self.time_boot_ms(), c.target_system,
                   c.target_component, sp['coordinate_frame'], sp['type_mask'], 0.0, 0.0, 0.0,
                   sp['vx'], sp['vy'], sp['vz'], 0.0, 0.0, 0.0, sp['yaw'], 0.0)
        self._last_setpoint_time = now
        self.last_setpoint = sp
        self.counters['setpoints_sent'] += 1
        if not live:
            self.counters['setpoints_zero_timeout'] += 1

    def _handle_not_guided_locked(self, now: float) -> None:
        mode = self.status.mode
        if self.cfg.auto_guided and mode in AUTO_GUIDED_FROM:
            if now - self._last_mode_request >= self.cfg.mode_request_period_s:
                self._last_mode_request = now
                _LOG.warning('vehicle in %s: requesting GUIDED before sending velocity setpoints', mode)
                self._send('command_long_send', self.cfg.target_system, self.cfg.target_component,
                           mavlink.MAV_CMD_DO_SET_MODE, 0, float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
                           float(COPTER_MODES['GUIDED']), 0, 0, 0, 0, 0)
        elif self._mode_warned != mode:
            self._mode_warned = mode
            _LOG.warning('vehicle in %s: velocity setpoints not sent (ArduCopter ignores them outside '
                         'GUIDED; switch to GUIDED to fly commands)', mode)

    # ------------------------------------------------------------------ commands with ACK
    def command_long(self, command: int, params: Sequence[float], timeout: float | None = None) -> int | None:
        """Send COMMAND_LONG and wait for its COMMAND_ACK; returns MAV_RESULT or None on timeout.

        Needs the receive thread (start()) or another thread calling poll().
        """
        timeout = self.cfg.ack_timeout_s if timeout is None else timeout
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        t0 = self._clock()
        with self._ack_cond:
            self._acks.pop(int(command), None)
        self._send('command_long_send', self.cfg.target_system, self.cfg.target_component, int(command), 0, *p)
        deadline = time.monotonic() + timeout
        with self._ack_cond:
            while True:
                ack = self._acks.get(int(command))
                if ack is not None and ack[1] >= t0:
                    return ack[0]
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._ack_cond.wait(left)

    def _texts_since(self, t0: float) -> list[str]:
        with self._lock:
            return [t for (ts, _, t) in self.statustexts if ts >= t0]

    def _report(self, what: str, result: int | None, t0: float) -> tuple[bool, str]:
        texts = self._texts_since(t0)
        ok = result == mavlink.MAV_RESULT_ACCEPTED
        if result is None:
            msg = f'{what}: no COMMAND_ACK within {self.cfg.ack_timeout_s:.1f} s'
        else:
            msg = f'{what}: {result_name(result)}'
        if texts and not ok:
            msg += ' (' + '; '.join(texts) + ')'
        return ok, msg

    def _require_link(self, what: str) -> tuple[bool, str] | None:
        with self._lock:
            if not self.status.link_up:
                return False, f'{what}: no link to the vehicle ({self.cfg.connection})'
        return None

    def set_mode(self, name: str) -> tuple[bool, str]:
        """Change flight mode (MAV_CMD_DO_SET_MODE); (accepted, honest message)."""
        if name not in COPTER_MODES:
            return False, f'set_mode: unknown ArduCopter mode {name!r}'
        refused = self._require_link(f'set_mode {name}')
        if refused:
            return refused
        t0 = self._clock()
        r = self.command_long(mavlink.MAV_CMD_DO_SET_MODE,
                              [mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_MODES[name]])
        ok, msg = self._report(f'set_mode {name}', r, t0)
        if ok:
            with self._lock:
                self.status.mode = name     # the next HEARTBEAT confirms it
        return ok, msg

    def arm(self) -> tuple[bool, str]:
        """Switch to GUIDED, then arm; reports the vehicle's COMMAND_ACK (and any PreArm text)."""
        refused = self._require_link('arm')
        if refused:
            return refused
        ok, msg = self.set_mode('GUIDED')
        if not ok:
            return False, f'arm: {msg}'
        t0 = self._clock()
        r = self.command_long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [1.0])
        ok, msg = self._report('arm', r, t0)
        if ok:
            with self._lock:
                self.status.armed = True    # the next HEARTBEAT confirms it
                self._hold_yaw_enu = None if self.status.attitude is None else \
                    frames.yaw_ned_to_enu(self.status.attitude[2])
        return ok, msg

    def disarm(self) -> tuple[bool, str]:
        """Disarm (ArduCopter refuses while flying)."""
        refused = self._require_link('disarm')
        if refused:
            return refused
        t0 = self._clock()
        return self._report('disarm', self.command_long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, [0.0]), t0)

    def takeoff(self, altitude_m: float | None = None) -> tuple[bool, str]:
        """MAV_CMD_NAV_TAKEOFF to `altitude_m` (default from config); setpoints pause during the climb."""
        alt = self.cfg.takeoff_altitude_m if altitude_m is None else float(altitude_m)
        if not (math.isfinite(alt) and alt > 0):
            return False, f'takeoff: bad altitude {alt!r}'
        refused = self._require_link('takeoff')
        if refused:
            return refused
        t0 = self._clock()
        with self._lock:
            ground = -float(self.status.position_ned[2]) if self.status.position_ned is not None else 0.0
            # pause setpoints before the command goes out: a velocity target would cancel the climb
            self._takeoff_until_alt = ground + alt - self.cfg.takeoff_done_margin_m
            self._takeoff_deadline = t0 + self.cfg.ack_timeout_s + alt / 0.3 + 5.0
        r = self.command_long(mavlink.MAV_CMD_NAV_TAKEOFF, [0, 0, 0, 0, 0, 0, alt])
        ok, msg = self._report(f'takeoff to {alt:.1f} m', r, t0)
        if not ok:
            with self._lock:
                self._takeoff_until_alt = None
        return ok, msg

    def land(self) -> tuple[bool, str]:
        """Switch to LAND (ArduCopter descends and disarms on touchdown)."""
        return self.set_mode('LAND')

    # ------------------------------------------------------------------ status
    def snapshot(self) -> dict:
        """Plain copy of the vehicle status for diagnostics."""
        with self._lock:
            st = self.status
            return dict(link='up' if st.link_up else ('lost' if st.ever_connected else 'waiting'),
                        mode=st.mode, armed=st.armed, landed_state=int(st.landed_state),
                        taking_off=self._takeoff_until_alt is not None,
                        command_live=self._cmd_time is not None
                        and self._clock() - self._cmd_time <= self.cfg.command_timeout_s)

    def wait_heartbeat(self, timeout: float) -> bool:
        """Block until the autopilot's heartbeat is seen (receive thread must run) or timeout."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if self.status.link_up:
                    return True
            time.sleep(0.02)
        return False
