"""Oscillation damper: a non-learned rule that damps a pilot-induced oscillation.

Why: a pilot who reacts late (choice reaction 0.35-0.6 s plus a video link's latency) and flies keys at a
fixed speed overshoots its aim, reverses, and overshoots again the other way: a pilot-induced oscillation
(PIO), the classic failure of a delayed human closing a fast loop. It circles its aim 0.5-1 m either side
and never stays inside its own "I am above it" radius long enough to descend: delay pilots (beta 1) can
swing +-0.9 m over the goal pad until the 60 s timeout with the learned actor inactive (|a| under the
blending threshold, so V = u), and unassisted they time out as often. The cure for a PIO is a lower loop
gain: while one is detected, the agent's horizontal action becomes a velocity damper, a_xy = -gain v_xy
(base_link, clipped to the actor's range), so the blended V_xy = (u_xy - gain v_xy) / 2 and a held key
moves the vehicle at about u / (2 + gain): each overshoot is that much shorter and the pilot settles over
its aim and descends.

Detection, from what the actor observes (the pilot's command) and odometry: a reversal is the pilot's
mean horizontal command over the last ``mean_s`` pointing against (negative dot product) its mean over
the same span ``gap_s`` earlier, both faster than ``speed_mps`` (held keys, not fine taps); it is counted
once, when that test turns true (it stays true for about ``gap_s`` after each reversal).
``min_reversals`` reversals within ``window_s`` is an oscillation, and it is damped only where it swings
across a pad: the vehicle's path between the last two reversals passes within ``cross_radius_m`` of a
mapped pad's centre (the pad recall's map) and the vehicle is still within ``near_m`` of it. Why the pad:
a damper's action points against the motion, and a pilot reads an assistant's push as a hint where the
goal is (the paper's conformance); key-confused pilots mid-transit (a spell of a flipped key and its end
are two reversals) would be slowed and talked back onto the pad behind them, a wrong-pad landing.
Swinging across a pad, the pilot is trying to settle over it. A pilot who leaves that pad is let go once
the vehicle has been getting farther from it for ``leave_s`` (an overshoot moves away for about a quarter
of a swing, ~1 s), because a keyboard pilot's late correction off the wrong pad, damped for longer (4 s),
reads the push as "go back" and lands there. The rule stays out while the pilot commands a descent (the
pad recall's touchdown centring and the actor handle the last metre) and when the damper action is under
the blending threshold (the vehicle nearly still: the assistant relinquishes, V = u).

Pure numpy; no rclpy.
"""
from __future__ import annotations

import math
from collections import deque
from typing import TYPE_CHECKING
from dataclasses import dataclass

import numpy as np

from assist_common.settings import check_named, setting
from .settings import node_param
from .stage import ACTION, Decision, Parts, Rule, Stage, StepContext

if TYPE_CHECKING:                     # the stage reads the recall's pad map
    from .recall import PadRecall


@dataclass
class DamperConfig:
    """Settings of the oscillation damper (policy_node parameters oscillation_damper_* map onto these)."""

    enabled: bool = node_param(True, 'oscillation_damper', 'Oscillation damper (assist_policy.damper, not learned): '
                               "while the pilot's held keys keep reversing (a pilot-induced oscillation), the "
                               "actor's horizontal action is replaced by a velocity damper, a_xy = -gain v_xy. "
                               'Default false in mode oracle.')
    # 1/s: a_xy = -gain v_xy while an oscillation is detected
    gain: float = node_param(2.0, 'oscillation_damper_gain', 'Gain of the oscillation damper (1/s): a_xy = -gain '
                             'v_xy.', min=0.0, max=10.0)
    speed_mps: float = setting(0.5, ge=0)  # mean horizontal pilot speed over mean_s that counts as a held key
    mean_s: float = setting(0.5, gt=0)  # span of each mean compared
    gap_s: float = setting(1.0, gt=0)  # the earlier mean is taken this long before the latest
    # reversals are counted over this window
    window_s: float = node_param(8.0, 'oscillation_damper_window_s', 'The oscillation damper counts reversals of '
                                 "the pilot's held keys over this window (s).", min=0.5, max=60.0)
    # this many reversals within window_s: an oscillation
    min_reversals: int = node_param(2, 'oscillation_damper_reversals', 'This many reversals within the window '
                                    'engage the oscillation damper.', min=1, max=20)
    # damped only if the last swing passed this close to a mapped pad's centre
    cross_radius_m: float = setting(0.5, ge=0)
    near_m: float = setting(1.5, ge=0)  # ... and the vehicle is still this close to that pad (horizontal m)
    leave_s: float = setting(1.5, ge=0)  # getting farther from that pad for this long: leaving it, let go
    leave_gain_m: float = setting(0.3, ge=0)  # ... by at least this much over leave_s
    # ... never nearer by more than this in one step (turbulence, not a turn)
    leave_jitter_m: float = setting(0.01, ge=0)

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line)."""
        check_named(self, type(self).__name__)


class OscillationDamper:
    """The reversal detector and the damping rule (see module docstring); ``reset`` at each new landing."""

    def __init__(self, cfg: DamperConfig | None = None):
        self.cfg = cfg or DamperConfig()
        self._u: deque[tuple[float, np.ndarray]] = deque()      # (t, u_xy) over the last gap_s + mean_s
        self._p: deque[tuple[float, np.ndarray]] = deque()      # (t, vehicle x, y) over the last leave_s
        self._reversals: deque[tuple[float, np.ndarray]] = deque()   # (t, vehicle x, y) of the reversals in window_s
        self._start: float | None = None                         # time of the first command of this landing
        self._reversing = False                                  # the reversal test held at the last command

    def reset(self) -> None:
        """Forget the pilot's commands and the reversals (new landing)."""
        self._u.clear()
        self._p.clear()
        self._reversals.clear()
        self._start = None
        self._reversing = False

    def _mean(self, t0: float, t1: float) -> np.ndarray | None:
        """Mean pilot u_xy over samples with t0 < t <= t1 (None: none)."""
        xs = [u for t, u in self._u if t0 < t <= t1]
        return np.mean(xs, axis=0) if xs else None

    def oscillating(self, t: float, u: np.ndarray, position: np.ndarray) -> bool:
        """Record the pilot's command `u` (base_link) at time `t` (s) and `position` (odom); whether it oscillates."""
        c = self.cfg
        u = np.asarray(u, dtype=float).reshape(3)
        p = np.asarray(position, dtype=float).reshape(3)
        if not (math.isfinite(t) and np.all(np.isfinite(u)) and np.all(np.isfinite(p))):
            return False
        if self._u and t < self._u[-1][0]:
            self.reset()                                # the clock went back: a new landing or a replay
        if self._start is None:
            self._start = t
        self._u.append((t, u[:2].copy()))
        while self._u and self._u[0][0] <= t - c.gap_s - c.mean_s:
            self._u.popleft()
        self._p.append((t, p[:2].copy()))
        while len(self._p) > 1 and self._p[1][0] <= t - c.leave_s:
            self._p.popleft()
        while self._reversals and self._reversals[0][0] < t - c.window_s:
            self._reversals.popleft()
        now, before = self._mean(t - c.mean_s, t), self._mean(t - c.gap_s - c.mean_s, t - c.gap_s)
        reversing = (now is not None and before is not None and t - self._start >= c.gap_s
                     and float(np.hypot(*now)) > c.speed_mps and float(np.hypot(*before)) > c.speed_mps
                     and float(now @ before) < 0.0)
        if reversing and not self._reversing:
            self._reversals.append((t, p[:2].copy()))
        self._reversing = reversing
        return len(self._reversals) >= c.min_reversals

    def across_pad(self, position: np.ndarray, pads: np.ndarray) -> bool:
        """Whether the swing between the last two reversals passed near a pad centre (`pads`, Nx2+ odom) that the
        vehicle is still near and has not been leaving for leave_s."""
        c = self.cfg
        pads = np.asarray(pads, dtype=float)
        if len(self._reversals) < 2 or pads.size == 0:
            return False
        pads = pads.reshape(len(pads), -1)[:, :2]
        a, b = self._reversals[-2][1], self._reversals[-1][1]
        ab = b - a
        s = np.clip(((pads - a) @ ab) / max(float(ab @ ab), 1e-9), 0.0, 1.0)
        seg = np.linalg.norm(pads - (a + s[:, None] * ab), axis=1)          # pad centre to the swing
        here = np.linalg.norm(pads - np.asarray(position, dtype=float).reshape(3)[:2], axis=1)
        return any(not self._leaving(pad) for pad in pads[(seg < c.cross_radius_m) & (here < c.near_m)])

    def _leaving(self, pad: np.ndarray) -> bool:
        """Whether the vehicle got farther from `pad` over leave_s (by leave_gain_m, no step leave_jitter_m nearer)."""
        c = self.cfg
        if not self._p or self._p[-1][0] - self._p[0][0] < c.leave_s - 1e-6:
            return False
        d = np.linalg.norm(np.array([xy for _, xy in self._p]) - pad, axis=1)
        return bool(d[-1] - d[0] > c.leave_gain_m and np.all(np.diff(d) > -c.leave_jitter_m))

    def apply(self, t: float, u: np.ndarray, agent: np.ndarray, velocity: np.ndarray, position: np.ndarray,
              pads: np.ndarray, max_speed: np.ndarray | tuple[float, float, float]) -> np.ndarray | None:
        """The agent action (m/s, base_link) with its horizontal part damping `velocity` (base_link), or None.

        Call every control step (it records the pilot's command and the vehicle's odom `position`); `pads`
        are the mapped pad centres (odom, Nx2 or Nx3). None when no oscillation across a pad is under way,
        the pilot commands a descent, or the rule is off.
        """
        if not self.cfg.enabled:
            return None
        u = np.asarray(u, dtype=float).reshape(3)
        if not self.oscillating(t, u, position) or u[2] < 0.0 or not self.across_pad(position, pads):
            return None
        v = np.asarray(velocity, dtype=float).reshape(3)
        if not np.all(np.isfinite(v)):
            return None
        a = np.asarray(agent, dtype=float).reshape(3).copy()
        ms = np.asarray(max_speed, dtype=float).reshape(3)
        a[:2] = np.clip(-self.cfg.gain * v[:2], -ms[:2], ms[:2])
        return a


# ----------------------------------------------------------------------------------------------- stage
class DamperStage(Stage):
    """1. The oscillation damper on the actor's horizontal action (reads the recall's pad map)."""

    key, phase, position = 'oscillation_damper', ACTION, 10

    def __init__(self, damper: OscillationDamper, recall: PadRecall):
        self.damper, self._recall = damper, recall

    def reset(self) -> None:
        """Forget the reversals and positions."""
        self.damper.reset()

    def apply(self, ctx: StepContext, d: Decision) -> Decision | None:
        """a_xy = -gain v_xy while the pilot oscillates across a mapped pad."""
        a = self.damper.apply(ctx.t, ctx.u, d.agent, ctx.velocity, ctx.position,
                              [m.xyz for m in self._recall.map.pads], ctx.max_speed)
        return None if a is None else Decision(a, None, self.key, 'oscillation damper: damping the pilot\'s '
                                                                  'oscillation')


def _make(cfg: DamperConfig, parts: Parts, threshold) -> tuple[dict, tuple[Stage, ...]]:
    """The damper and its stage (it reads the pad recall's map)."""
    damper = OscillationDamper(cfg)
    return {'damper': damper}, (DamperStage(damper, parts['recall']),)


RULE = Rule('damper', 'oscillation_damper', 'damper', DamperConfig, goal_agnostic=True, title='oscillation damper',
            make=_make)
