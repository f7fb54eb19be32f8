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
so its fine corrections never engage the rule; a held key (1 m/s) does within ~0.75 s. Pilots with a
reaction delay overshoot with a held key too; the rule then lets that overshoot through as well (the cost
is measured in the assist_policy README, issue 12 pilot override). It uses only what the actor observes
(u and its window mean) and odometry altitude. Pure numpy; no rclpy.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

# mean horizontal pilot command (m/s over the window) above which a key is held: above the paper pilot's
# fine taps (<= 0.71 m/s on a diagonal), below a held key (1 m/s)
OVERRIDE_SPEED_MPS = 0.75


@dataclass
class OverrideConfig:
    """Settings of the pilot override (policy_node parameters pilot_override_* map onto these)."""

    enabled: bool = True
    speed_mps: float = OVERRIDE_SPEED_MPS   # window-mean horizontal pilot speed that counts as a held key
    climb_mps: float = 0.3          # vertical V while yielding low (the pilot's own climb if faster)
    climb_below_m: float = 2.0      # altitude over the floor below which the yield adds the climb (pads <= 1.2 m)

    def __post_init__(self) -> None:
        """Reject settings that would make the rule engage on no input or descend (ValueError, one line)."""
        for name in ('speed_mps', 'climb_mps', 'climb_below_m'):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f'OverrideConfig.{name} must be a finite number >= 0, got {v!r}')


def override_action(cfg: OverrideConfig, u: np.ndarray, mean_u: np.ndarray, altitude_m: float,
                    max_speed: np.ndarray | tuple[float, float, float]) -> np.ndarray | None:
    """The agent action (m/s) that replaces the actor's while the pilot overrides, or None (rule not engaged)."""
    if not cfg.enabled:
        return None
    u = np.asarray(u, dtype=float).reshape(3)
    m = np.asarray(mean_u, dtype=float).reshape(3)
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(m)) and math.isfinite(float(altitude_m))):
        return None                   # nothing to judge by: the actor's action stands (the guard still acts)
    if u[2] < 0.0 or float(np.hypot(m[0], m[1])) <= cfg.speed_mps:
        return None
    if float(altitude_m) >= cfg.climb_below_m:
        return np.zeros(3)
    a = np.array([u[0], u[1], 2.0 * max(float(u[2]), cfg.climb_mps) - u[2]])
    ms = np.asarray(max_speed, dtype=float).reshape(3)
    return np.clip(a, -ms, ms)
