"""sitl_identify: record how ArduCopter SITL in GUIDED follows velocity setpoints, flying our airframe.

Runs the pybullet airframe as SITL's JSON physics backend in this process (UDP `--json-port`, the
same JsonSimRunner/QuadJsonModel as `sim_node physics:=ardupilot_json`) and talks MAVLink to a
running ArduCopter SITL (`--connection`). One thread does both, lock-step: every SITL frame steps
the physics once, then MAVLink is read, the setpoint is sent at `--command-hz` and a row is logged
at `--log-hz`, all on physics time (= SITL's clock). The flight: GUIDED, arm (retried while
ArduCopter refuses, e.g. until its EKF has a position), takeoff to `--altitude-m`, then per named
sequence: fly to the sequence's start spot with a position target, hover `--hover-s`, and send the
sequence's ENU velocity setpoints (SET_POSITION_TARGET_LOCAL_NED, type_mask 1479, yaw_rate 0:
heading held). Last, the touchdown series: descend at 0.5 m/s onto the open floor, without and
with a lateral command at contact, recording when our physics sees the first contact and when
ArduCopter's EXTENDED_SYS_STATE first says ON_GROUND.

Output (`--out`, created if missing; existing files are refused unless `--force`): one CSV per
sequence, `#` header lines then columns `t_s,cmd_x,cmd_y,cmd_z,vel_x,vel_y,vel_z,pos_x,pos_y,pos_z`
(ENU world, m and m/s, t from the sequence start) + ArduCopter's own LOCAL_POSITION_NED in ENU
(`ap_*`) and the true attitude; one `touchdown_<trial>.csv` trace per touchdown and
`touchdown.csv`, the per-trial summary. The scene has its pads 15 m away and walls 10 m away, so
the flights stay over open floor.

    sitl_identify --out ros2_ws/src/assist_sim/test/fixtures/guided
    sitl_identify --list
"""
from __future__ import annotations

import dataclasses
import datetime
import logging
import math
import os
import shlex
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from assist_common.atomic import write_text_atomic
from assist_common.settings import SettingsError, exit_error, parse_settings, setting

os.environ.setdefault('MAVLINK20', '1')    # MAVLink 2 framing; must be set before mavutil is imported

_LOG = logging.getLogger('sitl_identify')

#: ArduPilot commit the fixtures were recorded with (the one /work/shared/peers/sitl.sh builds)
ARDUPILOT_COMMIT = '90700977c553d2dfd95a305acf1c3e098e4d9477'
COLUMNS = ('t_s', 'cmd_x', 'cmd_y', 'cmd_z', 'vel_x', 'vel_y', 'vel_z', 'pos_x', 'pos_y', 'pos_z')
EXTRA_COLUMNS = ('ap_vel_x', 'ap_vel_y', 'ap_vel_z', 'ap_pos_x', 'ap_pos_y', 'ap_pos_z',
                 'roll_deg', 'pitch_deg', 'yaw_deg')
TOUCHDOWN_COLUMNS = ('contact', 'ap_landed_state')
# SET_POSITION_TARGET_LOCAL_NED.type_mask: bits set = fields ignored (1 x, 2 y, 4 z, 8-32 v, 64-256 a,
# 1024 yaw, 2048 yaw_rate). Velocity + yaw_rate (0: heading held), as mavlink_bridge_node sends.
TYPE_MASK_VELOCITY = 1 | 2 | 4 | 64 | 128 | 256 | 1024          # 1479
TYPE_MASK_POSITION = 8 | 16 | 32 | 64 | 128 | 256 | 1024        # 1528
GUIDED = 4                                  # ArduCopter custom_mode
LANDED_ON_GROUND = 1                        # MAV_LANDED_STATE_ON_GROUND
FORCE_DISARM_MAGIC = 21196.0
# ArduCopter parameters that shape the GUIDED velocity response, read back into every header
REPORTED_PARAMS = ('SIM_SPEEDUP', 'SIM_RATE_HZ', 'WPNAV_SPEED', 'WPNAV_SPEED_UP', 'WPNAV_SPEED_DN',
                   'WPNAV_ACCEL', 'WPNAV_ACCEL_Z', 'PSC_JERK_XY', 'PSC_JERK_Z', 'PSC_POSXY_P', 'PSC_VELXY_P',
                   'PSC_VELXY_I', 'PSC_VELXY_D', 'PSC_POSZ_P', 'PSC_VELZ_P', 'PSC_ACCZ_P', 'PSC_ACCZ_I',
                   'PILOT_ACCEL_Z', 'ANGLE_MAX', 'ATC_INPUT_TC', 'ATC_ACCEL_R_MAX', 'ATC_ACCEL_P_MAX',
                   'ATC_ANG_RLL_P', 'ATC_ANG_PIT_P', 'MOT_THST_HOVER', 'GUID_TIMEOUT', 'LAND_SPEED',
                   'DISARM_DELAY')


# ---------------------------------------------------------------------------------------- sequences
@dataclass(frozen=True)
class Sequence:
    """One identification sequence: ENU velocity setpoints at the command rate, flown from a start spot."""

    name: str
    description: str
    start_xy: tuple[float, float]           # world ENU spot the sequence starts above (hovering)
    commands: np.ndarray                    # (n, 3) ENU m/s; command k is sent at t = k / command_hz

    @property
    def n(self) -> int:
        """Number of setpoints."""
        return int(self.commands.shape[0])


class _Builder:
    """Piecewise-constant and sampled command tables at a fixed rate."""

    def __init__(self, hz: float):
        self.hz = hz
        self.rows: list[np.ndarray] = []

    def hold(self, v, seconds: float) -> _Builder:
        """Append `v` (ENU, 3) for `seconds`."""
        n = int(round(seconds * self.hz))
        self.rows.extend([np.asarray(v, dtype=float)] * n)
        return self

    def sampled(self, fn: Callable[[float], np.ndarray], seconds: float) -> _Builder:
        """Append fn(t) for t = 0, 1/hz, ... < seconds."""
        n = int(round(seconds * self.hz))
        self.rows.extend(np.asarray(fn(k / self.hz), dtype=float) for k in range(n))
        return self

    def array(self) -> np.ndarray:
        """(n, 3) table."""
        return np.array(self.rows, dtype=float).reshape(-1, 3)


PRE_ROLL_S = 1.0          # zero velocity at the start of every sequence (steady hover in the record)
RANDOM_SEEDS = {'random_a': 101, 'random_b': 202, 'random_c': 303}   # held-out pilot-like sequences


def _random_pilot(seed: int, hz: float, seconds: float = 18.0) -> np.ndarray:
    """Piecewise-constant pilot-like commands (holds 0.2-2 s, x/y within +-1.5, z within -1.0..+0.8 m/s),
    redrawn (same seed stream) until the commanded path stays within 3 m horizontally and 1.2 m vertically."""
    rng = np.random.default_rng(seed)
    for _ in range(1000):
        b = _Builder(hz).hold((0, 0, 0), PRE_ROLL_S)
        t = 0.0
        while t < seconds:
            hold = float(rng.uniform(0.2, 2.0))
            v = np.array([rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5), rng.uniform(-1.0, 0.8)])
            v[rng.random(3) < 0.3] = 0.0             # pilots often leave an axis alone
            v = np.round(v, 2)
            b.hold(v, hold)
            t += round(hold * hz) / hz
        b.hold((0, 0, 0), 3.0)
        table = b.array()
        path = np.cumsum(table, axis=0) / hz
        if np.abs(path[:, :2]).max() <= 3.0 and np.abs(path[:, 2]).max() <= 1.2:
            return table
    raise RuntimeError(f'no bounded random sequence for seed {seed}')


def build_sequences(hz: float = 20.0) -> dict[str, Sequence]:
    """Every identification sequence by name (fixed: the held-out random ones use fixed seeds)."""
    z = (0.0, 0.0, 0.0)
    seqs: list[Sequence] = []

    def add(name: str, description: str, start_xy, b: _Builder) -> None:
        seqs.append(Sequence(name, description, tuple(float(c) for c in start_xy), b.array()))

    def step(v, start):
        return _Builder(hz).hold(z, PRE_ROLL_S).hold(v, 4.0).hold(z, 5.0)

    add('step_x_pos', '+1 m/s east held 4 s, then 0', (-2.0, 0.0), step((1, 0, 0), None))
    add('step_x_neg', '-1 m/s east held 4 s, then 0', (2.0, 0.0), step((-1, 0, 0), None))
    add('step_y_pos', '+1 m/s north held 4 s, then 0', (0.0, -2.5), step((0, 1, 0), None))
    add('step_y_neg', '-1 m/s north held 4 s, then 0', (0.0, 2.5), step((0, -1, 0), None))
    add('step_diag', '(+1, +1) m/s east+north held 4 s, then 0', (-2.0, -2.0), step((1, 1, 0), None))
    add('step_z', 'vertical steps: +1.0 for 2 s, 0, -1.5 for 1.5 s, 0, -0.5 for 2 s, 0', (0.0, 0.0),
        _Builder(hz).hold(z, PRE_ROLL_S).hold((0, 0, 1.0), 2.0).hold(z, 3.0).hold((0, 0, -1.5), 1.5)
        .hold(z, 3.0).hold((0, 0, -0.5), 2.0).hold(z, 3.0))

    def ramp(t: float) -> np.ndarray:           # 0 -> 1.2 (4 s), hold 1 s, -> -1.2 (8 s), hold 1 s, -> 0 (4 s)
        knots_t = (0.0, 4.0, 5.0, 13.0, 14.0, 18.0)
        knots_v = (0.0, 1.2, 1.2, -1.2, -1.2, 0.0)
        return np.array([np.interp(t, knots_t, knots_v), 0.0, 0.0])
    add('ramp_x', 'east ramp 0 -> 1.2 m/s in 4 s, hold 1 s, -> -1.2 in 8 s, hold 1 s, -> 0 in 4 s', (-3.0, 0.0),
        _Builder(hz).hold(z, PRE_ROLL_S).sampled(ramp, 18.0).hold(z, 3.0))

    def square(half: float):
        return lambda t: np.array([1.0 if int(math.floor(t / half + 1e-9)) % 2 == 0 else -1.0, 0.0, 0.0])
    # ArduCopter's jerk-limited shaping turns the fast square wave into a drift of ~0.7 m/s east: start west
    add('square_x_0p25', 'east square wave +-1 m/s, half-period 0.25 s, 8 s, then 0', (-4.0, 0.0),
        _Builder(hz).hold(z, PRE_ROLL_S).sampled(square(0.25), 8.0).hold(z, 3.0))
    add('square_x_1', 'east square wave +-1 m/s, half-period 1 s, 10 s, then 0', (0.0, 0.0),
        _Builder(hz).hold(z, PRE_ROLL_S).sampled(square(1.0), 10.0).hold(z, 3.0))

    f0, f1, tc = 0.2, 2.0, 20.0

    def chirp(t: float) -> np.ndarray:
        return np.array([math.sin(2 * math.pi * (f0 * t + (f1 - f0) * t * t / (2 * tc))), 0.0, 0.0])
    add('chirp_x', 'east chirp 1 m/s amplitude, 0.2 -> 2 Hz linear over 20 s, then 0', (0.0, 0.0),
        _Builder(hz).hold(z, PRE_ROLL_S).sampled(chirp, tc).hold(z, 3.0))
    for name, seed in RANDOM_SEEDS.items():
        b = _Builder(hz)
        b.rows = list(_random_pilot(seed, hz))
        add(name, f'held-out pilot-like piecewise-constant x/y/z, holds 0.2-2 s, seed {seed}', (0.0, 0.0), b)
    return {s.name: s for s in seqs}


# ---------------------------------------------------------------------------------------- settings
@dataclass
class IdentifyConfig:
    """What sitl_identify flies and where it writes."""

    out: str = ''                                         # folder for the CSV files (required)
    connection: str = setting('tcp:127.0.0.1:5760', nonempty=True)
    json_port: int = setting(9002, ge=1, le=65535)
    sequences: str = ''                                   # comma-separated names; '' = all
    altitude_m: float = setting(3.0, ge=1.5, le=5.0)      # hover height of base_link above the floor
    command_hz: float = setting(20.0, ge=5.0, le=50.0)
    log_hz: float = setting(50.0, ge=10.0, le=200.0)
    hover_s: float = setting(3.0, ge=0.0, le=30.0)        # steady hover before each sequence
    reach_timeout_s: float = setting(30.0, gt=0.0, le=120.0)
    arm_timeout_s: float = setting(240.0, gt=0.0, le=3600.0)   # physics seconds of arming retries
    turbulence: bool = False                              # the sim's ground-effect turbulence force
    seed: int = setting(0, ge=0)
    touchdown_trials: int = setting(2, ge=0, le=10)       # straight descents (no lateral command)
    touchdown_lateral_mps: float = setting(0.5, ge=0.0, le=1.5)   # one more descent with this east command; 0: none
    touchdown_descent_mps: float = setting(0.5, gt=0.0, le=1.5)
    touchdown_release: bool = True                        # and one whose east command goes to 0 at contact
    touchdown_wait_s: float = setting(10.0, gt=0.0, le=60.0)      # after contact, for ON_GROUND
    ext_state_hz: float = setting(50.0, ge=10.0, le=100.0)        # EXTENDED_SYS_STATE request rate
    sitl_defaults: str = ('Tools/autotest/default_params/copter.parm,'
                          'ros2_ws/src/assist_sim/config/ardupilot_json_quad.parm')   # recorded in headers
    ardupilot_commit: str = setting(ARDUPILOT_COMMIT, nonempty=True)
    force: bool = False                                   # overwrite existing files in --out
    list: bool = False                                    # print the sequence names and exit

    def selected(self) -> list[str]:
        """Names of the sequences to fly, in order."""
        names = list(build_sequences(self.command_hz))
        if not self.sequences.strip():
            return names
        want = [s.strip() for s in self.sequences.split(',') if s.strip()]
        return want

    def check_relations(self) -> None:
        """Rules between fields."""
        if self.list:
            return
        if not self.out:
            raise SettingsError('--out is required (the folder the CSV files go to)')
        out = Path(self.out)
        if out.exists() and not out.is_dir():
            raise SettingsError(f'--out {self.out} exists and is not a folder')
        known = list(build_sequences(self.command_hz))
        want = [s.strip() for s in self.sequences.split(',') if s.strip()]
        bad = [s for s in want if s not in known]
        if bad:
            raise SettingsError(f'--sequences: unknown {", ".join(bad)} (known: {", ".join(known)})')
        if len(set(want)) != len(want):
            raise SettingsError('--sequences names a sequence twice')
        if self.log_hz < self.command_hz:
            raise SettingsError('--log-hz must be >= --command-hz')


def output_files(cfg: IdentifyConfig) -> list[str]:
    """File names the run writes into --out."""
    names = [f'{n}.csv' for n in cfg.selected()]
    trials = touchdown_trials(cfg)
    if trials:
        names += [f'touchdown_{t[0]}.csv' for t in trials] + ['touchdown.csv']
    return names


def touchdown_trials(cfg: IdentifyConfig) -> list[tuple[str, float, bool]]:
    """(trial name, east command at contact, whether it goes to 0 at contact) of the touchdown series."""
    trials = [(f'vertical_{i + 1}', 0.0, False) for i in range(cfg.touchdown_trials)]
    if cfg.touchdown_lateral_mps > 0:
        trials.append(('lateral', cfg.touchdown_lateral_mps, False))
        if cfg.touchdown_release:
            trials.append(('lateral_release', cfg.touchdown_lateral_mps, True))
    return trials


# ---------------------------------------------------------------------------------------- CSV
def _fmt(x: float, digits: int) -> str:
    s = f'{x:.{digits}f}'
    return '0' if s.lstrip('-').strip('0.') == '' else s


def fixture_text(header: list[str], columns: tuple[str, ...], rows: list[tuple]) -> str:
    """`# ` header lines, a column line and the rows (times 4 decimals, values 4, angles 2)."""
    lines = [f'# {h}' for h in header] + [','.join(columns)]
    digits = [4 if not c.endswith('_deg') else 2 for c in columns]
    for r in rows:
        lines.append(','.join(_fmt(float(v), d) if not isinstance(v, (int, np.integer)) else str(int(v))
                              for v, d in zip(r, digits)))
    return '\n'.join(lines) + '\n'


def read_fixture(path: str | Path) -> tuple[list[str], list[str], np.ndarray]:
    """(header lines without '# ', column names, (n, k) float array) of a fixture CSV."""
    header, columns, data = [], None, []
    for line in Path(path).read_text(encoding='utf-8').splitlines():
        if line.startswith('#'):
            header.append(line[1:].strip())
        elif columns is None:
            columns = line.split(',')
        elif line.strip():
            data.append([float(x) for x in line.split(',')])
    if columns is None:
        raise ValueError(f'{path}: no column line')
    return header, columns, np.array(data, dtype=float).reshape(-1, len(columns))


# ---------------------------------------------------------------------------------------- flying
class SitlError(RuntimeError):
    """SITL did not do what the identification needs (silent, restarted, refused, never reached)."""


@dataclass
class _Recorder:
    """Rows logged at the log rate from t0 (physics time) on."""

    t0: float
    touchdown: bool = False
    rows: list = dataclasses.field(default_factory=list)
    next_k: int = 0


class Identifier:
    """Physics server + MAVLink client in one lock-step loop (see the module docstring)."""

    def __init__(self, cfg: IdentifyConfig):
        from pymavlink import mavutil

        from .core.config import SceneConfig, TurbulenceConfig, WorldConfig
        from .core.runner import RunnerConfig
        from .core.world import LandingWorld
        from .json_backend import JsonBackendConfig, JsonSimRunner

        self.cfg = cfg
        self.mavutil = mavutil
        self.mavlink = mavutil.mavlink
        # pads from x = 15 m on, walls 10 m from the start spot on every side
        scene = SceneConfig(first_pad_x_m=(15.5, 16.0), wall_margin_m=10.0, room_half_width_m=10.0,
                            start_x_m=(0.0, 0.0), start_y_m=(0.0, 0.0))
        wcfg = WorldConfig(scene=scene, turbulence=TurbulenceConfig(enabled=cfg.turbulence))
        self.world = LandingWorld(wcfg, seed=cfg.seed)
        try:
            self.runner = JsonSimRunner(self.world, RunnerConfig(airborne_start=False, camera_rate_hz=0.0,
                                                                 auto_reset=False),
                                        JsonBackendConfig(port=cfg.json_port), seed=cfg.seed)
        except BaseException:
            self.world.close()
            raise
        self.runner.reset(cfg.seed)
        near = [p for p in self.world.scene.pads if math.hypot(*p.center) < 10.0]
        if near:
            raise SitlError(f'scene seed {cfg.seed} has a pad within 10 m of the start spot')
        self.server = self.runner.server
        self.offset = self.runner.odom_offset           # world ENU of ArduPilot's LOCAL_NED origin
        self._bc, self._vid = self.world._bc, self.world._vehicle
        self.mav = None
        self.hb = None
        self.acks: dict[int, int] = {}
        self.params: dict[str, float] = {}
        self.landed_state: int | None = None
        self.landed_state_log: list[tuple[float, int]] = []
        self.ap_pos = np.full(3, math.nan)
        self.ap_vel = np.full(3, math.nan)
        self.version = ''
        self.setpoint: Callable[[float], tuple[str, np.ndarray] | None] | None = None
        self.cmd_now = np.zeros(3)
        self._next_cmd_t = 0.0
        self._wall_hb = 0.0
        self.recorder: _Recorder | None = None
        self.on_step: Callable[[], None] | None = None
        self.steps = 0
        self.wall_start = time.monotonic()

    # ------------------------------------------------------------------ plumbing
    @property
    def t(self) -> float:
        """Physics time (s) = SITL's clock."""
        return self.world.time

    def close(self) -> None:
        """Release the socket, the MAVLink link and the world."""
        if self.mav is not None:
            self.mav.close()
        self.runner.close()
        self.world.close()

    def _state(self) -> tuple[np.ndarray, np.ndarray, tuple]:
        pos, orn = self._bc.getBasePositionAndOrientation(self._vid)
        lin, _ = self._bc.getBaseVelocity(self._vid)
        return np.array(pos), np.array(lin), orn

    def _handle(self, msg) -> None:
        typ = msg.get_type()
        if typ == 'HEARTBEAT' and msg.get_srcComponent() == 1 and msg.type != self.mavlink.MAV_TYPE_GCS:
            self.hb = msg
        elif typ == 'COMMAND_ACK':
            self.acks[msg.command] = msg.result
        elif typ == 'LOCAL_POSITION_NED':
            self.ap_pos = self.offset + np.array([msg.y, msg.x, -msg.z])
            self.ap_vel = np.array([msg.vy, msg.vx, -msg.vz])
        elif typ == 'EXTENDED_SYS_STATE':
            if msg.landed_state != self.landed_state:
                self.landed_state_log.append((self.t, int(msg.landed_state)))
            self.landed_state = int(msg.landed_state)
        elif typ == 'PARAM_VALUE':
            self.params[msg.param_id] = float(msg.param_value)
        elif typ == 'AUTOPILOT_VERSION':
            self.version = bytes(msg.flight_custom_version).rstrip(b'\0').decode('ascii', 'replace')
        elif typ == 'STATUSTEXT':
            _LOG.info('SITL: %s', msg.text)

    def _send_setpoint(self) -> None:
        sp = self.setpoint(self.t) if self.setpoint is not None else None
        if sp is None:
            return
        kind, v = sp
        ts, tc = self.mav.target_system, self.mav.target_component
        ms = int(self.t * 1000) & 0xFFFFFFFF
        if kind == 'vel':
            self.cmd_now = np.asarray(v, dtype=float)
            self.mav.mav.set_position_target_local_ned_send(
                ms, ts, tc, self.mavlink.MAV_FRAME_LOCAL_NED, TYPE_MASK_VELOCITY, 0, 0, 0,
                float(v[1]), float(v[0]), -float(v[2]), 0, 0, 0, 0, 0)
        else:
            self.cmd_now = np.zeros(3)
            ned = np.asarray(v, dtype=float) - self.offset
            self.mav.mav.set_position_target_local_ned_send(
                ms, ts, tc, self.mavlink.MAV_FRAME_LOCAL_NED, TYPE_MASK_POSITION,
                float(ned[1]), float(ned[0]), -float(ned[2]), 0, 0, 0, 0, 0, 0, 0, 0)

    def _record(self) -> None:
        rec = self.recorder
        pos, vel, orn = self._state()
        r, pch, y = self._bc.getEulerFromQuaternion(orn)
        row = [self.t - rec.t0, *self.cmd_now, *vel, *pos, *self.ap_vel, *self.ap_pos,
               math.degrees(r), math.degrees(pch), math.degrees(y)]
        if rec.touchdown:
            row += [int(self.world._legs_touching()), -1 if self.landed_state is None else self.landed_state]
        rec.rows.append(tuple(row))

    def step_once(self) -> None:
        """Serve one SITL frame (physics step + reply), then MAVLink, setpoint and log on physics time."""
        wall_end = time.monotonic() + 15.0
        while True:
            ev = self.server.poll(0.5)
            if ev in ('step', 'restart'):
                break
            if self.mav is not None:
                self._drain()
            if time.monotonic() > wall_end:
                raise SitlError('SITL sent no physics frame for 15 s (not started with --model JSON, '
                                f'or not sending to udp port {self.cfg.json_port}?)')
        if ev == 'restart' and self.steps > 0:
            raise SitlError('SITL restarted during the identification')
        self.steps += 1
        if self.mav is not None:
            self._drain()
            now = time.monotonic()
            if now - self._wall_hb > 1.0:
                self._wall_hb = now
                self.mav.mav.heartbeat_send(self.mavlink.MAV_TYPE_GCS, self.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            if self.setpoint is not None and self.t + 1e-7 >= self._next_cmd_t:
                self._send_setpoint()
                self._next_cmd_t += 1.0 / self.cfg.command_hz
                if self._next_cmd_t < self.t:
                    self._next_cmd_t = self.t + 1.0 / self.cfg.command_hz
        if self.on_step is not None:
            self.on_step()
        rec = self.recorder
        if rec is not None and self.t + 1e-7 >= rec.t0 + rec.next_k / self.cfg.log_hz:
            self._record()
            rec.next_k += 1

    def _drain(self) -> None:
        while True:
            msg = self.mav.recv_match(blocking=False)
            if msg is None:
                return
            self._handle(msg)

    def spin(self, seconds: float, until: Callable[[], bool] | None = None) -> bool:
        """Serve SITL for up to `seconds` of physics time or until `until()`; returns whether it came."""
        end = self.t + seconds
        while self.t < end:
            if until is not None and until():
                return True
            self.step_once()
        return until is not None and until()

    def set_setpoint(self, fn: Callable[[float], tuple[str, np.ndarray] | None] | None,
                     start: float | None = None) -> None:
        """New setpoint source; setpoints go out every 1/command_hz from physics time `start` (default:
        the next physics step)."""
        self.setpoint = fn
        self._next_cmd_t = self.t if start is None else start

    def command(self, cmd: int, params: list[float], timeout_s: float = 3.0) -> int | None:
        """COMMAND_LONG and its COMMAND_ACK result (None: no ACK within `timeout_s` physics seconds)."""
        p = (list(params) + [0.0] * 7)[:7]
        self.acks.pop(cmd, None)
        self.mav.mav.command_long_send(self.mav.target_system, self.mav.target_component, cmd, 0, *p)
        self.spin(timeout_s, lambda: cmd in self.acks)
        return self.acks.get(cmd)

    # ------------------------------------------------------------------ phases
    def connect(self) -> None:
        """Serve SITL's first frames, open MAVLink and wait for the autopilot's heartbeat."""
        _LOG.info('waiting for SITL on udp %s:%d', *self.server.address[:2])
        self.step_once()
        _LOG.info('SITL frames arriving; connecting MAVLink %s', self.cfg.connection)
        self.mav = self.mavutil.mavlink_connection(self.cfg.connection, source_system=255, source_component=190,
                                                   autoreconnect=False)
        if not self.spin(30.0, lambda: self.hb is not None):
            raise SitlError(f'no heartbeat from ArduCopter on {self.cfg.connection}')
        if self.armed:
            raise SitlError('ArduCopter is armed already (flown before this run?): restart SITL for a clean start')
        self.mav.target_system = self.hb.get_srcSystem()
        self.mav.target_component = self.hb.get_srcComponent()
        m = self.mavlink
        for msg_id, hz in ((m.MAVLINK_MSG_ID_LOCAL_POSITION_NED, self.cfg.log_hz),
                           (m.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, self.cfg.ext_state_hz)):
            r = self.command(m.MAV_CMD_SET_MESSAGE_INTERVAL, [float(msg_id), 1e6 / hz])
            if r != m.MAV_RESULT_ACCEPTED:
                raise SitlError(f'SET_MESSAGE_INTERVAL {msg_id} at {hz:g} Hz: result {r}')
        self.command(m.MAV_CMD_REQUEST_MESSAGE, [float(m.MAVLINK_MSG_ID_AUTOPILOT_VERSION)])
        for _ in range(3):                 # PARAM_VALUE replies can be dropped when many are asked at once
            for name in REPORTED_PARAMS:
                if name not in self.params:
                    self.mav.mav.param_request_read_send(self.mav.target_system, self.mav.target_component,
                                                         name.encode('ascii'), -1)
                    self.spin(0.05)
            if self.spin(2.0, lambda: all(n in self.params for n in REPORTED_PARAMS)):
                break
        missing = [n for n in REPORTED_PARAMS if n not in self.params]
        if missing:
            _LOG.warning('parameters not reported: %s', ', '.join(missing))
        if self.version and not self.cfg.ardupilot_commit.startswith(self.version.lower()):
            _LOG.warning('ArduCopter reports git %s, not --ardupilot-commit %s', self.version,
                         self.cfg.ardupilot_commit[:12])

    @property
    def armed(self) -> bool:
        """The autopilot's last heartbeat says armed."""
        return bool(self.hb and self.hb.base_mode & self.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def arm_and_takeoff(self) -> None:
        """GUIDED, arm (retried while refused), takeoff to the hover altitude and settle there."""
        m, cfg = self.mavlink, self.cfg
        end = self.t + cfg.arm_timeout_s
        t_first = self.t
        while not self.armed:
            if self.t > end:
                raise SitlError(f'ArduCopter refused to arm for {cfg.arm_timeout_s:g} s of SITL time')
            if not (self.hb and self.hb.custom_mode == GUIDED):
                self.command(m.MAV_CMD_DO_SET_MODE, [float(m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(GUIDED)])
                self.spin(1.0, lambda: self.hb.custom_mode == GUIDED)
                continue
            r = self.command(m.MAV_CMD_COMPONENT_ARM_DISARM, [1.0])
            if r == m.MAV_RESULT_ACCEPTED:
                self.spin(2.0, lambda: self.armed)
            else:
                self.spin(2.0)
        _LOG.info('armed after %.1f s of retries (SITL time %.1f s)', self.t - t_first, self.t)
        rel = cfg.altitude_m - self.offset[2]
        r = self.command(m.MAV_CMD_NAV_TAKEOFF, [0, 0, 0, 0, 0, 0, rel])
        if r != m.MAV_RESULT_ACCEPTED:
            raise SitlError(f'takeoff refused (result {r})')
        # ArduCopter ends its takeoff ~0.1 m short of the target; goto() then holds the exact altitude
        if not self.spin(40.0, lambda: self._state()[0][2] > cfg.altitude_m - 0.3):
            raise SitlError(f'takeoff did not reach the hover altitude in 40 s: base_link at '
                            f'{self._state()[0][2]:.2f} m, ArduCopter says {self.ap_pos[2]:.2f} m (ENU z)')
        _LOG.info('took off: %.2f m at SITL time %.1f s', self._state()[0][2], self.t)

    def goto(self, xy, hover_s: float) -> None:
        """Fly to (x, y, altitude) with a position target, then hold it `hover_s` once there and still."""
        target = np.array([xy[0], xy[1], self.cfg.altitude_m])
        self.set_setpoint(lambda t: ('pos', target))

        def there() -> bool:
            pos, vel, _ = self._state()
            return float(np.linalg.norm(pos - target)) < 0.15 and float(np.linalg.norm(vel)) < 0.1
        if not self.spin(self.cfg.reach_timeout_s, there):
            pos = self._state()[0]
            _LOG.warning('not settled at %s within %.0f s (at %s); going on', np.round(target, 2),
                         self.cfg.reach_timeout_s, np.round(pos, 2))
        self.spin(hover_s)

    def fly_sequence(self, seq: Sequence) -> list[tuple]:
        """Hover at the start spot, then send the sequence's setpoints; its rows (t from the first setpoint)."""
        self.goto(seq.start_xy, self.cfg.hover_s)
        hz = self.cfg.command_hz
        t0 = self.t + self.runner.model.dt      # the next physics step: first setpoint and first row
        self.recorder = _Recorder(t0=t0)
        zero = np.zeros(3)

        def sp(t: float):
            k = int(math.floor((t - t0) * hz + 1e-6))
            return ('vel', seq.commands[k] if k < seq.n else zero)
        self.set_setpoint(sp, t0)
        self.spin(seq.n / hz - 0.5 / self.cfg.log_hz)
        rows, self.recorder = self.recorder.rows, None
        self.set_setpoint(lambda t: ('vel', zero))
        return rows

    def touchdown(self, lateral_mps: float, release: bool = False) -> tuple[dict, list[tuple]]:
        """Descend onto the floor (east command `lateral_mps` below 1 m, back to 0 at contact if `release`);
        contact and ON_GROUND times."""
        cfg, m = self.cfg, self.mavlink
        self.goto((0.0, 0.0), cfg.hover_s)
        t0 = self.t + self.runner.model.dt
        self.recorder = _Recorder(t0=t0, touchdown=True)
        res = {'contact': None, 'on_ground': None, 'ground_before_contact': None, 'v_contact': None}
        descent = cfg.touchdown_descent_mps

        def sp(t: float):
            touched = res['contact'] is not None
            low = self._state()[0][2] < 1.0 or touched
            east = lateral_mps if low and not (release and touched) else 0.0
            return ('vel', np.array([east, 0.0, -descent]))

        def watch() -> None:
            if res['contact'] is None and self.world._legs_touching():
                res['contact'] = self.t
                res['v_contact'] = self._state()[1]
                res['cmd_contact'] = self.cmd_now.copy()
            if self.landed_state == LANDED_ON_GROUND:
                if res['contact'] is None and res['ground_before_contact'] is None:
                    res['ground_before_contact'] = self.t
                elif res['contact'] is not None and res['on_ground'] is None:
                    res['on_ground'] = self.t
        self.set_setpoint(sp, t0)
        self.on_step = watch
        try:
            if not self.spin(40.0, lambda: res['contact'] is not None):
                raise SitlError('no ground contact within 40 s of descending')
            self.spin(cfg.touchdown_wait_s, lambda: res['on_ground'] is not None)
            self.spin(1.0)                       # a second more of the record after ON_GROUND
        finally:
            self.on_step = None
        rows, self.recorder = self.recorder.rows, None
        self.set_setpoint(None)
        # stop the motors: a plain disarm once ArduCopter knows it landed, else a forced one
        r = self.command(m.MAV_CMD_COMPONENT_ARM_DISARM, [0.0])
        if r != m.MAV_RESULT_ACCEPTED:
            self.command(m.MAV_CMD_COMPONENT_ARM_DISARM, [0.0, FORCE_DISARM_MAGIC])
        self.spin(3.0, lambda: not self.armed)
        self.spin(2.0)
        for k in ('contact', 'on_ground', 'ground_before_contact'):    # times from the record's start
            if res[k] is not None:
                res[k] -= t0
        return res, rows


# ---------------------------------------------------------------------------------------- main
def _header(cfg: IdentifyConfig, ident: Identifier, name: str, description: str, extra: list[str]) -> list[str]:
    speedup = ident.params.get('SIM_SPEEDUP')
    params = ' '.join(f'{k}={ident.params[k]:g}' for k in REPORTED_PARAMS if k in ident.params)
    return [f'sequence: {name}',
            f'description: {description}',
            f'ardupilot_commit: {cfg.ardupilot_commit} (AUTOPILOT_VERSION git: {ident.version or "not reported"})',
            'vehicle: ArduCopter SITL GUIDED, --model JSON:127.0.0.1, physics assist_sim quad_json.py (in process)',
            f'sitl_defaults: {cfg.sitl_defaults}',
            f'ardupilot_params: {params}',
            f'sitl_speedup: {speedup:g}' if speedup is not None else 'sitl_speedup: not reported',
            f'turbulence: {"on" if cfg.turbulence else "off"}, seed {cfg.seed}',
            'setpoints: SET_POSITION_TARGET_LOCAL_NED type_mask 1479 (velocity, yaw_rate 0), '
            f'{cfg.command_hz:g} Hz; log {cfg.log_hz:g} Hz on physics time',
            'frames: ENU world (x east, y north, z up; base_link; floor z = 0); cmd = setpoint last sent; '
            'ap_* = ArduCopter LOCAL_POSITION_NED in ENU world (last received)',
            *extra,
            f'date_utc: {datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")}',
            'command: sitl_identify ' + ' '.join(shlex.quote(a) for a in sys.argv[1:])]


def _nan_safe(x) -> str:
    return 'nan' if x is None or not math.isfinite(x) else f'{x:.3f}'


def run(cfg: IdentifyConfig) -> int:
    """Fly everything and write the files; 0 on success."""
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    seqs = build_sequences(cfg.command_hz)
    ident = Identifier(cfg)
    try:
        ident.connect()
        ident.arm_and_takeoff()
        for name in cfg.selected():
            seq = seqs[name]
            wall0, t0 = time.monotonic(), ident.t
            rows = ident.fly_sequence(seq)
            _LOG.info('%s: %d rows, %.1f s SITL in %.1f s wall', name, len(rows), ident.t - t0,
                      time.monotonic() - wall0)
            header = _header(cfg, ident, name, seq.description,
                             [f'start_enu: {seq.start_xy[0]:g},{seq.start_xy[1]:g},{cfg.altitude_m:g}'])
            write_text_atomic(out / f'{name}.csv', fixture_text(header, COLUMNS + EXTRA_COLUMNS, rows))
        summary = []
        for i, (trial, lateral, release) in enumerate(touchdown_trials(cfg)):
            if i > 0 or not ident.armed:
                ident.arm_and_takeoff()
            res, rows = ident.touchdown(lateral, release)
            tc, tg, tb = res['contact'], res['on_ground'], res['ground_before_contact']
            v = res['v_contact']
            row = {'trial': trial, 'lateral_cmd_mps': lateral, 'lateral_released_at_contact': int(release),
                   'descent_cmd_mps': cfg.touchdown_descent_mps,
                   't_contact_s': tc, 't_on_ground_s': tg,
                   'delay_s': (tg - tc) if tg is not None else None,
                   'on_ground_came': int(tg is not None),
                   'on_ground_before_contact': int(tb is not None),
                   'vel_contact_z': float(v[2]), 'vel_contact_xy': float(np.hypot(v[0], v[1])),
                   'cmd_contact_x': float(res['cmd_contact'][0])}
            summary.append(row)
            header = _header(cfg, ident, f'touchdown_{trial}',
                             f'descend at {cfg.touchdown_descent_mps:g} m/s onto the floor, east command '
                             f'{lateral:g} m/s below 1 m{", 0 from contact on" if release else ""}; '
                             'contact = a leg touches (our physics), '
                             'ap_landed_state = EXTENDED_SYS_STATE.landed_state (1 ON_GROUND, 2 IN_AIR)',
                             ['start_enu: 0,0,' + f'{cfg.altitude_m:g}'])
            write_text_atomic(out / f'touchdown_{trial}.csv',
                              fixture_text(header, COLUMNS + EXTRA_COLUMNS + TOUCHDOWN_COLUMNS, rows))
            _LOG.info('touchdown %s: contact -> ON_GROUND %s s (came: %s)', trial,
                      _nan_safe(row['delay_s']), bool(row['on_ground_came']))
        if summary:
            write_text_atomic(out / 'touchdown.csv', _touchdown_text(cfg, ident, summary))
    finally:
        ident.close()
    return 0


def _touchdown_text(cfg: IdentifyConfig, ident: Identifier, summary: list) -> str:
    cols = ('trial', 'lateral_cmd_mps', 'lateral_released_at_contact', 'descent_cmd_mps', 't_contact_s',
            't_on_ground_s', 'delay_s', 'on_ground_came', 'on_ground_before_contact', 'vel_contact_z',
            'vel_contact_xy', 'cmd_contact_x')
    header = _header(cfg, ident, 'touchdown', 'touchdown series summary: times in s from the start of each '
                     'trial\'s record (touchdown_<trial>.csv t_s); delay = ON_GROUND - first contact; '
                     'nan = never came', [])
    lines = [f'# {h}' for h in header] + [','.join(cols)]
    for row in summary:
        lines.append(','.join(str(row[c]) if isinstance(row[c], (str, int)) else _nan_safe(row[c]) for c in cols))
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    """Command line (see the module docstring)."""
    cfg, _ = parse_settings(IdentifyConfig, __doc__.split('\n\n')[0], argv, prog='sitl_identify')
    if cfg.list:
        for s in build_sequences(cfg.command_hz).values():
            sys.stdout.write(f'{s.name:<15} {s.n / cfg.command_hz:5.1f} s  {s.description}\n')
        return 0
    existing = [n for n in output_files(cfg) if (Path(cfg.out) / n).exists()]
    if existing and not cfg.force:
        exit_error('sitl_identify', f'{cfg.out} already holds {", ".join(existing[:3])}'
                   f'{" ..." if len(existing) > 3 else ""}; --force to overwrite', 2)
    logging.basicConfig(level=logging.INFO, format='%(asctime)s %(name)s: %(message)s')
    try:
        return run(cfg)
    except (SitlError, OSError) as exc:
        exit_error('sitl_identify', exc, 1)


if __name__ == '__main__':
    sys.exit(main())
