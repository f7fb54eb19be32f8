"""MAVLink bridge core: ROS-side velocity commands (FLU) -> ArduCopter GUIDED velocity setpoints.

Pure Python (numpy + pymavlink), no rclpy: mavlink_bridge_node is a thin shell over MavlinkBridge.
What it does, as ArduCopter needs it:
- opens a vetted pymavlink connection (udpin:/udpout:/tcp:/tcpin:HOST:PORT or a serial device
  under /dev; anything else is refused), MAVLink 2, optionally signed (key file);
- locks onto the first autopilot HEARTBEAT with the configured system/component id (0 = any) and
  its source address; frames from other addresses or ids are dropped and counted (after a
  declared link loss the same ids may come back from the same host on a new port, `address_relock`);
- sends its own HEARTBEAT (onboard controller) at 1 Hz and tracks the autopilot's HEARTBEAT
  (mode, armed, link up/down after `link_timeout_s`, automatic recovery);
- asks for telemetry (ArduPilot sends nothing until asked): MAV_CMD_SET_MESSAGE_INTERVAL per
  message plus REQUEST_DATA_STREAM for older firmware, again whenever the link comes back;
- sends the latest command as SET_POSITION_TARGET_LOCAL_NED (velocity + absolute yaw, so the
  copter holds its heading) at `setpoint_rate_hz`, plus at most one immediate send of a changed
  command between two scheduled sends (so at most twice that rate whatever comes in); after
  `command_timeout_s` without a command it sends zero velocity; no setpoints while disarmed,
  during a takeoff climb (a velocity target would cancel it; the climb ends when the vehicle reports
  IN_AIR after TAKEOFF, reaches the takeoff altitude less `takeoff_done_margin_m`, or runs out of time)
  or outside GUIDED;
- link loss: zero velocity when the loss is declared and at `link_lost_setpoint_rate_hz` while
  it lasts (the link may be one-way), never the pilot's command;
- never changes the flight mode on its own: only set_mode / guided / land / arm (which selects
  GUIDED before arming a disarmed vehicle) do, each asked for through a service;
- safety: non-finite commands and telemetry rejected and counted, velocity_scale, per-axis and
  total speed clamps (changeable at run time through set_limits);
- arm / disarm / takeoff / land / set_mode as COMMAND_LONG, waiting for the honest COMMAND_ACK;
- the vehicle's landed state (EXTENDED_SYS_STATE) handed on at every report (changes logged)
  (`on_landed_state`); a value outside MAV_LANDED_STATE is refused and counted;
- touchdown envelope (assist_common.touchdown): the latest downward range from DISTANCE_SENSOR
  (orientation PITCH_270, within the sensor's own min/max, younger than `range_timeout_s`; anything
  else is an unknown range) goes with every velocity setpoint through TouchdownEnvelope, which turns a
  descent below `engage_range_m` into a vertical descent so ArduCopter's land detector declares the
  landing; it is reset when the vehicle disarms or takes off again after reporting ON_GROUND;
- nothing handed to it can end the link: a message that cannot be packed (a value that does not fit
  its field) or written is not sent, counted (`tx_errors`) and logged, throttled; every configured
  value is range-checked on creation (`setting(...)` rules, assist_common.settings).
"""
from __future__ import annotations

import collections
import dataclasses
import logging
import math
import os
import threading
import time
from dataclasses import dataclass, field
from struct import error as struct_error
from collections.abc import Callable, Sequence

import numpy as np

os.environ['MAVLINK20'] = '1'  # MAVLink 2 framing; must be set before mavutil is imported
from pymavlink import mavutil

from assist_common.mavlink_io import (COPTER_MODE_NAMES, COPTER_MODES, FORCE_ARM_DISARM_MAGIC,
                                      ThrottledLog, enable_signing, load_signing_key, next_message, open_connection,
                                      parse_endpoint, refresh_signing_timestamp)

from assist_common import frames
from assist_common.settings import check_named, setting
from assist_common.touchdown import TouchdownConfig, TouchdownEnvelope

_LOG = logging.getLogger(__name__)
mavlink = mavutil.mavlink

# SET_POSITION_TARGET_LOCAL_NED.type_mask: use vx, vy, vz and yaw; ignore position,
# acceleration and yaw rate (0x09C7).
TYPE_MASK_VELOCITY_YAW = (
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE)
# The same with yaw ignored and yaw rate 0 used: a brake when no heading is known yet (0x05C7).
TYPE_MASK_VELOCITY_YAW_RATE = (TYPE_MASK_VELOCITY_YAW & ~mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE) \
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE

RESULT_NAMES = {k: v.name.replace('MAV_RESULT_', '') for k, v in mavlink.enums['MAV_RESULT'].items()}
# MAV_LANDED_STATE values EXTENDED_SYS_STATE may carry (UNDEFINED 0 ... LANDING 4); anything else is refused
LANDED_STATES = {k: v.name.replace('MAV_LANDED_STATE_', '') for k, v in mavlink.enums['MAV_LANDED_STATE'].items()
                 if not v.name.endswith('_ENUM_END')}
# what packing or writing a message can raise: a value that does not fit its field, a dead serial port
SEND_ERRORS = (struct_error, OverflowError, ValueError, TypeError, OSError)
# DISTANCE_SENSOR.orientation of a rangefinder looking straight down (RNGFNDn_ORIENT 25)
RANGE_DOWN = mavlink.MAV_SENSOR_ROTATION_PITCH_270
LIMIT_FIELDS = ('velocity_scale', 'max_speed_x_mps', 'max_speed_y_mps', 'max_climb_mps', 'max_descent_mps',
                'max_speed_mps')


class NonFiniteTelemetry(ValueError):
    """A telemetry message with NaN or infinite fields."""


def result_name(result: int | None) -> str:
    """MAV_RESULT number -> short name ('ACCEPTED', 'FAILED', ...)."""
    if result is None:
        return 'NO_ACK'
    return RESULT_NAMES.get(int(result), str(result))


@dataclass
class BridgeConfig:
    """Everything the bridge needs; node parameters map 1:1 onto these fields (defaults and ranges from here).

    Every range is checked on creation (SettingsError, a ValueError): each value that reaches MAVLink
    fits its field, so no setting can make a message unpackable.
    """

    connection: str = 'udpin:127.0.0.1:14550'   # loopback: a remote sender cannot reach it
    baud: int = setting(57600, ge=1200, le=12000000)            # serial links only
    source_system: int = setting(255, ge=1, le=255)
    source_component: int = setting(191, ge=1, le=255)          # MAV_COMP_ID_ONBOARD_COMPUTER
    target_system: int = setting(1, ge=0, le=255)               # 0: lock onto the first autopilot's system id
    target_component: int = setting(1, ge=0, le=255)            # 0: lock onto the first autopilot's component id
    signing_key_file: str = ''             # MAVLink 2 signing key (32 raw bytes or 64 hex); '' = unsigned
    address_relock: bool = True            # after a declared loss, same ids from the same host on a new port
    velocity_scale: float = setting(1.0, gt=0.0, le=1.0)        # the paper halves the output on the real vehicle
    max_speed_x_mps: float = setting(2.0, gt=0.0, le=20.0)      # per-axis clamps (body FLU, after scaling)
    max_speed_y_mps: float = setting(2.0, gt=0.0, le=20.0)
    max_climb_mps: float = setting(1.0, gt=0.0, le=10.0)
    max_descent_mps: float = setting(1.0, gt=0.0, le=10.0)
    max_speed_mps: float = setting(2.5, gt=0.0, le=25.0)        # total speed clamp
    command_timeout_s: float = setting(0.5, ge=0.05, le=5.0)    # no command for this long -> zero velocity
    setpoint_rate_hz: float = setting(10.0, ge=1.0, le=50.0)    # current setpoint (+ <= 1 immediate send per period)
    link_timeout_s: float = setting(2.0, ge=0.5, le=30.0)       # no autopilot HEARTBEAT for this long -> link lost
    link_lost_setpoint_rate_hz: float = setting(2.0, ge=0.5, le=10.0)   # zero velocity while the link is lost
    heartbeat_rate_hz: float = setting(1.0, ge=0.2, le=10.0)    # our own HEARTBEAT
    odom_rate_hz: float = setting(30.0, ge=1.0, le=200.0)       # LOCAL_POSITION_NED + ATTITUDE requested at this rate
    status_rate_hz: float = setting(2.0, ge=0.1, le=50.0)       # EXTENDED_SYS_STATE, SYS_STATUS
    range_rate_hz: float = setting(20.0, ge=1.0, le=50.0)       # DISTANCE_SENSOR (downward range) requested
    range_timeout_s: float = setting(0.5, gt=0.0, le=5.0)       # an older downward range counts as unknown
    stream_request_period_s: float = setting(5.0, ge=0.5, le=600.0)   # re-ask for streams while no position
    ack_timeout_s: float = setting(3.0, ge=0.1, le=60.0)
    takeoff_altitude_m: float = setting(2.0, gt=0.0, le=100.0)
    takeoff_done_margin_m: float = setting(0.15, ge=0.0, le=1.0)   # climb done within this of the target altitude
    max_messages_per_poll: int = setting(1000, ge=1, le=100000)
    error_log_period_s: float = setting(5.0, gt=0.0, le=3600.0)   # errors: one line per kind per period
    allow_force_disarm: bool = False       # /uav/force_disarm stops the motors even in flight: sim/SITL only

    def __post_init__(self) -> None:
        check_named(self)
        parse_endpoint(self.connection)    # ValueError naming the accepted forms


@dataclass(frozen=True)
class EkfOrigin:
    """The EKF origin sent as SET_GPS_GLOBAL_ORIGIN (node parameter `ekf_origin`); ranges checked on creation."""

    latitude_deg: float = setting(0.0, ge=-90.0, le=90.0)
    longitude_deg: float = setting(0.0, ge=-180.0, le=180.0)
    altitude_m: float = setting(0.0, ge=-500.0, le=10000.0)     # AMSL: below the Dead Sea shore to above Everest

    def __post_init__(self) -> None:
        check_named(self)

    @classmethod
    def from_list(cls, values: Sequence[float]) -> EkfOrigin | None:
        """[latitude, longitude, altitude] -> EkfOrigin; [0.0] -> None (not sent); ValueError otherwise."""
        values = list(values)
        if values == [0.0]:
            return None
        if len(values) != 3:
            raise ValueError(f'must be [latitude deg, longitude deg, altitude m] or [0.0], got {values}')
        return cls(*values)


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


def downward_range_m(distance_m: float, min_m: float, max_m: float, orientation: int) -> float | None:
    """The downward range a rangefinder reading gives: None (unknown) unless the sensor faces down and the
    reading is finite and within the sensor's own [min, max]."""
    values = (distance_m, min_m, max_m)
    if int(orientation) != RANGE_DOWN or not all(math.isfinite(v) for v in values):
        return None
    if not min_m <= distance_m <= max_m:
        return None
    return float(distance_m)


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
class VehiclePeer:
    """The vehicle the bridge is locked onto: MAVLink ids and source address (None on streams)."""

    system: int
    component: int
    address: tuple | None

    def describe(self) -> str:
        """'1/1 at 127.0.0.1:5760' for logs and diagnostics."""
        where = f'{self.address[0]}:{self.address[1]}' if self.address else 'the link'
        return f'{self.system}/{self.component} at {where}'


@dataclass
class VehicleStatus:
    """What the bridge knows about the autopilot (guarded by the bridge lock)."""

    link_up: bool = False
    ever_connected: bool = False
    last_heartbeat: float | None = None
    mode: str = 'UNKNOWN'
    armed: bool = False
    system_status: int = 0
    landed_state: int | None = None      # MAV_LANDED_STATE from EXTENDED_SYS_STATE; None until one arrives
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
                 on_link: Callable[[bool, str], None] | None = None,
                 on_landed_state: Callable[[int], None] | None = None,
                 touchdown: TouchdownConfig | None = None):
        """`on_landed_state(state)` is called from the receive thread with every MAV_LANDED_STATE the vehicle
        reports (at status_rate_hz: a consumer can tell a current state from one a lost link left behind); the
        other callbacks likewise with odometry, STATUSTEXT and link changes. `touchdown` configures the
        envelope every setpoint passes through (default TouchdownConfig(); range-checked here)."""
        self.cfg = cfg
        touchdown = TouchdownConfig() if touchdown is None else touchdown
        check_named(touchdown)
        self.touchdown = TouchdownEnvelope(touchdown)
        self._range: tuple[float, float] | None = None     # (downward range m, receive time) of the latest reading
        self._clock = clock
        self._on_odometry = on_odometry
        self._on_statustext = on_statustext
        self._on_link = on_link
        self._on_landed_state = on_landed_state
        self._boot = clock()
        key = None
        if cfg.signing_key_file:
            key = load_signing_key(cfg.signing_key_file)    # ValueError: one line
        try:
            self.conn = open_connection(cfg.connection, baud=cfg.baud, source_system=cfg.source_system,
                                        source_component=cfg.source_component)
        except (OSError, ValueError) as exc:
            raise ConnectionError(f'cannot open MAVLink connection {cfg.connection!r}: {exc}') from exc
        except Exception as exc:   # pymavlink's serial/TCP classes raise bare Exception too
            raise ConnectionError(f'cannot open MAVLink connection {cfg.connection!r}: {exc}') from exc
        self.signing = key is not None
        if key is not None:
            enable_signing(self.conn, key)
        self._udp = isinstance(self.conn, mavutil.mavudp)
        self._lock = threading.RLock()
        self._send_lock = threading.Lock()
        self._ack_cond = threading.Condition(self._lock)
        self._acks: dict[int, tuple[int, float]] = {}
        self.status = VehicleStatus()
        self.peer: VehiclePeer | None = None
        self.counters: collections.Counter[str] = collections.Counter()
        self.counters['touchdown_engaged'] = 0     # on /diagnostics from the start
        self.statustexts: collections.deque[tuple[float, int, str]] = collections.deque(maxlen=50)
        self._throttled = ThrottledLog(_LOG, cfg.error_log_period_s, clock)
        self._cmd = np.zeros(3)
        self._cmd_time: float | None = None
        self._hold_yaw_enu: float | None = None
        self._takeoff_until_alt: float | None = None
        self._takeoff_deadline = 0.0
        self._next_setpoint_due = -math.inf
        self._immediate_ok = True        # one immediate send of a changed command per setpoint period
        self._sent_velocity: np.ndarray | None = None
        self._next_lost_setpoint = -math.inf
        self._last_heartbeat_sent = -math.inf
        self._last_stream_request = -math.inf
        self._mode_warned: str | None = None
        self._hb_mode, self._hb_armed = 'UNKNOWN', False    # as last reported by HEARTBEAT (for the log)
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
                wake = min(self._next_send_due(), self._last_heartbeat_sent + 1.0 / self.cfg.heartbeat_rate_hz)
                self.conn.select(min(max(wake - now, 0.0), 0.02))
                self.poll()
                self.tick()
            except Exception as exc:   # noqa: BLE001 - keep the link alive whatever one message did; counted, throttled
                self.counters['loop_errors'] += 1
                self._throttled.log(logging.ERROR, f'loop:{type(exc).__name__}',
                                    'MAVLink loop error (continuing): %s: %s', type(exc).__name__, exc)
                time.sleep(0.05)

    def _next_send_due(self) -> float:
        """When the loop next has a setpoint to send (inf: none while waiting or lost with a disarmed vehicle)."""
        st = self.status
        if st.link_up:
            return self._next_setpoint_due
        if self.peer is not None and st.armed:
            return self._next_lost_setpoint
        return math.inf

    def time_boot_ms(self) -> int:
        """Milliseconds since the bridge started (MAVLink time_boot_ms)."""
        return int((self._clock() - self._boot) * 1000.0) & 0xFFFFFFFF

    def set_limits(self, **changes: float) -> BridgeConfig:
        """Change velocity_scale and the speed clamps at run time (validated; ValueError refuses all)."""
        unknown = set(changes) - set(LIMIT_FIELDS)
        if unknown:
            raise ValueError(f'not changeable at run time: {", ".join(sorted(unknown))}')
        cfg = dataclasses.replace(self.cfg, **changes)
        with self._lock:
            self.cfg = cfg
        return cfg

    # ------------------------------------------------------------------ receiving
    def _next_message(self):
        """Next message or None (UDP: a datagram's truncated tail is dropped and counted)."""
        return next_message(self.conn, self._count_truncated, self._accept_datagram if self._udp else None)

    def _count_truncated(self) -> None:
        self.counters['rx_truncated'] += 1

    def _relock_allowed(self, address: tuple | None = None) -> bool:
        """After a declared loss (address_relock): the same vehicle ids from the same host, any port."""
        if not self.cfg.address_relock or self.status.link_up:
            return False
        peer = self.peer
        return address is None or peer is None or peer.address is None or address[0] == peer.address[0]

    def _accept_datagram(self, address: tuple) -> bool:
        """UDP source vetting before parsing: only the locked vehicle's address once locked."""
        peer = self.peer
        if peer is None or address == peer.address or self._relock_allowed(address):
            return True
        self.counters['rx_foreign_address'] += 1
        self._throttled.log(logging.WARNING, 'foreign_address', 'ignoring MAVLink from %s:%s: locked onto vehicle %s',
                            address[0], address[1], peer.describe())
        return False

    def poll(self) -> int:
        """Handle every pending incoming message (non-blocking); returns how many were handled."""
        n = 0
        for _ in range(self.cfg.max_messages_per_poll):
            try:
                msg = self._next_message()
            except (mavlink.MAVError, OSError, ValueError, IndexError, struct_error) as exc:
                self.counters['rx_errors'] += 1
                self._throttled.log(logging.WARNING, 'rx_error', 'MAVLink receive error: %s', exc)
                continue
            if msg is None:
                break
            n += 1
            mtype = msg.get_type()
            if mtype == 'BAD_DATA':
                self.counters['rx_bad_data'] += 1
                if 'signature' in str(getattr(msg, 'reason', '')):
                    self.counters['rx_bad_signature'] += 1
                    self._throttled.log(logging.WARNING, 'bad_signature',
                                        'dropped a MAVLink frame without a valid signature (from %s)',
                                        getattr(msg, 'src_address', None) or 'the link')
                continue
            try:
                self._handle(msg, mtype)
            except (ValueError, TypeError, OverflowError, AttributeError) as exc:
                self.counters['rx_rejected'] += 1
                if isinstance(exc, NonFiniteTelemetry):
                    self.counters['rx_non_finite'] += 1
                self._throttled.log(logging.WARNING, f'rejected:{mtype}', 'rejected %s: %s', mtype, exc)
        return n

    def _wanted(self, system: int, component: int) -> bool:
        c = self.cfg
        return c.target_system in (0, system) and c.target_component in (0, component)

    def _check_source(self, msg, mtype: str) -> bool:
        """Lock onto the first vehicle, then let only its frames through (the rest counted)."""
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        address = getattr(msg, 'src_address', None)
        is_autopilot_hb = mtype == 'HEARTBEAT' and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID
        peer = self.peer
        if peer is None:
            if is_autopilot_hb and self._wanted(*src):
                self._lock_onto(VehiclePeer(src[0], src[1], address))
                return True
            self.counters['rx_before_lock'] += 1
            return False
        if src != (peer.system, peer.component):
            self.counters['rx_foreign_id'] += 1
            self._throttled.log(logging.WARNING, 'foreign_id', 'ignoring MAVLink from system %d component %d: '
                                'locked onto vehicle %s', src[0], src[1], peer.describe())
            return False
        if address != peer.address:    # only reaches here while a relock is allowed
            if is_autopilot_hb and self._relock_allowed(address):
                _LOG.warning('vehicle %d/%d came back from a new address %s:%s (was %s)', src[0], src[1],
                             address[0], address[1], peer.describe())
                self._lock_onto(VehiclePeer(src[0], src[1], address))
                self.counters['vehicle_relocks'] += 1
                return True
            self.counters['rx_foreign_address'] += 1
            return False
        return True

    def _lock_onto(self, peer: VehiclePeer) -> None:
        with self._lock:
            self.peer = peer
        if self._udp and self.conn.udp_server and peer.address is not None:
            # udpin sends to every known client: from now on only to the vehicle
            self.conn.clients = {peer.address}
            self.conn.clients_last_alive = {peer.address: time.time()}
        self.counters['vehicle_locks'] += 1
        _LOG.info('locked onto vehicle %s%s', peer.describe(), ' (signed link)' if self.signing else '')

    def _handle(self, msg, mtype: str) -> None:
        if not self._check_source(msg, mtype):
            return
        now = self._clock()
        if mtype == 'HEARTBEAT':
            if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:
                return
            with self._lock:
                st = self.status
                st.last_heartbeat = now
                old_mode, was_armed = st.mode, st.armed
                reported_mode, reported_armed = self._hb_mode, self._hb_armed
                st.mode = COPTER_MODE_NAMES.get(int(msg.custom_mode), f'MODE_{msg.custom_mode}')
                if old_mode == 'GUIDED' and st.mode != 'GUIDED':
                    self._takeoff_until_alt = None
                st.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                st.system_status = int(msg.system_status)
                if was_armed and not st.armed:
                    self._hold_yaw_enu = None
                    self._takeoff_until_alt = None
                    self.touchdown.reset()          # the next flight starts a new descent
                came_up = not st.link_up
                st.link_up = True
                self._hb_mode, self._hb_armed = st.mode, st.armed
            if came_up:
                self._link_changed(True, f"vehicle heartbeat from {self.peer.describe()}, mode {st.mode}, "
                                         f"{'armed' if st.armed else 'disarmed'}")
            elif st.mode != reported_mode:     # as the vehicle reports it (set_mode's guess aside)
                _LOG.info('vehicle mode %s (was %s)', st.mode, reported_mode)
            if st.armed != reported_armed and not came_up:
                _LOG.info('vehicle %s in %s', 'armed' if st.armed else 'disarmed', st.mode)
        elif mtype == 'LOCAL_POSITION_NED':
            vals = (msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz)
            if not all(math.isfinite(v) for v in vals):
                raise NonFiniteTelemetry(f'non-finite LOCAL_POSITION_NED {vals}')
            odom = None
            with self._lock:
                st = self.status
                st.position_ned = np.array(vals[:3], dtype=float)
                st.velocity_ned = np.array(vals[3:], dtype=float)
                st.last_position = now
                if st.attitude is not None:
                    odom = self._odometry_locked()
                self._check_takeoff_locked(now)
            if odom is not None and self._on_odometry is not None:
                self._on_odometry(odom)
        elif mtype == 'ATTITUDE':
            vals = (msg.roll, msg.pitch, msg.yaw, msg.rollspeed, msg.pitchspeed, msg.yawspeed)
            if not all(math.isfinite(v) for v in vals):
                raise NonFiniteTelemetry(f'non-finite ATTITUDE {vals}')
            with self._lock:
                self.status.attitude = (float(msg.roll), float(msg.pitch), float(msg.yaw))
                self.status.rates_frd = np.array(vals[3:], dtype=float)
        elif mtype == 'EXTENDED_SYS_STATE':
            state = int(msg.landed_state)
            if state not in LANDED_STATES:
                self.counters['rx_bad_landed_state'] += 1
                raise ValueError(f'landed_state {state} is not a MAV_LANDED_STATE (0-{max(LANDED_STATES)})')
            with self._lock:
                previous = self.status.landed_state
                changed = state != previous
                self.status.landed_state = state
                if previous == mavlink.MAV_LANDED_STATE_ON_GROUND and state in (
                        mavlink.MAV_LANDED_STATE_TAKEOFF, mavlink.MAV_LANDED_STATE_IN_AIR):
                    self.touchdown.reset()          # landed, then took off: a new flight
                if (self._takeoff_until_alt is not None and previous == mavlink.MAV_LANDED_STATE_TAKEOFF
                        and state == mavlink.MAV_LANDED_STATE_IN_AIR):
                    # ArduCopter's own word that its takeoff reached the target: the altitude threshold
                    # is measured from where the EKF put the ground at the takeoff command, which is off
                    # while the estimate still converges (a vehicle moved on the ground, a baro drift)
                    _LOG.info('takeoff complete (the vehicle reports IN_AIR at %.2f m); velocity setpoints resume',
                              self._altitude_locked())
                    self._takeoff_until_alt = None
            if changed:
                _LOG.info('vehicle landed state %s', LANDED_STATES[state])
            if self._on_landed_state is not None:       # every report: its arrival says the state is current
                self._on_landed_state(state)
        elif mtype == 'DISTANCE_SENSOR':
            self._on_distance_sensor(msg, now)
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

    def _on_distance_sensor(self, msg, now: float) -> None:
        """Keep the latest downward range (cm on the wire); a reading outside the sensor's own limits makes
        the range unknown, a sensor that does not face down is ignored (both counted)."""
        if int(msg.orientation) != RANGE_DOWN:
            self.counters['range_not_down'] += 1
            return
        rng = downward_range_m(msg.current_distance * 0.01, msg.min_distance * 0.01, msg.max_distance * 0.01,
                               msg.orientation)
        with self._lock:
            if rng is None:
                self.counters['range_out_of_limits'] += 1
                self._range = None
            else:
                self.counters['range_received'] += 1
                self._range = (rng, now)

    def downward_range(self, now: float | None = None) -> float | None:
        """The latest downward range (m), or None when unknown (none, invalid, or older than range_timeout_s)."""
        now = self._clock() if now is None else now
        with self._lock:
            if self._range is None or now - self._range[1] > self.cfg.range_timeout_s:
                return None
            return self._range[0]

    def _touchdown_locked(self, v: np.ndarray, now: float) -> np.ndarray:
        """`v` (body FLU, z up) through the touchdown envelope at the current downward range."""
        rng = self.downward_range(now)
        before = self.touchdown.engagements
        out = self.touchdown.apply(v, rng, now)
        if self.touchdown.engagements != before:
            self.counters['touchdown_engaged'] += 1
            _LOG.info('touchdown: range %.2f m, command (%.2f, %.2f, %.2f) m/s -> vertical descent at %.2f m/s',
                      rng, v[0], v[1], v[2], self.touchdown.cfg.descent_mps)
        if self.touchdown.engaged:      # the descent clamp still holds
            out[2] = max(float(out[2]), -self.cfg.max_descent_mps)
        return out

    def _odometry_locked(self) -> Odometry:
        st = self.status
        r = frames.attitude_ned_frd_to_enu_flu(*st.attitude)
        v_enu = frames.ned_to_enu(st.velocity_ned)
        return Odometry(position=frames.ned_to_enu(st.position_ned), quaternion=frames.matrix_to_quaternion(r),
                        linear_velocity=r.T @ v_enu, angular_velocity=frames.frd_to_flu(st.rates_frd),
                        yaw=frames.yaw_ned_to_enu(st.attitude[2]))

    def _link_changed(self, up: bool, why: str) -> None:
        if up:
            _LOG.info("MAVLink link up on '%s': %s", self.cfg.connection, why)
            self.counters['link_up_events'] += 1
            with self._lock:
                self.status.ever_connected = True
            self.request_streams()
        else:
            _LOG.error("MAVLink link lost on '%s': %s; sending zero velocity at %.1f Hz until it returns",
                       self.cfg.connection, why, self.cfg.link_lost_setpoint_rate_hz)
            self.counters['link_lost_events'] += 1
        if self._on_link is not None:
            self._on_link(up, why)

    # ------------------------------------------------------------------ sending
    def _send(self, fn_name: str, *args) -> bool:
        """Pack and send one message; False (counted as tx_errors, logged throttled) when it cannot be packed
        or written: no value handed to the bridge can end it."""
        try:
            with self._send_lock:
                getattr(self.conn.mav, fn_name)(*args)
        except SEND_ERRORS as exc:
            self.counters['tx_errors'] += 1
            name = fn_name.removesuffix('_send')
            self._throttled.log(logging.ERROR, f'tx:{name}', 'cannot send %s (not sent, counted as tx_errors): '
                                '%s: %s', name.upper(), type(exc).__name__, exc)
            return False
        return True

    def _target(self) -> tuple[int, int]:
        peer = self.peer
        if peer is not None:
            return peer.system, peer.component
        return self.cfg.target_system, self.cfg.target_component

    def send_vision(self, est) -> bool:
        """Send one VISION_POSITION_ESTIMATE (assist_bridge.vision.VisionEstimate) if the link is up."""
        with self._lock:
            up = self.status.link_up
        if not up:
            return False
        return self._send('vision_position_estimate_send', est.usec, est.x, est.y, est.z, est.roll, est.pitch,
                          est.yaw, list(est.covariance), est.reset_counter)

    def set_ekf_origin(self, lat_deg: float, lon_deg: float, alt_m: float) -> bool:
        """SET_GPS_GLOBAL_ORIGIN: the EKF's origin, which external navigation without GPS needs (link up only).

        The values are range-checked as EkfOrigin (SettingsError, a ValueError); False when not sent."""
        origin = EkfOrigin(lat_deg, lon_deg, alt_m)
        with self._lock:
            up = self.status.link_up
        if not up:
            return False
        system, _ = self._target()
        return self._send('set_gps_global_origin_send', system, int(round(origin.latitude_deg * 1e7)),
                          int(round(origin.longitude_deg * 1e7)), int(round(origin.altitude_m * 1000)))

    def request_streams(self) -> None:
        """Ask the autopilot for the telemetry the bridge uses (both ways ArduPilot understands)."""
        self._last_stream_request = self._clock()
        c = self.cfg
        ts, tc = self._target()
        odom_hz = int(max(1, round(c.odom_rate_hz)))
        stat_hz = int(max(1, round(c.status_rate_hz)))
        for stream, hz in ((mavlink.MAV_DATA_STREAM_POSITION, odom_hz), (mavlink.MAV_DATA_STREAM_EXTRA1, odom_hz),
                           (mavlink.MAV_DATA_STREAM_EXTENDED_STATUS, stat_hz),
                           (mavlink.MAV_DATA_STREAM_EXTRA3, stat_hz)):
            self._send('request_data_stream_send', ts, tc, stream, hz, 1)
        for mid, hz in ((mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, c.odom_rate_hz),
                        (mavlink.MAVLINK_MSG_ID_ATTITUDE, c.odom_rate_hz),
                        (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, c.status_rate_hz),
                        (mavlink.MAVLINK_MSG_ID_SYS_STATUS, c.status_rate_hz),
                        (mavlink.MAVLINK_MSG_ID_DISTANCE_SENSOR, c.range_rate_hz)):
            self._send('command_long_send', ts, tc, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, float(mid), 1e6 / hz,
                       0, 0, 0, 0, 0)
        self.counters['stream_requests'] += 1

    def set_command(self, v_flu: Sequence[float], now: float | None = None) -> np.ndarray:
        """Accept a body-FLU velocity command (ValueError if non-finite).

        The scheduled sends carry the latest command; a changed command also goes out at once if no
        immediate send has been made since the last scheduled one (at most 2x setpoint_rate_hz out).
        """
        now = self._clock() if now is None else now
        v = limit_velocity(v_flu, self.cfg)
        with self._lock:
            self._cmd = v
            self._cmd_time = now
            self.counters['commands_accepted'] += 1
            changed = self._sent_velocity is None or not np.array_equal(v, self._sent_velocity)
            if changed and self._immediate_ok:
                if self._send_setpoint_locked(now):
                    self._immediate_ok = False
                    self.counters['setpoints_immediate'] += 1
            elif changed:
                self.counters['commands_deferred'] += 1
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
        """Periodic work: own heartbeat, link watchdog, stream re-requests, setpoint sends."""
        now = self._clock() if now is None else now
        c = self.cfg
        if now - self._last_heartbeat_sent >= 1.0 / c.heartbeat_rate_hz:
            self._last_heartbeat_sent = now
            with self._send_lock:
                refresh_signing_timestamp(self.conn)
            self._send('heartbeat_send', mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0,
                       mavlink.MAV_STATE_ACTIVE)
        lost = False
        with self._lock:
            st = self.status
            if st.link_up and st.last_heartbeat is not None and now - st.last_heartbeat > c.link_timeout_s:
                st.link_up = False
                lost = True
        if lost:
            self._next_lost_setpoint = -math.inf     # the first brake goes out with the declaration
            self._link_changed(False, f'no heartbeat for {c.link_timeout_s:.1f} s')
        with self._lock:
            if not st.link_up:
                self._lost_link_brake_locked(now)
                return
            need = ((st.last_position is None or now - st.last_position > c.stream_request_period_s)
                    and now - self._last_stream_request > c.stream_request_period_s)
            self._check_takeoff_locked(now)
            if now >= self._next_setpoint_due:
                period = 1.0 / c.setpoint_rate_hz
                # fixed-rate schedule (no drift); a late tick re-anchors it instead of bursting
                late = now - self._next_setpoint_due > period
                self._next_setpoint_due = now + period if late else self._next_setpoint_due + period
                self._immediate_ok = True
                self._send_setpoint_locked(now)
        if need:
            self.request_streams()

    def _lost_link_brake_locked(self, now: float) -> None:
        """While the link is lost: zero velocity at a low rate to a vehicle last seen armed."""
        st = self.status
        if self.peer is None or not st.armed or now < self._next_lost_setpoint:
            return
        self._next_lost_setpoint = now + 1.0 / self.cfg.link_lost_setpoint_rate_hz
        ts, tc = self._target()
        v = self._touchdown_locked(np.zeros(3), now)     # the range is stale by now: zero, in practice
        if self._hold_yaw_enu is not None or st.attitude is not None:
            yaw_enu = self._hold_yaw_enu if self._hold_yaw_enu is not None else frames.yaw_ned_to_enu(st.attitude[2])
            sp = velocity_setpoint(v, yaw_enu)
        else:       # no heading known: rotation-free, so only a vertical part can be sent as is
            sp = dict(coordinate_frame=mavlink.MAV_FRAME_LOCAL_NED, type_mask=TYPE_MASK_VELOCITY_YAW_RATE,
                      vx=0.0, vy=0.0, vz=float(-v[2]), yaw=0.0)
        if not self._send('set_position_target_local_ned_send', self.time_boot_ms(), ts, tc, sp['coordinate_frame'],
                          sp['type_mask'], 0.0, 0.0, 0.0, sp['vx'], sp['vy'], sp['vz'], 0.0, 0.0, 0.0, sp['yaw'],
                          0.0):
            return
        self.last_setpoint = sp
        self._sent_velocity = np.zeros(3)
        self.counters['setpoints_link_lost'] += 1

    def _altitude_locked(self) -> float:
        """Height above the EKF origin from the last LOCAL_POSITION_NED (-inf before one came)."""
        st = self.status
        return -float(st.position_ned[2]) if st.position_ned is not None else -math.inf

    def _check_takeoff_locked(self, now: float) -> None:
        if self._takeoff_until_alt is None:
            return
        alt = self._altitude_locked()
        if alt >= self._takeoff_until_alt:
            _LOG.info('takeoff complete at %.2f m; velocity setpoints resume', alt)
            self._takeoff_until_alt = None
        elif now > self._takeoff_deadline:
            _LOG.warning('takeoff climb not finished in time (altitude %.2f m); velocity setpoints resume', alt)
            self._takeoff_until_alt = None

    def _send_setpoint_locked(self, now: float) -> bool:
        """Send the current command (zero after the command timeout) if the vehicle flies it now."""
        c = self.cfg
        st = self.status
        if not st.link_up:
            self.counters['setpoints_suppressed_link'] += 1
            return False
        live = self._cmd_time is not None and now - self._cmd_time <= c.command_timeout_s
        v = self._cmd if live else np.zeros(3)
        if st.mode != 'GUIDED':
            if live and st.armed and np.any(v != 0.0) and self._mode_warned != st.mode:
                self._mode_warned = st.mode
                _LOG.warning('vehicle in %s: velocity setpoints not sent (ArduCopter flies them only in GUIDED; '
                             'the bridge never switches on its own: call /uav/guided)', st.mode)
            return False
        self._mode_warned = None
        if not st.armed or self._takeoff_until_alt is not None:
            return False
        if self._hold_yaw_enu is None:
            if st.attitude is None:
                return False
            self._hold_yaw_enu = frames.yaw_ned_to_enu(st.attitude[2])
            _LOG.info('holding heading %.1f deg (NED) while flying velocity setpoints',
                      math.degrees(frames.yaw_enu_to_ned(self._hold_yaw_enu)))
        sp = velocity_setpoint(self._touchdown_locked(v, now), self._hold_yaw_enu)
        ts, tc = self._target()
        if not self._send('set_position_target_local_ned_send', self.time_boot_ms(), ts, tc, sp['coordinate_frame'],
                          sp['type_mask'], 0.0, 0.0, 0.0, sp['vx'], sp['vy'], sp['vz'], 0.0, 0.0, 0.0, sp['yaw'], 0.0):
            return False
        self.last_setpoint = sp
        self._sent_velocity = v.copy()
        self.counters['setpoints_sent'] += 1
        if not live:
            self.counters['setpoints_zero_timeout'] += 1
        return True

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
        ts, tc = self._target()
        if not self._send('command_long_send', ts, tc, int(command), 0, *p):
            return None                 # could not be sent (counted, logged): no ACK will come
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
        """Change flight mode (MAV_CMD_DO_SET_MODE) as asked; (accepted, honest message)."""
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

    def guided(self) -> tuple[bool, str]:
        """Switch to GUIDED because the pilot asked for it (the /uav/guided service)."""
        return self.set_mode('GUIDED')

    def arm(self) -> tuple[bool, str]:
        """Disarmed: switch to GUIDED, then arm. Already armed: nothing is sent (no mode change)."""
        refused = self._require_link('arm')
        if refused:
            return refused
        with self._lock:
            armed, mode = self.status.armed, self.status.mode
        if armed:
            return True, f'arm: already armed (mode {mode}; mode not changed)'
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

    def force_disarm(self) -> tuple[bool, str]:
        """Disarm even when the autopilot thinks it is flying (ARM_DISARM param2 21196); only if allowed.

        For simulation episodes: a vehicle the landing judge saw come to rest on a pad edge or on its
        side in LAND may never detect its landing, so it never disarms and the next episode never
        starts. On a real vehicle this is a motor kill, hence allow_force_disarm (off by default).
        """
        if not self.cfg.allow_force_disarm:
            return False, 'force_disarm: refused, allow_force_disarm is false (it stops the motors even in flight)'
        refused = self._require_link('force_disarm')
        if refused:
            return refused
        t0 = self._clock()
        return self._report('force_disarm', self.command_long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM,
                                                              [0.0, FORCE_ARM_DISARM_MAGIC]), t0)

    def reboot(self) -> tuple[bool, str]:
        """Reboot the autopilot (MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN), only while disarmed.

        For a vehicle whose state estimate did not recover by itself (e.g. ArduCopter SITL's EKF
        after the airframe was flipped in a crash refuses to arm on "Check mag field"); the link
        drops while it restarts and the bridge reconnects.
        """
        refused = self._require_link('reboot')
        if refused:
            return refused
        with self._lock:
            if self.status.armed:
                return False, 'reboot: refused, the vehicle is armed'
        t0 = self._clock()
        return self._report('reboot', self.command_long(mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, [1.0]), t0)

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
            peer = self.peer
            return dict(link='up' if st.link_up else ('lost' if st.ever_connected else 'waiting'),
                        mode=st.mode, armed=st.armed,
                        landed_state='UNKNOWN' if st.landed_state is None else LANDED_STATES[st.landed_state],
                        taking_off=self._takeoff_until_alt is not None,
                        command_live=self._cmd_time is not None
                        and self._clock() - self._cmd_time <= self.cfg.command_timeout_s,
                        vehicle=peer.describe() if peer else 'none', signing=self.signing,
                        touchdown=('engaged' if self.touchdown.engaged else 'idle') if self.touchdown.cfg.enabled
                        else 'off', range_m='unknown' if (rng := self.downward_range()) is None else round(rng, 3))

    def wait_heartbeat(self, timeout: float) -> bool:
        """Block until the autopilot's heartbeat is seen (receive thread must run) or timeout."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if self.status.link_up:
                    return True
            time.sleep(0.02)
        return False
