"""Scripted oracle assistant (knows the true goal): demonstrations to preload TD3's replay buffer.

The paper preloads the replay buffer with transitions collected by earlier models; here the
earliest "model" is this privileged controller. Its transitions are valid off-policy data for any
condition (the stored observation is whatever the env's condition observes), so it can seed both
oracle and latent training.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from assist_common.frames import nearest_xy

from .actions import DEFAULT_MAX_SPEED, unscale_action


# The teacher's yield threshold (m/s of mean horizontal pilot command over 1 s): above what the paper
# pilot's fine taps reach (duty <= 0.5 per axis near its aim: <= 0.71 m/s on a diagonal), below a held key
# (1 m/s).
YIELD_SPEED_MPS = 0.75
# Height over the pad (m) below which the `nearest_pad_commit` teacher pushes down again: under the
# late_correction pilots' noticing heights (0.4-1.5 m) for most of them, and above the last ~0.4 m of
# the descent (the vehicle's centre sits ~0.1 m over the pad top at touchdown).
COMMIT_HEIGHT_M = 0.5
# Lead (s) of the `_lead` teachers: they aim the vehicle's position this far ahead (position + lead x horizontal
# velocity). ArduCopter's GUIDED response lags (it brakes in ~0.65 m from 1 m/s), so a stiff teacher aimed at
# where the vehicle is overshoots and circles the pad; measured on the paper pilot (beta 0.5, 10 landings, seed
# 2024, floor guard): scripted oracle on the arducopter plant 8/10 -> 10/10 on the goal pad, 0.237 -> 0.121 m;
# on the ideal plant 10/10 both, 0.079 -> 0.062 m.
LEAD_S = 0.3


def holds_key(mean_pilot: np.ndarray, speed_mps: float) -> bool:
    """Whether the pilot's mean command over the window says a horizontal key is held (faster than `speed_mps`)."""
    m = np.asarray(mean_pilot, dtype=float)
    return float(np.hypot(m[0], m[1])) > speed_mps


@dataclass
class ScriptedConfig:
    """Gains of the scripted oracle assistant."""

    # 1/s: velocity toward the goal per metre of offset. The assistant gets half of V = (u + a)/2 and
    # |a| <= 1 m/s, so a stiff gain (a saturates beyond ~0.25 m) is what beats the pilot's drift and the
    # ground-effect turbulence in the last metre. Measured (5 betas x 24 landings, seed 2024): nearest-pad
    # assistant 0.175 m mean / 0.130 median at 0.75, 0.144 / 0.106 at 1.5, 0.118 / 0.082 at 2.5,
    # 0.097 / 0.068 at 4; oracle 0.090 +- 0.051 m at 4 (paper's oracle: 0.10 +- 0.07).
    gain_xy: float = 4.0
    engage_radius_m: float = 100.0    # helps everywhere by default
    descend_radius_m: float = 0.25    # pushes down when this close to the goal centre (horizontally)
    climb_height_m: float = 0.35      # pushes up when lower than this above the goal and not over it
    climb_radius_m: float = 0.4
    descend_mps: float = 1.0
    climb_mps: float = 0.5
    cancel_pilot: float = 1.0         # fraction of the pilot's horizontal command cancelled
    # Yield to a deliberate correction (0 = never, the reference script): when the pilot's mean
    # horizontal command over the last second exceeds this (a held key, not fine taps: the paper pilot
    # taps at duty <= 0.5 near its aim) while it is not descending, the nearest-pad assistant relinquishes
    # instead of cancelling the pilot on the pad below: a pilot who set off for a neighbour pad and
    # noticed late can leave it. Uses only what the actor observes (u and its 1 s mean).
    yield_speed_mps: float = 0.0
    # Do not hurry a descent the pilot is already making : while the pilot commands descent the
    # nearest-pad assistant adds none of its own (a_z = 0, so V_z = u_z / 2 while it centres) instead of
    # pushing down at descend_mps. It still descends for a pilot who hovers low over the pad. The pilot
    # gets twice the time to see that the pad below is the wrong one and leave it, and under the paper's
    # conformance update its goal estimate is not dragged down with the vehicle (a push down drags it, which
    # keeps the late_correction pilots from ever noticing).
    # Measured: docs/experiments/2026-11-descent-sparing-teachers.md.
    gentle_descent: bool = False
    # With gentle_descent: below this height over the pad (m) the assistant pushes down again as the
    # reference does, so the last part of the descent is committed and quick. Meant to shorten the slow
    # final descent, in which the gentle teacher's learned imitators land less precisely than the
    # reference's (whether that is the cause is not settled: docs/experiments/2026-11-descent-sparing-teachers.md,
    # DAgger with the descent-sparing teachers). 0 = gentle all the way down.
    commit_height_m: float = 0.0
    # Aim where the vehicle will be `lead_s` seconds from now (position + lead_s x horizontal velocity), not where it
    # is: damps the overshoot a lagging autopilot adds (LEAD_S). 0 = aim at the current position.
    lead_s: float = 0.0
    # Privileged (knows the goal; a teacher for actors that infer it, never a reference of what is perceivable):
    # the nearest-pad assistant relinquishes over any pad but the pilot's goal. Imitated from what the actor sees,
    # its action is the helping one scaled by how sure the actor can be that the pad below is the goal.
    goal_gated: bool = False


class ScriptedOracle:
    """a = 2 gain (G - p)_xy - u_xy (clipped), descend over the goal, climb when low and off it."""

    def __init__(self, cfg: ScriptedConfig | None = None, max_speed=DEFAULT_MAX_SPEED):
        self.cfg = cfg or ScriptedConfig()
        self.max_speed = max_speed

    def velocity(self, goal: np.ndarray, position: np.ndarray, pilot: np.ndarray | None = None,
                 velocity: np.ndarray | None = None) -> np.ndarray:
        """Assistant velocity (m/s) at `position` (moving at `velocity`, for `lead_s`) for true goal `goal`,
        cancelling the pilot's `pilot` command."""
        c = self.cfg
        p = np.asarray(position, dtype=float)
        if c.lead_s > 0.0 and velocity is not None:
            v = np.asarray(velocity, dtype=float)
            p = p + c.lead_s * np.array([v[0], v[1], 0.0])
        d = np.asarray(goal, dtype=float) - p
        horiz = float(np.hypot(d[0], d[1]))
        a = np.zeros(3)
        if horiz > c.engage_radius_m:
            return a
        u = np.zeros(3) if pilot is None else np.asarray(pilot, dtype=float)
        # V = (u + a) / 2: with a = 2 * gain * d - u the vehicle flies gain * d whatever the pilot does
        a[:2] = 2.0 * c.gain_xy * d[:2] - c.cancel_pilot * u[:2]
        if horiz < c.descend_radius_m:
            a[2] = -c.descend_mps
        elif -d[2] < c.climb_height_m and horiz > c.climb_radius_m:
            a[2] = c.climb_mps
        return np.clip(a, -np.asarray(self.max_speed), np.asarray(self.max_speed))

    def raw_action(self, env) -> np.ndarray:
        """Raw action in [-1, 1]^3 for the env's current state (uses the true goal)."""
        st = env.world.state
        return unscale_action(self.velocity(env.world.goal_position, st.position, env.pilot_action, st.velocity),
                              self.max_speed)


# Named nearest-pad teachers (goal-agnostic but for the goal-gated one; `nearest_pad` is the reference script).
NEAREST_PAD_VARIANTS = {
    'nearest_pad': {},                                                # centre and push down
    'nearest_pad_yield': {'yield_speed_mps': YIELD_SPEED_MPS},        # + let a held-key correction through
    'nearest_pad_gentle': {'gentle_descent': True},                   # + add no descent to the pilot's
    'nearest_pad_commit': {'gentle_descent': True, 'commit_height_m': COMMIT_HEIGHT_M},  # gentle, then commit
    # the commit teacher that also lets a held-key correction through (it costs reaction-delayed
    # pilots, whose delayed overshoot is a held key too: docs/experiments/2026-11-memory-displacement.md)
    'nearest_pad_commit_yield': {'gentle_descent': True, 'commit_height_m': COMMIT_HEIGHT_M,
                                 'yield_speed_mps': YIELD_SPEED_MPS},
    # the commit teacher aiming ahead of a lagging autopilot (LEAD_S)
    'nearest_pad_commit_lead': {'gentle_descent': True, 'commit_height_m': COMMIT_HEIGHT_M, 'lead_s': LEAD_S},
    # privileged: the commit teacher over the goal pad only (a teacher for an actor that infers the goal)
    'nearest_pad_goal_commit': {'gentle_descent': True, 'commit_height_m': COMMIT_HEIGHT_M, 'goal_gated': True},
}


def make_nearest_pad(variant: str = 'nearest_pad', max_speed=DEFAULT_MAX_SPEED) -> ScriptedNearestPad:
    """The named nearest-pad teacher (NEAREST_PAD_VARIANTS); ValueError for an unknown name."""
    if variant not in NEAREST_PAD_VARIANTS:
        raise ValueError(f'unknown nearest-pad variant {variant!r}; one of {", ".join(NEAREST_PAD_VARIANTS)}')
    return ScriptedNearestPad(ScriptedConfig(**NEAREST_PAD_VARIANTS[variant]), max_speed=max_speed)


class ScriptedNearestPad:
    """Goal-agnostic demonstrator: once the pilot descends (or is low), centre it on the pad below.

    Uses only what the latent condition can perceive (the closest pad's position, the pilot's
    command), so a latent actor can imitate it; relinquishes (a = 0) while the pilot is in transit.
    """

    def __init__(self, cfg: ScriptedConfig | None = None, max_speed=DEFAULT_MAX_SPEED, low_height_m: float = 1.2):
        self.cfg = cfg or ScriptedConfig()
        self.max_speed = max_speed
        self.low_height_m = low_height_m
        self.oracle = ScriptedOracle(self.cfg, max_speed)

    def yields(self, pilot: np.ndarray, mean_pilot: np.ndarray | None) -> bool:
        """Whether the pilot is making a deliberate correction the assistant should let through."""
        c = self.cfg
        if c.yield_speed_mps <= 0 or mean_pilot is None:
            return False
        return float(np.asarray(pilot, dtype=float)[2]) >= 0.0 and holds_key(mean_pilot, c.yield_speed_mps)

    def velocity(self, pads: np.ndarray, position: np.ndarray, pilot: np.ndarray,
                 mean_pilot: np.ndarray | None = None, velocity: np.ndarray | None = None,
                 goal: np.ndarray | None = None) -> np.ndarray:
        """Assistant velocity toward the pad nearest to the vehicle, or zero in transit (or when yielding, or,
        goal-gated, over a pad that is not the one nearest `goal`)."""
        if self.yields(pilot, mean_pilot):
            return np.zeros(3)
        p = np.asarray(position, dtype=float)
        pads = np.asarray(pads, dtype=float)
        k = nearest_xy(pads, p)
        if self.cfg.goal_gated:
            if goal is None:
                raise ValueError('a goal-gated teacher needs the goal')
            if k != nearest_xy(pads, goal):
                return np.zeros(3)
        height = p[2] - pads[k, 2]          # over the pad below
        descending = float(np.asarray(pilot, dtype=float)[2]) < 0
        if not (descending or height < self.low_height_m):
            return np.zeros(3)
        a = self.oracle.velocity(pads[k], p, pilot, velocity)
        committed = height < self.cfg.commit_height_m
        if self.cfg.gentle_descent and descending and a[2] < 0 and not committed:
            a[2] = 0.0
        return a

    def raw_action(self, env) -> np.ndarray:
        """Raw action in [-1, 1]^3 for the env's current state (pad positions; the goal only when goal-gated)."""
        mean_u = None
        if self.cfg.yield_speed_mps > 0:
            mean_u, _ = env.builder.history.means(env.elapsed_s)
        st = env.world.state
        goal = env.world.goal_position if self.cfg.goal_gated else None
        return unscale_action(self.velocity(env.world.pad_top_centers, st.position, env.pilot_action, mean_u,
                                            st.velocity, goal), self.max_speed)
