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

from .settings import node_param

REASONS = ('odom_jump', 'landed', 'takeoff', 'service', 'episode')


@dataclass
class FlightConfig:
    """Thresholds of the flight boundaries (policy_node flight_* parameters)."""

    # False: only the explicit boundaries (~/reset, a new env episode)
    enabled: bool = node_param(True, 'flight_boundaries', 'Forget the flight (action history, pad and wall maps, '
                               'landing spots, override and damper state) at an odometry jump, a landing and a '
                               'take-off (assist_policy.flight); false: only at ~/reset.')
    # odometry moving this much farther than its speed explains: a jump (m)
    jump_m: float = node_param(1.0, 'flight_jump_m', 'Odometry moving this much farther between two samples than '
                               'its speed explains is a jump (reset, teleport, EKF reset): a new flight (m).',
                               min=0.0, max=100.0, min_exclusive=True)
    # slower than this (3-D norm of the twist) counts as at rest
    rest_speed_mps: float = node_param(0.05, 'flight_rest_speed_mps', 'Slower than this (odometry twist norm, m/s) '
                                       'counts as at rest.', min=0.0, max=1.0, min_exclusive=True)
    # ... for this long, while the command flown descends: landed
    rest_s: float = node_param(1.0, 'flight_rest_s', 'At rest this long while /cmd_vel descends at '
                               'flight_rest_descent_mps or more: landed, the flight ends (s).',
                               min=0.0, max=60.0, min_exclusive=True)
    # the command's descent that makes a rest a landing (m/s)
    rest_descent_mps: float = node_param(0.1, 'flight_rest_descent_mps', 'Descent of the command flown that makes a '
                                         'rest a landing (m/s).', min=0.0, max=5.0, min_exclusive=True)
    # rising this far above the resting altitude: a take-off (m)
    takeoff_climb_m: float = node_param(0.3, 'flight_takeoff_climb_m', 'After a landing, rising this far above it '
                                        'is a take-off: a new flight (m).', min=0.0, max=10.0, min_exclusive=True)
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
