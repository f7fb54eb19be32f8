"""When a flight begins and ends, from what a real vehicle has: odometry and the command flown.

The assistant's memories (action history, pad and wall maps, landing spots, override and damper state)
belong to one flight (ARCHITECTURE.md, "Flights and the assistant's memory"). ``FlightMonitor.update`` is
called once per control step by policy_node's core and by the training/evaluation env alike, and names a
flight boundary when it sees one:

* ``odom_jump``: the position moved farther between two odometry samples than the vehicle's speed explains,
  by more than ``jump_m`` (a simulator reset, a teleport, an EKF reset or a new odometry origin). Memories
  kept in the odom frame mean nothing across it.
* ``landed``: the vehicle came to rest (speed below ``rest_speed_mps`` for ``rest_s``) while the command
  flown asked it down at ``rest_descent_mps`` or more: it stands on a surface (a disarmed vehicle on the
  ground reads the same). A hover does not count: the command does not descend; a descent the floor guard
  holds does not either (the command flown climbs or holds).
* ``takeoff``: after a landing (or when the first odometry finds the vehicle at rest near the odom origin,
  as an autopilot starts on the ground), the vehicle rose ``takeoff_climb_m`` above where it rested.

``~/reset`` on policy_node (``reason`` 'service') and the env's ``reset`` (a new episode: reason 'episode')
are the explicit boundaries. ``/sim/goal`` is not one: the latent and end-to-end assistants never read it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

REASONS = ('odom_jump', 'landed', 'takeoff', 'service', 'episode')


@dataclass
class FlightConfig:
    """Thresholds of the flight boundaries (policy_node flight_* parameters)."""

    enabled: bool = True               # False: only the explicit boundaries (~/reset, a new env episode)
    jump_m: float = 1.0                # odometry moving this much farther than its speed explains: a jump (m)
    rest_speed_mps: float = 0.05       # slower than this (3-D norm of the twist) counts as at rest
    rest_s: float = 1.0                # ... for this long, while the command flown descends: landed
    rest_descent_mps: float = 0.1      # the command's descent that makes a rest a landing (m/s)
    takeoff_climb_m: float = 0.3       # rising this far above the resting altitude: a take-off (m)
    ground_altitude_m: float = 0.3     # the first odometry at rest below this altitude (odom z) starts landed

    def __post_init__(self) -> None:
        """Reject non-finite or non-positive thresholds (ValueError, one line)."""
        for name in ('jump_m', 'rest_speed_mps', 'rest_s', 'rest_descent_mps', 'takeoff_climb_m'):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f'FlightConfig.{name} must be a finite number > 0, got {v!r}')
        g = self.ground_altitude_m
        if not (isinstance(g, (int, float)) and math.isfinite(g)):
            raise ValueError(f'FlightConfig.ground_altitude_m must be a finite number, got {g!r}')


class FlightMonitor:
    """Watches odometry and the command flown; ``update`` returns the reason of a flight boundary, else None."""

    def __init__(self, cfg: FlightConfig | None = None):
        self.cfg = cfg or FlightConfig()
        self.reset()

    def reset(self) -> None:
        """Start watching afresh (after an explicit boundary)."""
        self._last: tuple[float, np.ndarray, float] | None = None   # (t, position, speed) of the last update
        self._rest_since: float | None = None
        self._landed_z: float | None = None          # resting altitude while landed; None: flying

    @property
    def landed(self) -> bool:
        """Whether the vehicle is on a surface (between a landing and the next take-off)."""
        return self._landed_z is not None

    def update(self, t: float, position: np.ndarray, velocity: np.ndarray, command_vz: float) -> str | None:
        """One control step: odometry (`position` odom, `velocity` any frame: only its norm is read) at time `t`
        and the vertical command flown in the previous step; the boundary seen, or None."""
        c = self.cfg
        p = np.asarray(position, dtype=float).reshape(3)
        speed = float(np.linalg.norm(np.asarray(velocity, dtype=float)))
        t = float(t)
        if not self.cfg.enabled:
            return None
        if not (np.all(np.isfinite(p)) and math.isfinite(speed) and math.isfinite(t)):
            return None
        last, self._last = self._last, (t, p, speed)
        if last is None:                           # the first odometry of a flight
            if speed < c.rest_speed_mps and p[2] < c.ground_altitude_m:
                self._landed_z = float(p[2])       # an autopilot starting on the ground
            return None
        t0, p0, s0 = last
        dt = max(t - t0, 0.0)
        if float(np.linalg.norm(p - p0)) > c.jump_m + max(speed, s0) * dt:
            self._rest_since, self._landed_z = None, None
            return 'odom_jump'
        if self._landed_z is not None:
            if p[2] > self._landed_z + c.takeoff_climb_m:
                self._landed_z, self._rest_since = None, None
                return 'takeoff'
            self._landed_z = min(self._landed_z, float(p[2]))
            return None
        if speed < c.rest_speed_mps and math.isfinite(command_vz) and command_vz <= -c.rest_descent_mps:
            if self._rest_since is None:
                self._rest_since = t
            if t - self._rest_since >= c.rest_s - 1e-9:
                self._landed_z, self._rest_since = float(p[2]), None
                return 'landed'
        else:
            self._rest_since = None
        return None
