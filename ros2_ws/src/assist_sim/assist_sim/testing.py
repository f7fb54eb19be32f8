"""Helpers shared by the packages' tests, the cross-package tests and the benches (no rclpy, no pytest).

Package tests cannot see tests/conftest.py, so what more than one of them needs lives here:
a free UDP port for MAVLink loopback links, a clean stop for a node subprocess, and a kinematic
stand-in for LandingWorld that the MAVLink vehicle can fly without pybullet.
"""
from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
from types import SimpleNamespace
from typing import Sequence

import numpy as np


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
        """position, velocity (ENU), quaternion (x, y, z, w), angular_velocity, yaw, time."""
        q = np.array([0.0, 0.0, math.sin(self.yaw / 2), math.cos(self.yaw / 2)])
        return SimpleNamespace(position=self.pos.copy(), velocity=self.vel.copy(), quaternion=q,
                               angular_velocity=np.zeros(3), yaw=self.yaw, time=0.0)

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
