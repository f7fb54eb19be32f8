"""Touchdown envelope: the last decimetres of a descent end in a landing the autopilot detects.

ArduCopter declares a landing only after about a second of descent demand with no large lean request
and a quiet airframe; a vehicle that touches a pad while the pilot or the assistant still asks for
sideways speed slides on the pad top and keeps flying. The envelope acts on the downward range (base_link
to the surface below, as a downward rangefinder reads it) in two bands:

* **final descent** (range below `engage_range_m` while the command descends, until it stops descending, climbs
  faster than `abort_climb_mps` or the range grows past `release_range_m`): the descent becomes a steady
  `descent_mps`, and the sideways command is kept but limited to `lateral_max_mps`, so the pilot or the
  assistant can still centre the vehicle (a vehicle that comes over a pad's edge low is not pinned there)
  while little sideways speed is left at contact;
* **touchdown** (range at or below `commit_range_m`: the legs are down or a few centimetres off, the command
  not climbing): no sideways part, the steady descent, and, given the time, the touchdown is committed:
  for `commit_s` the descent holds whatever is commanded (a climb included), long enough for ArduCopter to
  declare the landing (~1.65 s after contact on SITL), so a pilot's hop after the legs touched does not
  undo a landing that has happened.

An unknown range (none, stale, out of the sensor's limits) passes the command through. The bridge applies
the envelope to every setpoint it sends to ArduPilot; the simulator's ArduCopter plant applies the same
class, so both plants end a landing the same way.

Pure Python; frames: any frame whose z axis is vertical (ENU world or a yaw-only body frame).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .settings import setting


@dataclass
class TouchdownConfig:
    """When the envelope takes over a descent and how it finishes it."""

    enabled: bool = setting(True)
    engage_range_m: float = setting(0.40, gt=0.0, le=5.0)     # range below which a descent becomes the final one
    release_range_m: float = setting(0.60, gt=0.0, le=10.0)   # range above which it lets go again
    descent_mps: float = setting(0.5, gt=0.0, le=2.0)         # final descent (ArduCopter LAND_SPEED-like)
    engage_descent_mps: float = setting(0.15, ge=0.0, le=2.0)  # a command descending faster than this engages it
    abort_climb_mps: float = setting(0.3, gt=0.0, le=5.0)     # a command climbing faster than this lets go
    lateral_max_mps: float = setting(0.3, ge=0.0, le=5.0)     # sideways speed left to the command in the final descent
    commit_range_m: float = setting(0.16, gt=0.0, le=2.0)     # at or below this range the legs are down (0.12 landed)
    commit_s: float = setting(3.0, ge=0.0, le=30.0)           # a committed touchdown holds this long; 0: never commits

    def check_relations(self) -> None:
        """The ranges are ordered: commit < engage < release."""
        if self.release_range_m <= self.engage_range_m:
            raise ValueError(f'release_range_m ({self.release_range_m}) must exceed engage_range_m '
                             f'({self.engage_range_m})')
        if self.commit_range_m >= self.engage_range_m:
            raise ValueError(f'commit_range_m ({self.commit_range_m}) must be below engage_range_m '
                             f'({self.engage_range_m})')


class TouchdownEnvelope:
    """Stateful filter on velocity setpoints (module docstring); `engaged` says whether it holds the descent."""

    def __init__(self, cfg: TouchdownConfig | None = None):
        self.cfg = cfg or TouchdownConfig()
        self.cfg.check_relations()
        self.engaged = False
        self.engagements = 0            # times it took over a descent
        self.commits = 0                # touchdowns it committed
        self._committed_until: float | None = None

    def reset(self) -> None:
        """Forget the current descent (a new flight)."""
        self.engaged = False
        self._committed_until = None

    @property
    def committed(self) -> bool:
        """A touchdown is being held (until `commit_s` after the legs came down)."""
        return self._committed_until is not None

    def apply(self, command, range_m: float | None, now: float | None = None) -> np.ndarray:
        """The setpoint to send for `command` (vx, vy, vz) at downward range `range_m` (None/NaN: unknown) at
        time `now` (s, any monotonic clock; None: no touchdown is committed)."""
        cmd = np.asarray(command, dtype=float).reshape(3)
        c = self.cfg
        if not c.enabled:
            return cmd
        descent = np.array([0.0, 0.0, -c.descent_mps])
        if self._committed_until is not None:
            if now is not None and now < self._committed_until:
                return descent
            self._committed_until = None
        known = range_m is not None and math.isfinite(range_m)
        if not known or cmd[2] > c.abort_climb_mps:
            self.engaged = False
            return cmd
        if range_m <= c.commit_range_m:                      # the legs are down: finish the landing
            if not self.engaged:
                self.engaged = True
                self.engagements += 1
            if now is not None and c.commit_s > 0.0:
                self._committed_until = now + c.commit_s
                self.commits += 1
            return descent
        if self.engaged and (range_m > c.release_range_m or cmd[2] >= -c.engage_descent_mps):
            self.engaged = False          # up and away, or the command stopped descending (e.g. a floor guard)
        elif not self.engaged and range_m < c.engage_range_m and cmd[2] < -c.engage_descent_mps:
            self.engaged = True
            self.engagements += 1
        if not self.engaged:
            return cmd
        out = descent.copy()
        speed = math.hypot(cmd[0], cmd[1])
        scale = min(1.0, c.lateral_max_mps / speed) if speed > 0.0 else 0.0
        out[:2] = cmd[:2] * scale
        return out
