"""Helpers shared by the packages' tests, the cross-package tests and the benches (no rclpy, no pytest).

Package tests cannot see tests/conftest.py, so what more than one of them needs lives here:
a free UDP port for MAVLink loopback links, a clean stop for a node subprocess, a kinematic
stand-in for LandingWorld that the MAVLink vehicle can fly without pybullet, that vehicle stepping in
real time on its own thread (VehicleThread), and an autopilot that
is always in GUIDED and armed but answers nothing (the bridge's bench and graph tests).
"""
from __future__ import annotations

import math
import os
import signal
import socket
import struct
import subprocess
import threading
import time
from types import SimpleNamespace
from collections.abc import Sequence

import numpy as np

from assist_common.mavlink_io import mavlink, mavutil

from .mavlink_vehicle import MavlinkVehicle, MavlinkVehicleConfig

SO_TIMESTAMPNS = getattr(socket, 'SO_TIMESTAMPNS', 35)   # Linux value; Python < 3.12 has no constant


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nobody is bound to right now."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(('127.0.0.1', 0))
    port = s.getsockname()[1]
    s.close()
    return port


def stop_process(proc: subprocess.Popen, timeout: float = 10.0) -> int:
    """SIGINT a node process (started with start_new_session=True), SIGKILL its group if it hangs; exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)
    return proc.returncode


class KinematicWorld:
    """Stand-in for LandingWorld: flies the commanded body-FLU velocity exactly, floor at z = 0.

    Yaw turns toward its target at 2 rad/s. Disarmed, it stops (`fall_when_disarmed` False) or
    drops at 1 m/s to the floor. Has what MavlinkVehicle uses: reset, step, state, landed,
    set_armed, set_yaw_target, episode, scene.
    """

    def __init__(self, start_xy: Sequence[float] = (0.0, 0.0), start_altitude_m: float = 1.5,
                 fall_when_disarmed: bool = False):
        self.start_xy = np.asarray(start_xy, dtype=float)
        self.start_altitude_m = float(start_altitude_m)
        self.fall_when_disarmed = fall_when_disarmed
        self.episode, self.scene, self.armed = -1, None, False
        self.pos, self.vel = np.zeros(3), np.zeros(3)
        self.yaw, self.yaw_target = 0.0, 0.0
        self.last_cmd_flu = np.zeros(3)

    def reset(self, seed=None, *, airborne: bool = True, **kwargs):
        """New episode at the start point, airborne (and armed) or on the floor."""
        self.episode += 1
        self.scene = 'kinematic'
        self.pos = np.array([*self.start_xy, self.start_altitude_m if airborne else 0.0])
        self.vel, self.yaw, self.armed = np.zeros(3), 0.0, airborne
        return self.state

    def set_armed(self, armed: bool) -> None:
        """Motors on or off."""
        self.armed = bool(armed)

    def set_yaw_target(self, yaw: float) -> None:
        """Heading (ENU, rad) to turn to."""
        self.yaw_target = float(yaw)

    @property
    def landed(self) -> bool:
        """On the floor and (nearly) still."""
        return self.pos[2] <= 1e-9 and np.linalg.norm(self.vel) < 0.2

    @property
    def state(self) -> SimpleNamespace:
        """position, velocity (ENU), quaternion (x, y, z, w), angular_velocity, yaw, time, height_above_surface."""
        q = np.array([0.0, 0.0, math.sin(self.yaw / 2), math.cos(self.yaw / 2)])
        return SimpleNamespace(position=self.pos.copy(), velocity=self.vel.copy(), quaternion=q,
                               angular_velocity=np.zeros(3), yaw=self.yaw, time=0.0,
                               height_above_surface=float(self.pos[2]))

    def step(self, cmd_flu, dt: float | None = None) -> SimpleNamespace:
        """Fly `cmd_flu` (m/s, body FLU) for `dt` seconds."""
        cmd_flu = np.asarray(cmd_flu, dtype=float).reshape(3)
        if not np.all(np.isfinite(cmd_flu)):
            raise ValueError(f'non-finite command {cmd_flu}')
        self.last_cmd_flu = cmd_flu
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        if self.armed:
            v = np.array([c * cmd_flu[0] - s * cmd_flu[1], s * cmd_flu[0] + c * cmd_flu[1], cmd_flu[2]])
        elif self.fall_when_disarmed:
            v = np.array([0.0, 0.0, -1.0 if self.pos[2] > 0 else 0.0])
        else:
            v = np.zeros(3)
        self.vel = v
        self.pos = self.pos + v * dt
        if self.pos[2] < 0.0:
            self.pos[2] = 0.0
            self.vel[:] = 0.0
        err = (self.yaw_target - self.yaw + math.pi) % (2 * math.pi) - math.pi
        self.yaw += max(-2.0 * dt, min(2.0 * dt, err))
        return self.state


class VehicleThread:
    """The MAVLink ArduCopter stand-in (MavlinkVehicle) flying `world` (a KinematicWorld by default) in
    real time on its own thread, sending to udpout:127.0.0.1:`port`; `cfg` are MavlinkVehicleConfig fields."""

    def __init__(self, port: int, world=None, step_s: float = 0.02, **cfg):
        self.world = world or KinematicWorld()
        self.vehicle = MavlinkVehicle(self.world, f'udpout:127.0.0.1:{port}', MavlinkVehicleConfig(**cfg))
        self._step_s = step_s
        self._run = True
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while self._run:
            self.vehicle.step(self._step_s)
            time.sleep(self._step_s)

    def stop(self) -> None:
        """Stop stepping and close the link (a second call does nothing)."""
        if self._run:
            self._run = False
            self.thread.join()
            self.vehicle.close()


class SilentAutopilot:
    """ArduCopter-looking endpoint on UDP loopback that never answers a command.

    Sends HEARTBEAT (GUIDED, armed) at 1 Hz and ATTITUDE (level, heading `yaw_ned_rad`) at 10 Hz to
    a bridge listening on `port`; records every SET_POSITION_TARGET_LOCAL_NED with the kernel's
    receive stamp (SO_TIMESTAMPNS, CLOCK_REALTIME: compare with time.time()), so the time is when
    the datagram arrived, not when this receive thread woke up; records COMMAND_LONG ids; and keeps
    every other message of the types in `keep` (`received(type)`).
    """

    def __init__(self, port: int, yaw_ned_rad: float = 0.0,
                 keep: tuple[str, ...] = ('VISION_POSITION_ESTIMATE', 'SET_GPS_GLOBAL_ORIGIN'),
                 send_position: bool = False):
        self.keep = set(keep)
        self.send_position = send_position      # also LOCAL_POSITION_NED (hovering at 1 m): the bridge's /odom
        self._kept: list[tuple[float, object]] = []
        self.conn = mavutil.mavlink_connection(f'udpout:127.0.0.1:{port}', source_system=1, source_component=1,
                                               dialect='ardupilotmega')
        self.yaw_ned_rad = float(yaw_ned_rad)
        self._lock = threading.Lock()
        self._setpoints: list[tuple[float, float, float]] = []   # (arrival time, vx, vy) NED
        self._commands: list[int] = []
        self._error: Exception | None = None                     # what stopped the receive thread
        self._run = True
        self._threads = [threading.Thread(target=self._rx, daemon=True), threading.Thread(target=self._tx, daemon=True)]
        for t in self._threads:
            t.start()

    def _tx(self) -> None:
        n = 0
        while self._run:
            if n % 10 == 0:
                self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                             mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
                                             | mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 4, mavlink.MAV_STATE_ACTIVE)
            self.conn.mav.attitude_send(n * 100, 0.0, 0.0, self.yaw_ned_rad, 0.0, 0.0, 0.0)
            if self.send_position:
                self.conn.mav.local_position_ned_send(n * 100, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0)
            n += 1
            time.sleep(0.1)

    def _rx(self) -> None:
        try:
            self._receive()
        except Exception as exc:  # noqa: BLE001 - handed to the caller by setpoints() / commands()
            self._error = exc

    def _receive(self) -> None:
        sock = self.conn.port
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        sock.settimeout(0.05)
        while self._run:
            try:
                data, anc, _flags, _addr = sock.recvmsg(4096, socket.CMSG_SPACE(16))
            except (TimeoutError, BlockingIOError):
                continue
            t = time.time()
            for level, kind, raw in anc:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(raw) >= 16:
                    sec, nsec = struct.unpack('qq', raw[:16])
                    t = sec + nsec * 1e-9
            for m in self.conn.mav.parse_buffer(data) or ():
                with self._lock:
                    if m.get_type() == 'SET_POSITION_TARGET_LOCAL_NED':
                        self._setpoints.append((t, float(m.vx), float(m.vy)))
                    elif m.get_type() == 'COMMAND_LONG':
                        self._commands.append(int(m.command))
                    elif m.get_type() in self.keep:
                        self._kept.append((t, m))

    def _check(self) -> None:
        if self._error is not None:
            raise RuntimeError(f'silent autopilot receive thread failed: {self._error!r}') from self._error

    def setpoints(self) -> list[tuple[float, float, float]]:
        """Velocity setpoints received so far: (kernel arrival time, vx, vy) in NED."""
        self._check()
        with self._lock:
            return list(self._setpoints)

    def commands(self) -> list[int]:
        """MAV_CMD ids of the COMMAND_LONGs received so far."""
        self._check()
        with self._lock:
            return list(self._commands)

    def received(self, mtype: str) -> list[tuple[float, object]]:
        """(arrival time, message) of every kept message of type `mtype` so far."""
        self._check()
        with self._lock:
            return [(t, m) for t, m in self._kept if m.get_type() == mtype]

    def close(self) -> None:
        """Stop both threads and close the link."""
        self._run = False
        for t in self._threads:
            t.join(timeout=1.0)
        self.conn.close()


class RecordingWorld(KinematicWorld):
    """KinematicWorld that keeps (height before the step, commanded body FLU velocity) of every step."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.lock = threading.Lock()
        self.steps: list[tuple[float, np.ndarray]] = []

    def step(self, cmd_flu, dt=None):
        with self.lock:
            self.steps.append((float(self.pos[2]), np.array(cmd_flu, dtype=float)))
        return super().step(cmd_flu, dt)

    def flown(self) -> list[tuple[float, np.ndarray]]:
        """Every step so far: (height before it, commanded body FLU velocity)."""
        with self.lock:
            return list(self.steps)
