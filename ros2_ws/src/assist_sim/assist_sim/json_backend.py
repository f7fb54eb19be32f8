"""ArduPilot SITL JSON physics backend: UDP protocol, lock-step server and the sim_node runner.

Pure Python (socket, json, numpy, pybullet through assist_sim.core), no rclpy. The protocol was
checked against ArduPilot's own source at commit 90700977c553 (libraries/SITL/SIM_JSON.h, SIM_JSON.cpp,
libraries/SITL/examples/JSON/readme.md and examples/JSON/pybullet/robot.py):

* SITL -> physics, UDP to port 9002, little-endian `struct servo_packet_16 { uint16 magic = 18458;
  uint16 frame_rate; uint32 frame_count; uint16 pwm[16]; }` (40 bytes), or `servo_packet_32`
  (magic 29569, pwm[32], 72 bytes) when SERVO_32_ENABLE = 1. We reply to the packet's source address.
* physics -> SITL: one JSON object preceded AND terminated by "\\n". SITL turns every "\\n" into NUL
  and parses the text between the last two NULs, so without the leading newline the very first
  reply is never parsed. Its parser is strstr + sscanf, not a JSON parser: a key must be followed
  directly by `":` and the value (no space: json.dumps separators=(',', ':')), vectors as
  `[a,b,c]`. Required: timestamp, imu.gyro, imu.accel_body, position, velocity and one of
  attitude / quaternion (quaternion wins when both are sent). Optional rng_1..rng_6 etc.
  A reply missing a required field is dropped by SITL without advancing its frame_count.
* Time: SITL advances its clock by (timestamp - last timestamp); a timestamp that goes backwards
  is a "physics reset" (deltat 0). Only steps 0 < deltat < 0.1 s pace SITL's frame timing, so we
  send the physics time of the current SITL session (0 at each SITL start) and step exactly
  1/frame_rate per new frame (lock-step: SITL waits for our reply, SITL sets the pace).
* frame_count increments only after SITL parsed a reply; with no reply for ~1 s SITL re-sends the
  same frame (same count). We answer a repeated count with the previous reply, physics not
  stepped (upstream's pybullet example drops duplicates without a reply, which leaves SITL
  re-sending forever once a reply is lost). A count lower than the last one means SITL restarted:
  the vehicle is reset. SITL's source port changes on restart, so every datagram is answered to
  its own source address (the socket binds to loopback by default).
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import socket
import struct
import time
from dataclasses import dataclass
from collections.abc import Callable

import numpy as np

from .core.quad_json import QuadJsonConfig, QuadJsonModel
from .core.runner import RunnerConfig, StepOutput
from .core.world import LandingWorld, VehicleState

_LOG = logging.getLogger(__name__)

MAGIC_16 = 18458
MAGIC_32 = 29569
HEADER = struct.Struct('<HHI')
PACKET_16 = struct.Struct('<HHI16H')
PACKET_32 = struct.Struct('<HHI32H')


@dataclass(frozen=True)
class ServoPacket:
    """One decoded SITL servo output packet."""

    frame_rate: int
    frame_count: int
    pwm: tuple[int, ...]


def decode_servo_packet(data: bytes, min_rate: int = 1, max_rate: int = 10000) -> tuple[ServoPacket | None, str]:
    """Decode a SITL datagram: (packet, '') or (None, reason) with reason in
    'bad_length', 'bad_magic', 'bad_frame_rate'."""
    if len(data) < HEADER.size:
        return None, 'bad_length'
    magic = HEADER.unpack_from(data)[0]
    if magic == MAGIC_16:
        fmt = PACKET_16
    elif magic == MAGIC_32:
        fmt = PACKET_32
    else:
        return None, 'bad_magic'
    if len(data) != fmt.size:
        return None, 'bad_length'
    fields = fmt.unpack(data)
    rate, count = fields[1], fields[2]
    if not min_rate <= rate <= max_rate:
        return None, 'bad_frame_rate'
    return ServoPacket(frame_rate=rate, frame_count=count, pwm=tuple(fields[3:])), ''


def encode_servo_packet(frame_rate: int, frame_count: int, pwm, channels: int = 16) -> bytes:
    """Encode a servo packet as SITL sends it (used by stand-ins and the bench)."""
    vals = [int(x) for x in pwm] + [0] * channels
    if channels == 16:
        return PACKET_16.pack(MAGIC_16, frame_rate, frame_count & 0xFFFFFFFF, *vals[:16])
    if channels == 32:
        return PACKET_32.pack(MAGIC_32, frame_rate, frame_count & 0xFFFFFFFF, *vals[:32])
    raise ValueError('channels must be 16 or 32')


def encode_reply(fields: dict) -> bytes:
    """One SITL JSON input frame: "\\n" + compact JSON + "\\n"; raises ValueError on a non-finite value."""
    text = json.dumps(fields, separators=(',', ':'), allow_nan=False)
    return b'\n' + text.encode('ascii') + b'\n'


@dataclass
class JsonBackendConfig:
    """Where to listen and how to judge the link."""

    host: str = '127.0.0.1'
    port: int = 9002
    min_frame_rate_hz: int = 100          # SIM_RATE_HZ outside [min, max] is refused (counted)
    max_frame_rate_hz: int = 4000
    silence_timeout_s: float = 1.0        # no packet for this long (wall clock) -> SITL silent
    send_rangefinder: bool = True         # rng_1 (set RNGFND1_TYPE 100 in ArduPilot)


class JsonPhysicsServer:
    """Lock-step UDP server: each new SITL frame steps `model` once and is answered with its sensors."""

    COUNTERS = ('rx_packets', 'bad_magic', 'bad_length', 'bad_frame_rate', 'duplicate_frames',
                'missed_frames', 'sitl_restarts', 'replies', 'reply_errors')

    def __init__(self, model: QuadJsonModel, cfg: JsonBackendConfig | None = None,
                 origin_enu=(0.0, 0.0, 0.0), clock: Callable[[], float] = time.monotonic):
        self.model = model
        self.cfg = cfg or JsonBackendConfig()
        self.origin_enu = np.asarray(origin_enu, dtype=float)
        self._clock = clock
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.bind((self.cfg.host, int(self.cfg.port)))
        except OSError:
            self.sock.close()
            raise
        self.address = self.sock.getsockname()
        self.counters = {k: 0 for k in self.COUNTERS}
        self.last_frame_count: int | None = None
        self.last_pwm: tuple[int, ...] = (0,) * 16
        self.frame_rate: int | None = None
        self.session_time = 0.0           # physics time of this SITL session (JSON timestamp)
        self.peer = None
        self.last_packet_wall: float | None = None
        self._last_reply: bytes | None = None
        self.on_restart: Callable[[], None] | None = None   # called before stepping a restarted SITL

    # ------------------------------------------------------------------ link state
    @property
    def connected(self) -> bool:
        """A valid packet arrived at least once."""
        return self.last_packet_wall is not None

    def silent_for(self) -> float:
        """Wall seconds since the last valid packet (inf before the first)."""
        return math.inf if self.last_packet_wall is None else self._clock() - self.last_packet_wall

    @property
    def silent(self) -> bool:
        """No valid packet for longer than silence_timeout_s (or never)."""
        return self.silent_for() > self.cfg.silence_timeout_s

    # ------------------------------------------------------------------ serving
    def poll(self, timeout: float) -> str | None:
        """Wait up to `timeout` s for one datagram and handle it.

        Returns 'step' (physics advanced one frame, reply sent), 'restart' (SITL restarted: vehicle
        reset through on_restart, then stepped and answered), 'duplicate' (previous reply re-sent),
        'dropped' (malformed, counted) or None (nothing arrived)."""
        self.sock.settimeout(max(0.0, timeout))
        try:
            data, addr = self.sock.recvfrom(2048)
        except (TimeoutError, BlockingIOError):
            return None
        except OSError as exc:          # e.g. ICMP port unreachable from a previous reply on some stacks
            _LOG.debug('recvfrom: %s', exc)
            return None
        return self.handle(data, addr)

    def handle(self, data: bytes, addr) -> str:
        """Handle one datagram from `addr` (see poll)."""
        self.counters['rx_packets'] += 1
        pkt, reason = decode_servo_packet(data, self.cfg.min_frame_rate_hz, self.cfg.max_frame_rate_hz)
        if pkt is None:
            self.counters[reason] += 1
            _LOG.debug('dropped SITL packet from %s: %s (%d bytes)', addr, reason, len(data))
            return 'dropped'
        self.last_packet_wall = self._clock()
        self.peer = addr
        event = 'step'
        last = self.last_frame_count
        if last is not None and pkt.frame_count == last and self._last_reply is not None:
            self.counters['duplicate_frames'] += 1
            self._send(self._last_reply, addr)
            return 'duplicate'
        if last is not None and pkt.frame_count < last:
            self.counters['sitl_restarts'] += 1
            _LOG.warning('SITL frame_count went back from %d to %d: SITL restarted, resetting the vehicle',
                         last, pkt.frame_count)
            self.session_time = 0.0
            if self.on_restart is not None:
                self.on_restart()
            event = 'restart'
        elif last is not None and pkt.frame_count > last + 1:
            self.counters['missed_frames'] += pkt.frame_count - last - 1
        self.last_frame_count = pkt.frame_count
        self.last_pwm = pkt.pwm
        if pkt.frame_rate != self.frame_rate:
            self.frame_rate = pkt.frame_rate
            self.model.set_rate(pkt.frame_rate)
        self.model.step(pkt.pwm)
        self.session_time += self.model.dt
        try:
            reply = encode_reply(self.model.sensors(self.session_time, self.origin_enu,
                                                    rangefinder=self.cfg.send_rangefinder))
        except ValueError as exc:       # non-finite state: never send it; SITL re-sends and waits
            self.counters['reply_errors'] += 1
            self._last_reply = None     # the re-sent frame is served afresh, not with an older reply
            _LOG.error('physics state not finite, no reply sent: %s', exc)
            return event
        self._last_reply = reply
        self._send(reply, addr)
        return event

    def _send(self, reply: bytes, addr) -> None:
        try:
            self.sock.sendto(reply, addr)
            self.counters['replies'] += 1
        except OSError as exc:
            self.counters['reply_errors'] += 1
            _LOG.warning('cannot answer SITL at %s: %s', addr, exc)

    def motors_stopped(self, pwm_max: float) -> bool:
        """All four motor outputs at or below `pwm_max` (disarmed: ArduCopter outputs MOT_PWM_MIN)."""
        return all(int(x) <= pwm_max for x in self.last_pwm[:4])

    def close(self) -> None:
        """Close the socket."""
        self.sock.close()


@dataclass
class JsonRunnerConfig:
    """Episodes in ardupilot_json mode."""

    start_xy_m: tuple[float, float] = (0.0, 0.0)   # every episode starts landed here (the EKF origin)
    disarmed_pwm_max: float = 1050.0     # motors at/below this = disarmed (MOT_PWM_MIN 1000; SPIN_ARM gives 1100)
    poll_timeout_s: float = 0.1          # longest one step() waits for SITL before returning


class JsonSimRunner:
    """sim_node's runner for `physics: ardupilot_json`: same interface as core.runner.SimRunner.

    Each `step()` serves SITL until one control period (1/control_hz of physics time) has passed
    or `poll_timeout_s` of wall time went by without SITL (then the vehicle holds: physics is
    lock-stepped to SITL and does not advance). Episodes start landed and disarmed at
    `start_xy_m`; after a landing (same judge as velocity mode) the next episode starts once SITL
    has disarmed (all motors at minimum PWM) for `reset_delay_s`, by teleporting the airframe and
    rebuilding the scene. A /sim/reset while the motors spin is deferred until they stop. The
    episode clock (duration_s, the judge's max_episode_s) starts at takeoff, when the judge arms.

    Episodes are counted by landings and resets, not by SITL restarts: a landing result (then the
    automatic reset) or a /sim/reset starts the next episode k + 1, in the scene `cfg.episode_seeds[k + 1]`
    (past the list's end, or without one, the world's own sequence), while a SITL restart before the
    landing (a reboot after a crash or a refused arming) starts episode k again, with the same number
    and, with episode_seeds, the same scene. So an evaluation plan's scenes come in the same order
    whatever restarts a run needs. A SITL restart while airborne ends the landing as a timeout ('SITL
    restarted in flight'): the vehicle is back on the ground at the start spot, so it cannot go on.
    """

    def __init__(self, world: LandingWorld, cfg: RunnerConfig | None = None,
                 backend_cfg: JsonBackendConfig | None = None, json_cfg: JsonRunnerConfig | None = None,
                 model_cfg: QuadJsonConfig | None = None, seed: int = 0, diag=None):
        self.world = world
        self.cfg = cfg or RunnerConfig(airborne_start=False)
        self.json_cfg = json_cfg or JsonRunnerConfig()
        self.model = QuadJsonModel(world, model_cfg, seed=seed)
        x0, y0 = self.json_cfg.start_xy_m
        self.server = JsonPhysicsServer(self.model, backend_cfg, origin_enu=(x0, y0, 0.0))
        self.server.on_restart = self._on_sitl_restart
        self.diag = diag
        self._agent_seen = False
        self._next_frame_time = 0.0
        self._landed_at: float | None = None
        self._stopped_since: float | None = None
        self._reset_pending = False
        self._airborne = False
        self.episodes_finished = 0
        self.commands_rejected = 0
        self._aborted = None              # the landing a SITL restart in flight ended (reported by step())
        self._episode_index = -1          # the current episode's number: index into cfg.episode_seeds

    # -------------------------------------------------------------- interface shared with SimRunner
    @property
    def odom_offset(self) -> np.ndarray:
        """World (ENU) position of the autopilot's odom origin: base_link resting at the start spot.

        ArduPilot's LOCAL_NED origin is where its EKF initialised, i.e. the vehicle on the ground at
        the start spot, so /odom from the bridge = world - odom_offset; /sim/goal is published in
        that frame in this mode."""
        x0, y0 = self.json_cfg.start_xy_m
        return np.array([x0, y0, self.world.cfg.vehicle.leg_length_m + 0.002])

    def markers_in_odom(self, boxes: list) -> list:
        """/sim/scene boxes (core.scene_markers.BoxMarker, world frame) moved into the odom frame."""
        off = self.odom_offset
        return [dataclasses.replace(b, center=tuple(float(c - o) for c, o in zip(b.center, off))) for b in boxes]

    def set_command(self, v) -> str | None:
        """Velocity commands go to ArduPilot through the bridge, not to the sim."""
        self.commands_rejected += 1
        return 'physics is ardupilot_json: fly through mavlink_bridge_node'

    def note_agent_command(self) -> None:
        """Record that the assistant was live during this episode."""
        self._agent_seen = True

    @property
    def reset_pending(self) -> bool:
        """A reset waits for the motors to stop."""
        return self._reset_pending

    def reset(self, seed: int | None = None) -> VehicleState:
        """New scene and episode, vehicle landed at the start spot; deferred while the motors spin."""
        if self.server.connected and not self.server.motors_stopped(self.json_cfg.disarmed_pwm_max):
            self._reset_pending = True
            _LOG.info('reset deferred until SITL disarms (motors spinning)')
            return self.world.state
        return self._reset_now(seed)

    def _reset_now(self, seed: int | None = None, advance: bool = True) -> VehicleState:
        """Start the next episode (`advance`) or the current one again (a SITL restart before its landing)."""
        x0, y0 = self.json_cfg.start_xy_m
        if advance or self._episode_index < 0:
            self._episode_index += 1
        k = self._episode_index
        if seed is None and k < len(self.cfg.episode_seeds):
            seed = int(self.cfg.episode_seeds[k])
        state = self.world.reset(seed, start_position=(x0, y0, 0.0), airborne=False)
        self.world.episode = k          # not counting SITL restarts (see the class docstring)
        self.model.reset()
        self._agent_seen = False
        self._landed_at = None
        self._stopped_since = None
        self._reset_pending = False
        self._airborne = False
        self._next_frame_time = self.world.time
        return state

    def _on_sitl_restart(self) -> None:
        w = self.world
        if self._airborne and not w.done:        # the landing cannot go on: it ends here, reported by step()
            w._finish('timeout', None, 'SITL restarted in flight')
            w.result.assisted = self._agent_seen
            self._aborted = w.result
            self.episodes_finished += 1
            _LOG.warning('episode %d ended: SITL restarted in flight', w.episode)
        self._reset_now(advance=w.done)           # before its landing: the same episode again

    def step(self, fly=None) -> StepOutput:
        """Serve SITL for one control period (or until it is silent for poll_timeout_s)."""
        w, srv = self.world, self.server
        period_end = w.time + 1.0 / w.cfg.control_hz - 1e-9
        wall_end = time.monotonic() + self.json_cfg.poll_timeout_s
        out_landing, frame, new_episode = None, None, False
        while w.time < period_end:
            was_done = w.done
            ev = srv.poll(max(0.0, wall_end - time.monotonic()))
            if ev is None:
                break
            if ev == 'restart':          # on_restart already reset the vehicle before this frame
                new_episode = True
                if self._aborted is not None:
                    out_landing, self._aborted = self._aborted, None
            if ev not in ('step', 'restart'):
                if time.monotonic() >= wall_end:
                    break
                continue
            wall_end = time.monotonic() + self.json_cfg.poll_timeout_s
            if w._judge_active and not self._airborne:
                # the judge starts at takeoff; so does the episode clock here: arming SITL takes tens
                # of seconds on the ground, which must not count against max_episode_s
                self._airborne = True
                w.episode_time = 0.0
            if w.done and not was_done:
                w.result.assisted = self._agent_seen
                out_landing = w.result
                self.episodes_finished += 1
                self._landed_at = w.time
            if self.cfg.camera_rate_hz > 0 and w.time + 1e-9 >= self._next_frame_time:
                frame = w.render()      # after the reply: SITL is not kept waiting for the render
                self._next_frame_time += 1.0 / self.cfg.camera_rate_hz
                if self._next_frame_time < w.time:
                    self._next_frame_time = w.time + 1.0 / self.cfg.camera_rate_hz
            if self._maybe_reset():
                new_episode = True
        self._report()
        return StepOutput(state=w.state, frame=frame, landing=out_landing, new_episode=new_episode)

    def _maybe_reset(self) -> bool:
        w = self.world
        if not (self._reset_pending or (self.cfg.auto_reset and self._landed_at is not None)):
            return False
        if not self.server.motors_stopped(self.json_cfg.disarmed_pwm_max):
            self._stopped_since = None
            return False
        if self._stopped_since is None:
            self._stopped_since = w.time
        if self._reset_pending or w.time - self._stopped_since >= self.cfg.reset_delay_s:
            self._reset_now()
            return True
        return False

    def _report(self) -> None:
        if self.diag is None:
            return
        srv = self.server
        for k, v in srv.counters.items():
            self.diag.set(f'json_{k}', v)
        self.diag.set('json_frame_rate_hz', srv.frame_rate or 0)
        self.diag.set('json_session_time_s', f'{srv.session_time:.2f}')
        self.diag.set('json_motor_pwm', list(srv.last_pwm[:4]))
        host, port = srv.address[0], srv.address[1]
        c = srv.counters
        dropped = c['bad_magic'] + c['bad_length'] + c['bad_frame_rate']
        if not srv.connected and dropped:
            self.diag.status(2, f'no valid SITL packet on udp {host}:{port}: dropped {c["bad_magic"]} with a wrong '
                                f'magic, {c["bad_length"]} with a wrong length, {c["bad_frame_rate"]} with a '
                                f'frame rate outside {srv.cfg.min_frame_rate_hz}-{srv.cfg.max_frame_rate_hz} Hz')
        elif not srv.connected:
            self.diag.status(1, f'waiting for ArduPilot SITL (JSON) on udp {host}:{port}')
        elif srv.silent:
            self.diag.status(2, f'SITL silent for {srv.silent_for():.1f} s: physics paused, vehicle holds')
        else:
            self.diag.status(0, f'SITL connected ({srv.frame_rate} Hz, frame {srv.last_frame_count})')

    def close(self) -> None:
        """Release the UDP socket."""
        self.server.close()


__all__ = ['MAGIC_16', 'MAGIC_32', 'ServoPacket', 'decode_servo_packet', 'encode_servo_packet', 'encode_reply',
           'JsonBackendConfig', 'JsonPhysicsServer', 'JsonRunnerConfig', 'JsonSimRunner', 'make_json_runner']


def make_json_runner(world: LandingWorld, runner_cfg: RunnerConfig, params, diag=None) -> JsonSimRunner:
    """JsonSimRunner from sim_node's parameters (json_host, json_port, json_silence_timeout_s, seed);
    raises OSError when the UDP port cannot be bound."""
    backend = JsonBackendConfig(host=str(params['json_host']), port=int(params['json_port']),
                                silence_timeout_s=float(params['json_silence_timeout_s']))
    return JsonSimRunner(world, runner_cfg, backend, seed=int(params['seed']), diag=diag)
