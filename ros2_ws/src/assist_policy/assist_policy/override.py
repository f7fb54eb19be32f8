"""Pilot override: a non-learned arbitration rule that lets a deliberate correction through (issue 12).

Rule: while the pilot holds a horizontal key (its mean horizontal command over the observation window,
1 s, is faster than ``speed_mps``) and does not command a descent, the assistant's action is replaced:
below ``climb_below_m`` of altitude over the floor by a' = (u_x, u_y, 2 max(u_z, climb) - u_z), so that
the blended V = (u + a') / 2 = (u_x, u_y, max(u_z, climb_mps)): the pilot's correction passes at full
speed and the vehicle rises gently; higher up by a' = 0 (relinquish, V = u). a' is clipped to the
actor's max_speed as any action is.

Why: a pilot who set off for a neighbour pad and sees the mistake low over it (late_correction, and the
independent pilot of issue 12: "sudden late corrections") holds a key toward the right pad. The
nearest-pad behaviour the learned assistant imitates cancels that command over the pad below and pushes
down, so the pilot lands on the wrong pad, or, once the correction wins, the vehicle slides off the pad
still descending and catches its edge (tipped over). The climb is what makes letting go safe: a
multirotor accelerating sideways at 1-1.5 m/s keeps sinking for a while, and low over a pad up to 1.2 m
tall its legs then hit the pad's edge.

Threshold: the paper pilot taps keys near its aim (duty <= 0.5 per axis: <= 0.71 m/s mean on a diagonal),
so its fine corrections never engage the rule; a held key (1 m/s) does within ~0.75 s.

Reversals: a pilot with a reaction delay overshoots its aim with a held key and comes back with another,
held the opposite way; passing those through keeps it oscillating around the pad until time runs out
(measured: delay pilots 74.5 -> 61.8 % success). So a held key that reverses one held within the last
``reversal_s`` seconds (negative dot product of the window means) is an overshoot being corrected, not a
departure, and the actor keeps helping. A pilot leaving the wrong pad has descended over it for seconds
first, so its held key reverses nothing.

It uses only what the actor observes (u and its window mean), odometry altitude and time. Pure numpy;
no rclpy.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from .scripted import YIELD_SPEED_MPS, holds_key


@dataclass
class OverrideConfig:
    """Settings of the pilot override (policy_node parameters pilot_override_* map onto these)."""

    enabled: bool = True
    # window-mean horizontal pilot speed that counts as a held key: the yielding teacher's test and threshold
    # (scripted.holds_key, YIELD_SPEED_MPS: above the paper pilot's fine taps, below a held key)
    speed_mps: float = YIELD_SPEED_MPS
    climb_mps: float = 0.3          # vertical V while yielding low (the pilot's own climb if faster)
    climb_below_m: float = 2.0      # altitude over the floor below which the yield adds the climb (pads <= 1.2 m)
    reversal_s: float = 3.0         # a held key reversing one held within this many seconds does not engage it

    def __post_init__(self) -> None:
        """Reject settings that would make the rule engage on no input or descend (ValueError, one line)."""
        for name in ('speed_mps', 'climb_mps', 'climb_below_m', 'reversal_s'):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f'OverrideConfig.{name} must be a finite number >= 0, got {v!r}')


def yield_action(cfg: OverrideConfig, u: np.ndarray, altitude_m: float,
                 max_speed: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """The agent action (m/s) while yielding: V = (u_xy, max(u_z, climb)) when low, V = u (a = 0) higher up."""
    if float(altitude_m) >= cfg.climb_below_m:
        return np.zeros(3)
    a = np.array([u[0], u[1], 2.0 * max(float(u[2]), cfg.climb_mps) - u[2]])
    ms = np.asarray(max_speed, dtype=float).reshape(3)
    return np.clip(a, -ms, ms)


class PilotOverride:
    """The rule with its memory of recent held keys (for reversals); ``reset`` at each new landing."""

    def __init__(self, cfg: OverrideConfig | None = None):
        self.cfg = cfg or OverrideConfig()
        self._held: deque[tuple[float, float, float]] = deque()    # (time, window-mean x, y) of recent held keys

    def reset(self) -> None:
        """Forget the held keys seen (new landing)."""
        self._held.clear()

    def apply(self, now: float, u: np.ndarray, mean_u: np.ndarray, altitude_m: float,
              max_speed: np.ndarray | tuple[float, float, float]) -> np.ndarray | None:
        """The agent action (m/s) replacing the actor's at time `now`, or None (the rule does not act)."""
        c = self.cfg
        u = np.asarray(u, dtype=float).reshape(3)
        m = np.asarray(mean_u, dtype=float).reshape(3)
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(m)) and math.isfinite(float(altitude_m))
                and math.isfinite(float(now))):
            return None               # nothing to judge by: the actor's action stands (the guard still acts)
        if self._held and self._held[-1][0] > now:
            self._held.clear()        # the clock went back (a new run, a replayed bag): old keys do not count
        while self._held and self._held[0][0] < now - c.reversal_s:
            self._held.popleft()
        if not holds_key(m, c.speed_mps):
            return None
        mx, my = float(m[0]), float(m[1])
        reverses = any(mx * hx + my * hy < 0.0 for _, hx, hy in self._held)
        self._held.append((float(now), mx, my))
        if not c.enabled or reverses or u[2] < 0.0:
            return None
        return yield_action(c, u, altitude_m, max_speed)
