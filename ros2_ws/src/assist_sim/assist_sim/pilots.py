"""A population of simulated pilots: the paper's model plus behavioural families seen in human pilots.

``assist_sim.pilot.SimulatedPilot`` (the paper's goal-estimate model, ``paper`` here) stays the
reference. Each family below changes one documented aspect of how a person flies a keyboard drone;
its parameters are drawn per episode (every ``reset``) from the ranges in its config dataclass, from a
generator spawned off the pilot's own (``Generator.spawn``: the paper model's random stream is left
untouched, so a family and the paper pilot with the same seed differ only by the family's behaviour;
every run is deterministic per seed). Keyboard pilots command discrete speeds: every family's
horizontal command per axis is 0 or +-key speed, the vertical one 0, +up or -down speed (all but
``glide``, an analog stick).

Families (``FAMILIES``; the reasoning is in each class's docstring):

=================  ===========================================================================
``paper``          the paper's pilot (reference; ``SimulatedPilot`` semantics, bit-identical)
``delay``          reaction delay: the whole command comes 0.25-0.8 s late
``bang_bang``      holds keys at a higher speed and releases them late -> overshoot, reversals;
                   commits to a descent it started while passing over the target
``tapper``         hesitation and key-tapping: short taps near the aim, freezes (more often near it)
``late_correction`` discrete wrong-pad choice (a neighbour pad, exactly), no gradual correction, then
                   a sudden late switch to the true goal (low over the wrong pad, or after a while)
``change_mind``    the goal itself changes: flies to its goal as the paper pilot, then chooses another pad
                   (low over its aim, or after a while); the landing is judged on the final goal
``depth_bias``     persistent misjudgement of its own position along the viewing depth (x), which
                   skill never removes
``key_confusion``  spells of swapped axes or a flipped sign (control-display mapping errors)
``ignorer``        alpha ~ U(0, 0.1): barely follows the assistant (fights it back to its own aim)
``follower``       alpha ~ U(0.9, 1): follows the assistant almost completely
``keyboard``       composite: delay + bang-bang + tapping + late correction + depth bias
``glide``          analog stick, proportional and trembling, descends along a glide path toward its
                   aim (over the nearer pads), straight down over it
``low_flyer``      gets low first, cruises just over the pad tops, descends over its aim
``cautious``       climbs to look, flies beside the row of pads (some landings), descends in stages
                   with a hover to check after each
=================  ===========================================================================

Split (``TRAIN_FAMILIES`` / ``HELDOUT_FAMILIES``): training may use ``paper``, ``delay``, ``tapper``,
``depth_bias`` and ``follower``; ``bang_bang``, ``late_correction``, ``key_confusion``, ``ignorer``,
``keyboard``, ``glide``, ``low_flyer``, ``cautious`` and ``change_mind`` are for evaluation only (``cautious`` and
``change_mind``, ``UNTUNED_FAMILIES``, are held out from tuning as well: no non-learned rule was tuned against
them). ``change_mind`` (``GOAL_CHANGING_FAMILIES``) changes the goal the landing is judged on: the env applies its
``new_goal_index``; the graph cannot (no topic of the contract carries it), so sim_pilot_node refuses it.
Population names (``POPULATIONS``): ``mix`` = one of the first five held-out families (``MIX_FAMILIES``)
drawn uniformly per episode (the held-out evaluation docs/results.md reports), ``approach_mix`` =
``glide`` or ``low_flyer`` (``APPROACH_FAMILIES``: pilots that descend before they are over their aim,
which breaks an assistant that learned from keyboard families that a descent starts over the aim; kept
out of ``mix`` so that ``mix`` results stay comparable), ``train_mix`` = one training family drawn per
episode (domain randomisation for training).

``make_pilot(name, alpha, beta, cfg, rng, pads)`` builds a pilot by name; ``pads`` (the pad top
centres, known to the env and to sim_pilot_node from /sim/scene) lets ``late_correction`` pick a real
neighbour pad; without it the neighbour is taken one mean pad spacing away along x.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .cues import Cue, CueConfig, CueReader
from .pilot import PilotConfig, SimulatedPilot

Range = tuple[float, float]


def _draw(rng: np.random.Generator, r: Range) -> float:
    """Uniform draw from a documented (lo, hi) range."""
    return float(rng.uniform(r[0], r[1]))


# --------------------------------------------------------------------------- family configs
@dataclass
class DelayConfig:
    """Reaction delay range (s)."""

    # Simple visual reaction time is ~0.2-0.25 s, choice reaction time 0.35-0.6 s (Hick-Hyman), and a
    # remote pilot watching a video feed adds display/link latency (0.05-0.3 s): 0.25-0.8 s in all.
    delay_s: Range = (0.25, 0.8)


@dataclass
class BangBangConfig:
    """Bang-bang keyboard pilot: faster keys, late release, committed descent."""

    # Keys held at a higher speed than the paper pilot's 1 m/s (impatient pilots; teleop keys are often
    # set fast), released only some time after the target is passed (motor + perceptual lag of seeing
    # that it has passed: overshoot ~ speed x release delay), each reversal shortens the delay (the pilot
    # learns within the episode). It starts descending when it passes within descend_radius of its aim
    # and keeps descending until it is farther than commit_radius (humans commit to a started action).
    speed_xy_mps: Range = (1.0, 1.5)
    release_delay_s: Range = (0.3, 0.9)
    learn_factor: Range = (0.4, 0.7)     # release delay multiplied by this after each reversal
    commit_radius_m: Range = (0.8, 1.6)


@dataclass
class TapperConfig:
    """Hesitant key-tapping pilot."""

    # Novice keyboard users tap keys rather than hold them when fine-positioning (short press, visual
    # check, next press), and freeze when unsure (hesitation), more so close to the landing decision.
    tap_radius_m: Range = (1.0, 2.5)    # taps within this distance of the aim, holds keys farther out
    tap_s: Range = (0.1, 0.25)          # key-down time of one tap
    gap_s: Range = (0.15, 0.6)          # key-up time between taps
    pause_rate_hz: Range = (0.05, 0.2)  # freezes per second far from the aim
    near_factor: float = 3.0            # freeze rate multiplier within near_radius_m of the aim
    near_radius_m: float = 1.0
    pause_s: Range = (0.5, 2.0)         # freeze length


@dataclass
class LateCorrectionConfig:
    """Wrong-pad choice, then a sudden late correction."""

    # Pads look alike from the start point; a pilot picks the wrong (neighbouring) one outright, flies
    # to it with confidence (no gradual correction), and notices only when low over it (the pad's
    # markings become legible) or after a while, then switches its aim to the true goal at once.
    lateral_sigma_m: float = 0.1
    notice_height_m: Range = (0.4, 1.5)   # height over the wrong pad's top at which it notices
    notice_time_s: Range = (10.0, 30.0)   # ...or after this long, whichever comes first
    fallback_gap_m: float = 4.0           # neighbour distance along x when the pads are unknown


@dataclass
class ChangeOfMindConfig:
    """The goal itself changes: the pilot decides on another pad mid-approach."""

    # A person told "land on that one" changes their mind, or is told another pad, while already low over the
    # first one (the hard case for an assistant that has just helped them there) or earlier in the approach. The
    # new goal is a neighbour pad (the nearest other pad, side drawn) or any other pad; the pilot sees where it is
    # with the paper pilot's wrong-in-depth first estimate. The landing is judged on the final goal.
    switch_height_m: Range = (0.5, 1.5)   # height over its aim's top at which it changes its mind ...
    switch_radius_m: float = 1.0          # ... within this of its aim horizontally
    switch_time_s: Range = (8.0, 25.0)    # ...or after this long, whichever comes first
    neighbour_share: float = 0.7          # chance the new goal is a neighbour pad (else any other pad)


@dataclass
class DepthBiasConfig:
    """Persistent depth misjudgement."""

    # Egocentric distances in rendered and remote views are misjudged systematically (typically
    # compressed by 10-30 %), and the error is consistent within a person and session: a constant
    # offset in where the pilot thinks the drone is along the viewing depth (x, the row of pads),
    # which skill (beta) does not remove because the pilot does not know it has it.
    bias_m: Range = (0.25, 0.6)          # magnitude; sign drawn 50/50


@dataclass
class KeyConfusionConfig:
    """Spells of wrong key mapping."""

    # Control-display mapping errors: the view and the body frame differ, W/S vs arrow keys are mixed
    # up, or left/right is reversed after the pilot's mental frame rotates; the pilot sees the drone go
    # the wrong way and fixes the mapping after a reaction + re-orientation time.
    rate_hz: Range = (0.03, 0.1)         # spell onsets per second
    start_probability: float = 0.3       # chance to start the episode confused
    duration_s: Range = (1.0, 3.0)
    kinds: tuple[str, ...] = ('swap_xy', 'flip_x', 'flip_y', 'flip_z')


@dataclass
class AlphaConfig:
    """Conformance extremes."""

    ignorer_alpha: Range = (0.0, 0.1)
    follower_alpha: Range = (0.9, 1.0)


@dataclass
class GlideConfig:
    """Analog-stick pilot that descends along a glide path."""

    # Many people fly a multirotor with an analog stick (gamepad, RC transmitter) and land it the way they
    # would approach with any vehicle: moving toward the aim and descending at once, the lower the nearer,
    # then straight down once over it. The stick is deflected in proportion to the offset they see
    # (saturating), with a small hand tremor, and reacts after a short delay. This breaks the assumption
    # every keyboard family shares (a descent starts only over the aim): the glide passes over the nearer
    # pads while descending.
    gain_per_s: Range = (0.6, 1.5)      # horizontal command per metre of offset (1/s)
    max_speed_mps: Range = (0.7, 1.2)   # stick saturation
    slope: Range = (0.3, 0.9)           # glide path: metres of height over the aim per metre of offset
    final_radius_m: Range = (0.15, 0.35)   # straight down inside this offset
    tremor_mps: Range = (0.03, 0.2)     # hand tremor (Ornstein-Uhlenbeck, tremor_tau_s correlation)
    tremor_tau_s: float = 0.3
    delay_s: Range = (0.1, 0.4)         # reaction delay (visual reaction + video latency)
    path_gain_per_s: float = 1.0        # vertical command per metre off the glide path (1/s)
    path_offset_m: float = 0.3          # glide path height over the aim at final_radius_m
    final_descent_mps: float = 0.4


@dataclass
class LowFlyerConfig:
    """Keyboard pilot that gets low first, then flies over the pads."""

    # Novices descend early to see the pads better and to feel in control, then fly the rest of the way
    # low over the pads at a constant height (a little over the tallest pad top they see) and descend the
    # last bit over their aim as the paper pilot does. Low, the camera sees one pad at a time.
    cruise_over_top_m: Range = (0.3, 0.9)   # cruise height over the tallest pad top
    band_m: float = 0.1                     # dead band around the cruise height
    fallback_top_m: float = 1.2             # tallest pad top when the pads are unknown


@dataclass
class CautiousConfig:
    """Keyboard pilot that climbs to look, approaches beside the row of pads and descends in stages."""

    # A careful novice first climbs to see more of the ground, then (on some landings) flies beside the row
    # of pads rather than over them, keeping the aim in view at an angle and away from the other pads,
    # and slides in sideways once level with it; over the aim it descends in stages, stopping after each
    # to check its alignment (hover, horizontal corrections only) before going on. Flight-training advice
    # for novices reads this way ("gain height to get a picture", "stop, check, descend"). Held out: no rule
    # was tuned against it. It tests the rules off their tuning: the camera sees the ground from higher, a
    # side approach shows the pads from the edge of the view or not at all, and stage pauses look like
    # hesitation.
    look_climb_m: Range = (0.3, 1.2)     # climb over the start height before setting off
    side_probability: float = 0.5        # share of landings flown beside the row
    side_offset_m: Range = (1.2, 2.5)    # the transit line's lateral offset from the aim (sign drawn)
    slide_in_m: Range = (0.4, 1.2)       # slides in once this close to the aim along x
    step_m: Range = (0.3, 0.8)           # height lost in one descent stage
    check_s: Range = (0.6, 2.0)          # hover between two stages
    climb_band_m: float = 0.1            # the climb is done within this of its target height


@dataclass
class FamilyConfig:
    """All family constants in one place (config is data)."""

    delay: DelayConfig = field(default_factory=DelayConfig)
    bang_bang: BangBangConfig = field(default_factory=BangBangConfig)
    tapper: TapperConfig = field(default_factory=TapperConfig)
    late: LateCorrectionConfig = field(default_factory=LateCorrectionConfig)
    change_mind: ChangeOfMindConfig = field(default_factory=ChangeOfMindConfig)
    depth_bias: DepthBiasConfig = field(default_factory=DepthBiasConfig)
    key_confusion: KeyConfusionConfig = field(default_factory=KeyConfusionConfig)
    alpha: AlphaConfig = field(default_factory=AlphaConfig)
    glide: GlideConfig = field(default_factory=GlideConfig)
    low_flyer: LowFlyerConfig = field(default_factory=LowFlyerConfig)
    cautious: CautiousConfig = field(default_factory=CautiousConfig)


# --------------------------------------------------------------------------- base with hooks
class FamilyPilot(SimulatedPilot):
    """The paper's pilot, restructured with hooks the families override (``paper`` = no overrides).

    Hooks: ``_draw_params`` (per-episode parameters), ``_perceived`` (where the pilot thinks the drone
    is), ``_horizontal`` (keys for x, y), ``_vertical`` (up/down key), ``_output`` (post-processing of
    the whole command: tapping, confusion, delay). Mixins chain them with ``super()``.
    """

    name = 'paper'

    def __init__(self, alpha: float = 0.5, beta: float = 0.5, cfg: PilotConfig | None = None,
                 rng: np.random.Generator | int | None = None, pads: np.ndarray | None = None,
                 family_cfg: FamilyConfig | None = None, cues: CueConfig | None = None):
        super().__init__(alpha, beta, cfg, rng)
        self.fcfg = family_cfg or FamilyConfig()
        self.family_rng = self.rng.spawn(1)[0]
        # the assistant's cues (assist_sim.cues), read with their own generator: a pilot who does not read them
        # flies as without them
        self.cues = CueReader(cues, self.rng.spawn(1)[0])
        self.pads = None if pads is None else np.asarray(pads, dtype=float).reshape(-1, 3)
        self.base_alpha = self.alpha
        self.params: dict[str, float | str] = {}
        self.t = 0.0
        # the pad the pilot now wants when it changed its goal during this landing (index into `pads`), else None:
        # the env then judges the landing on that pad (a family that never changes its goal leaves it None)
        self.new_goal_index: int | None = None

    @property
    def dt(self) -> float:
        """Control period (s)."""
        return 1.0 / self.cfg.control_hz

    def _start_delay(self, delay_s: float) -> None:
        """Empty the transport delay line of `delay_s` (at least one control step) for a new landing."""
        self.delay_steps = max(1, int(round(delay_s * self.cfg.control_hz)))
        self._queue: deque[np.ndarray] = deque()

    def _delayed(self, u: np.ndarray) -> np.ndarray:
        """`u` into the delay line; what comes out delay_steps later (nothing pressed before the first)."""
        self._queue.append(np.array(u, dtype=float))
        if len(self._queue) > self.delay_steps:
            return self._queue.popleft()
        return np.zeros(3)

    def reset(self, goal: np.ndarray, position: np.ndarray, goal_estimate: np.ndarray | None = None) -> None:
        """New landing: draw this episode's family parameters, then the paper's reset."""
        self.alpha = self.base_alpha
        self.params = {}
        self.t = 0.0
        self.new_goal_index = None
        self._draw_params()
        super().reset(goal, position, goal_estimate)
        self.cues.reset()

    def see_cue(self, cue: Cue | None) -> None:
        """The assistant's cue the station shows now (assist_sim.cues; None: none)."""
        self.cues.see(cue)

    def act(self, position: np.ndarray, agent_action: np.ndarray | None = None) -> np.ndarray:
        """The paper's step (estimate, then command) with the cues read where the pilot reads them."""
        self.goal_estimate, follow = self.cues.estimate(self.goal, self.goal_estimate)
        u = super().act(position, agent_action if follow else None)
        if self.cues.reading:
            u = u.copy()
            u[2] = self.cues.vertical(self.goal, float(np.asarray(position, dtype=float)[2]), float(u[2]),
                                      self.cfg.speed_down_mps)
        return u

    def _draw_params(self) -> None:
        """Per-episode family parameters (none for the paper pilot)."""

    def _perceived(self, p: np.ndarray) -> np.ndarray:
        return p + self.perception_error

    def _horizontal(self, d: np.ndarray, dist: float, pressing: bool) -> np.ndarray:
        c = self.cfg
        u = np.zeros(2)
        if pressing:
            for i in (0, 1):
                if abs(d[i]) > c.deadband_m:
                    u[i] = c.speed_xy_mps * np.sign(d[i])
        return u

    def _descend_radii(self) -> tuple[float, float]:
        return self.cfg.descend_radius_m, self.cfg.hold_radius_m

    def _vertical(self, p: np.ndarray, dist: float) -> float:
        c = self.cfg
        start, stop = self._descend_radii()
        if dist < start:
            self._descending = True
        elif dist > stop:
            self._descending = False
        if self._descending:
            return -c.speed_down_mps
        if p[2] - self.goal_estimate[2] < c.clearance_m:
            return c.speed_up_mps
        return 0.0

    def _output(self, u: np.ndarray, dist: float) -> np.ndarray:
        return u

    def command(self, position: np.ndarray) -> np.ndarray:
        """Keyboard-like command (3,) m/s; the paper's logic with the family hooks."""
        c = self.cfg
        p = np.asarray(position, dtype=float).reshape(3)
        self._update_perception()
        d = self.goal_estimate - self._perceived(p)
        dist = float(np.hypot(d[0], d[1]))
        period = max(1, int(round(c.tap_period_s * c.control_hz)))
        phase = (self._step % period) / period
        self._step += 1
        duty = self.duty * (c.fine_duty if dist < c.fine_radius_m else 1.0)
        u = np.zeros(3)
        u[:2] = self._horizontal(d, dist, phase < duty)
        u[2] = self._vertical(p, dist)
        out = self._output(u, dist)
        self.t += self.dt
        return out


# --------------------------------------------------------------------------- mixins (one per behaviour)
class DelayMixin(FamilyPilot):
    """Reaction delay: the command reaches the keys delay_s late (a pure transport delay).

    The pilot reacts to what it saw delay_s ago; for a memoryless mapping that is the same as delaying
    its output. Before the first delayed command arrives it presses nothing.
    """

    def _draw_params(self) -> None:
        super()._draw_params()
        delay = _draw(self.family_rng, self.fcfg.delay.delay_s)
        self.params['delay_s'] = delay
        self._start_delay(delay)

    def _output(self, u: np.ndarray, dist: float) -> np.ndarray:
        return self._delayed(super()._output(u, dist))


class BangBangMixin(FamilyPilot):
    """Bang-bang keys with late release (overshoot) and a committed descent (see BangBangConfig)."""

    def _draw_params(self) -> None:
        super()._draw_params()
        b, r = self.fcfg.bang_bang, self.family_rng
        self.params.update(speed_xy_mps=_draw(r, b.speed_xy_mps), release_delay_s=_draw(r, b.release_delay_s),
                           learn_factor=_draw(r, b.learn_factor), commit_radius_m=_draw(r, b.commit_radius_m))
        self._key = np.zeros(2)             # held direction per axis (-1, 0, +1)
        self._release = np.full(2, -1.0)    # seconds left before releasing a passed key (-1: not passed)
        self._delay = np.full(2, float(self.params['release_delay_s']))

    def _horizontal(self, d: np.ndarray, dist: float, pressing: bool) -> np.ndarray:
        c, speed = self.cfg, float(self.params['speed_xy_mps'])
        for i in (0, 1):
            if self._key[i] == 0:
                if abs(d[i]) > c.deadband_m:
                    self._key[i] = np.sign(d[i])
                continue
            passed = np.sign(d[i]) != self._key[i] or abs(d[i]) <= c.deadband_m
            if not passed:
                self._release[i] = -1.0
                continue
            if self._release[i] < 0:
                self._release[i] = self._delay[i]
            self._release[i] -= self.dt
            if self._release[i] <= 0:
                self._key[i] = 0.0
                self._release[i] = -1.0
                self._delay[i] *= float(self.params['learn_factor'])
        return speed * self._key.copy()

    def _descend_radii(self) -> tuple[float, float]:
        return self.cfg.descend_radius_m, float(self.params['commit_radius_m'])


class TapperMixin(FamilyPilot):
    """Hesitation and key-tapping: near the aim keys only in short taps; freezes (no key) now and then.

    In transit (farther than tap_radius_m from its aim) it holds keys like the paper pilot; within
    tap_radius_m the horizontal keys follow this family's tap clock (exactly tap_s on, gap_s off,
    replacing the paper pilot's duty cycle there) while the descent key stays held; freezes (all keys
    up) start at pause_rate_hz, near_factor times as often within near_radius_m of the aim.
    """

    def _draw_params(self) -> None:
        super()._draw_params()
        t, r = self.fcfg.tapper, self.family_rng
        self.params.update(tap_s=_draw(r, t.tap_s), gap_s=_draw(r, t.gap_s),
                           pause_rate_hz=_draw(r, t.pause_rate_hz), tap_radius_m=_draw(r, t.tap_radius_m))
        self._tap_clock = 0.0
        self._pause_left = 0.0
        self.paused = False

    def _tapping(self, dist: float) -> bool:
        return dist < float(self.params['tap_radius_m'])

    def _horizontal(self, d: np.ndarray, dist: float, pressing: bool) -> np.ndarray:
        return super()._horizontal(d, dist, True if self._tapping(dist) else pressing)

    def _output(self, u: np.ndarray, dist: float) -> np.ndarray:
        u = super()._output(u, dist).copy()
        t = self.fcfg.tapper
        rate = float(self.params['pause_rate_hz']) * (t.near_factor if dist < t.near_radius_m else 1.0)
        if self._pause_left <= 0 and self.family_rng.random() < rate * self.dt:
            self._pause_left = _draw(self.family_rng, t.pause_s)
        self.paused = self._pause_left > 0
        if self.paused:
            self._pause_left -= self.dt
            return np.zeros(3)
        if self._tapping(dist):
            tap, gap = float(self.params['tap_s']), float(self.params['gap_s'])
            if self._tap_clock >= tap:
                u[:2] = 0.0
            self._tap_clock = (self._tap_clock + self.dt) % (tap + gap)
        return u


def neighbour_pad(pads: np.ndarray, goal: np.ndarray, side: float) -> int:
    """Index of the pad next to the one at `goal` along the row (x), on `side` (+1 / -1), or on the other side at the
    row's end (at least two pads)."""
    order = np.argsort(pads[:, 0])
    k = int(np.argmin(np.linalg.norm(pads[order, :2] - np.asarray(goal, dtype=float)[:2], axis=1)))
    j = k + int(side)
    if not 0 <= j < len(order):
        j = k - int(side)
    return int(order[j])


class LateCorrectionMixin(FamilyPilot):
    """Flies confidently to a neighbour pad, then switches to the true goal suddenly and late."""

    def _draw_params(self) -> None:
        super()._draw_params()
        lc, r = self.fcfg.late, self.family_rng
        self.params.update(notice_height_m=_draw(r, lc.notice_height_m), notice_time_s=_draw(r, lc.notice_time_s),
                           side=float(r.choice([-1.0, 1.0])), lateral=float(r.normal(0.0, lc.lateral_sigma_m)))
        self.corrected = False

    def initial_estimate(self, goal: np.ndarray, position: np.ndarray) -> np.ndarray:
        """A neighbour pad's centre (the real one when the pads are known)."""
        goal = np.asarray(goal, dtype=float).reshape(3)
        side = float(self.params.get('side', 1.0))
        wrong = goal + np.array([side * self.fcfg.late.fallback_gap_m, 0.0, 0.0])
        if self.pads is not None and len(self.pads) > 1:
            wrong = self.pads[neighbour_pad(self.pads, goal, side)].copy()
        return wrong + np.array([0.0, float(self.params.get('lateral', 0.0)), 0.0])

    def update_estimate(self, agent_action: np.ndarray | None = None) -> np.ndarray:
        """No gradual correction before the switch (confident); the paper's update after it."""
        if self.corrected:
            return super().update_estimate(agent_action)
        beta = self.beta
        self.beta = 0.0
        try:
            return super().update_estimate(agent_action)
        finally:
            self.beta = beta

    def command(self, position: np.ndarray) -> np.ndarray:
        """Check the noticing trigger, then the family command."""
        p = np.asarray(position, dtype=float).reshape(3)
        if not self.corrected:
            low = (p[2] - self.goal_estimate[2] < float(self.params['notice_height_m'])
                   and np.hypot(*(p[:2] - self.goal_estimate[:2])) < 1.0)
            if low or self.t >= float(self.params['notice_time_s']):
                self.corrected = True
                self.params['corrected_at_s'] = round(self.t, 2)
                self.goal_estimate = self.goal + np.array([0.0, float(self.params['lateral']), 0.0])
                self._descending = False
        return super().command(position)


class ChangeOfMindMixin(FamilyPilot):
    """Flies to its goal as the paper pilot does, then chooses another pad: low over its aim, or after a while."""

    def _draw_params(self) -> None:
        super()._draw_params()
        cm, r = self.fcfg.change_mind, self.family_rng
        self.params.update(switch_height_m=_draw(r, cm.switch_height_m), switch_time_s=_draw(r, cm.switch_time_s),
                           neighbour=bool(r.uniform() < cm.neighbour_share), side=float(r.choice([-1.0, 1.0])),
                           pick=float(r.uniform()))

    def _other_pad(self) -> int | None:
        """The pad it changes to (drawn at reset): a neighbour along the row, or any other pad; None without pads."""
        if self.pads is None or len(self.pads) < 2:
            return None
        if self.params['neighbour']:
            return neighbour_pad(self.pads, self.goal, float(self.params['side']))
        goal = int(np.argmin(np.linalg.norm(self.pads[:, :2] - self.goal[:2], axis=1)))
        others = [i for i in range(len(self.pads)) if i != goal]
        return others[min(int(float(self.params['pick']) * len(others)), len(others) - 1)]

    def command(self, position: np.ndarray) -> np.ndarray:
        """Check the change-of-mind trigger, then the family command."""
        p = np.asarray(position, dtype=float).reshape(3)
        if self.new_goal_index is None and 'switched_at_s' not in self.params:
            low = (p[2] - self.goal_estimate[2] < float(self.params['switch_height_m'])
                   and np.hypot(*(p[:2] - self.goal_estimate[:2])) < self.fcfg.change_mind.switch_radius_m)
            if low or self.t >= float(self.params['switch_time_s']):
                self.params['switched_at_s'] = round(self.t, 2)
                j = self._other_pad()
                if j is not None:
                    self.new_goal_index = j
                    self.goal = self.pads[j].copy()
                    self.goal_estimate = SimulatedPilot.initial_estimate(self, self.goal, p)
                    self.params['new_goal_index'] = j
                    self._descending = False
        return super().command(position)


class DepthBiasMixin(FamilyPilot):
    """A constant error in judging the drone's own x (viewing depth) on top of the paper's drifting one."""

    def _draw_params(self) -> None:
        super()._draw_params()
        r = self.family_rng
        self.params['bias_m'] = float(r.choice([-1.0, 1.0])) * _draw(r, self.fcfg.depth_bias.bias_m)

    def _perceived(self, p: np.ndarray) -> np.ndarray:
        return super()._perceived(p) + np.array([float(self.params['bias_m']), 0.0, 0.0])


def confuse(u: np.ndarray, kind: str) -> np.ndarray:
    """A command as a confused key mapping turns it (swap x/y, or one axis's sign flipped)."""
    v = np.asarray(u, dtype=float).copy()
    if kind == 'swap_xy':
        v[0], v[1] = v[1], v[0]
    elif kind in ('flip_x', 'flip_y', 'flip_z'):
        v['xyz'.index(kind[-1])] *= -1.0
    else:
        raise ValueError(f'unknown confusion {kind!r}')
    return v


class KeyConfusionMixin(FamilyPilot):
    """Spells of a wrong key mapping (``confuse``), each lasting duration_s; ``confusion`` is the current one."""

    def _draw_params(self) -> None:
        super()._draw_params()
        k, r = self.fcfg.key_confusion, self.family_rng
        self.params['rate_hz'] = _draw(r, k.rate_hz)
        self.confusion: str | None = None
        self._left = 0.0
        if r.random() < k.start_probability:
            self._start_spell()

    def _start_spell(self) -> None:
        k, r = self.fcfg.key_confusion, self.family_rng
        self.confusion = str(r.choice(list(k.kinds)))
        self._left = _draw(r, k.duration_s)
        self.params['spells'] = int(self.params.get('spells', 0)) + 1

    def _output(self, u: np.ndarray, dist: float) -> np.ndarray:
        u = super()._output(u, dist)
        if self.confusion is None and self.family_rng.random() < float(self.params['rate_hz']) * self.dt:
            self._start_spell()
        if self.confusion is None:
            return u
        out = confuse(u, self.confusion)
        self._left -= self.dt
        if self._left <= 0:
            self.confusion = None
        return out


class AlphaMixin(FamilyPilot):
    """Conformance drawn per episode from the family's range (overrides the alpha it was built with)."""

    alpha_range_name = ''

    def _draw_params(self) -> None:
        super()._draw_params()
        self.alpha = _draw(self.family_rng, getattr(self.fcfg.alpha, self.alpha_range_name))
        self.params['alpha'] = self.alpha


# --------------------------------------------------------------------------- the families
class PaperPilot(FamilyPilot):
    """The paper's pilot (reference)."""

    name = 'paper'


class DelayPilot(DelayMixin):
    """Reaction delay."""

    name = 'delay'


class BangBangPilot(BangBangMixin):
    """Bang-bang overshoot."""

    name = 'bang_bang'


class TapperPilot(TapperMixin):
    """Hesitation and key-tapping."""

    name = 'tapper'


class LateCorrectionPilot(LateCorrectionMixin):
    """Wrong pad, then a sudden late correction."""

    name = 'late_correction'


class ChangeOfMindPilot(ChangeOfMindMixin):
    """Changes its goal to another pad mid-approach (judged on the final goal)."""

    name = 'change_mind'


class DepthBiasPilot(DepthBiasMixin):
    """Persistent depth misjudgement."""

    name = 'depth_bias'


class KeyConfusionPilot(KeyConfusionMixin):
    """Key confusion spells."""

    name = 'key_confusion'


class IgnorerPilot(AlphaMixin):
    """Ignores the assistant (alpha ~ 0)."""

    name = 'ignorer'
    alpha_range_name = 'ignorer_alpha'


class FollowerPilot(AlphaMixin):
    """Follows the assistant (alpha ~ 1)."""

    name = 'follower'
    alpha_range_name = 'follower_alpha'


class KeyboardPilot(DelayMixin, TapperMixin, LateCorrectionMixin, DepthBiasMixin, BangBangMixin):
    """Composite keyboard pilot: late, tapping, overshooting, wrong pad first, biased in depth."""

    name = 'keyboard'


class GlidePilot(FamilyPilot):
    """Analog stick, glide-path descent (GlideConfig): the paper's goal estimate and perception, another hand.

    Horizontal: gain x perceived offset to its aim, saturated at max_speed, plus tremor. Vertical: down
    toward the glide path when above it (path_offset + slope x (offset - final_radius) over its aim's
    height, at most speed_down), holding its height under it (climbing, as the paper pilot, only when
    lower than clearance_m over its aim), straight down at final_descent_mps inside final_radius. The
    whole command comes delay_s late. Commands are continuous: this family is not a keyboard.
    """

    name = 'glide'

    def _draw_params(self) -> None:
        super()._draw_params()
        g, r = self.fcfg.glide, self.family_rng
        self.params.update(gain_per_s=_draw(r, g.gain_per_s), max_speed_mps=_draw(r, g.max_speed_mps),
                           slope=_draw(r, g.slope), final_radius_m=_draw(r, g.final_radius_m),
                           tremor_mps=_draw(r, g.tremor_mps), delay_s=_draw(r, g.delay_s))
        self._start_delay(float(self.params['delay_s']))
        self._tremor = np.zeros(2)

    def command(self, position: np.ndarray) -> np.ndarray:
        """Stick command (3,) m/s toward the current estimate along the glide path (delayed)."""
        g, c, prm = self.fcfg.glide, self.cfg, self.params
        p = np.asarray(position, dtype=float).reshape(3)
        self._update_perception()
        d = self.goal_estimate - self._perceived(p)
        dist = float(np.hypot(d[0], d[1]))
        v = float(prm['gain_per_s']) * d[:2]
        speed = float(np.hypot(v[0], v[1]))
        if speed > float(prm['max_speed_mps']):
            v *= float(prm['max_speed_mps']) / speed
        final = float(prm['final_radius_m'])
        if dist < final:
            vz = -g.final_descent_mps
        else:
            path_z = self.goal_estimate[2] + g.path_offset_m + float(prm['slope']) * (dist - final)
            vz = float(np.clip(g.path_gain_per_s * (path_z - p[2]), -c.speed_down_mps, 0.0))
            if p[2] - self.goal_estimate[2] < c.clearance_m:
                vz = c.speed_up_mps         # under the glide path it holds its height, climbing only when low
        rho = float(np.exp(-self.dt / g.tremor_tau_s))
        self._tremor = (rho * self._tremor + np.sqrt(1.0 - rho * rho) * float(prm['tremor_mps'])
                        * self.family_rng.standard_normal(2))
        self._step += 1
        self.t += self.dt
        return self._delayed(np.array([*(v + self._tremor), vz]))


class LowFlyerPilot(FamilyPilot):
    """Gets low, then flies over the pads (LowFlyerConfig): the paper pilot with a cruise height."""

    name = 'low_flyer'

    def _draw_params(self) -> None:
        super()._draw_params()
        lf = self.fcfg.low_flyer
        top = float(self.pads[:, 2].max()) if self.pads is not None and len(self.pads) else lf.fallback_top_m
        self.params['cruise_z_m'] = top + _draw(self.family_rng, lf.cruise_over_top_m)

    def _vertical(self, p: np.ndarray, dist: float) -> float:
        v = super()._vertical(p, dist)
        if self._descending:
            return v
        z, band = float(self.params['cruise_z_m']), self.fcfg.low_flyer.band_m
        if p[2] > z + band:
            return -self.cfg.speed_down_mps
        if p[2] < z - band:
            return self.cfg.speed_up_mps
        return 0.0


class CautiousPilot(FamilyPilot):
    """Climbs to look, flies beside the row, descends in stages (CautiousConfig): the paper pilot otherwise.

    Phases: climb straight up look_climb_m over the start height (no horizontal key); then the paper
    pilot's keys toward its aim, or, on a side landing, toward a point side_offset_m beside it until it is
    within slide_in_m of the aim along x (from then on, the aim itself); the paper pilot's descent
    decision, cut into stages: after losing step_m it hovers for check_s (horizontal keys only), then
    goes on if it still believes it is over its aim.
    """

    name = 'cautious'

    def _draw_params(self) -> None:
        super()._draw_params()
        c, r = self.fcfg.cautious, self.family_rng
        side = float(r.choice([-1.0, 1.0])) * _draw(r, c.side_offset_m)
        self.params.update(look_climb_m=_draw(r, c.look_climb_m),
                           side_m=side if r.random() < c.side_probability else 0.0,
                           slide_in_m=_draw(r, c.slide_in_m), step_m=_draw(r, c.step_m), check_s=_draw(r, c.check_s))
        self._look_z: float | None = None       # set from the first position seen
        self._slid = False
        self._stage_z: float | None = None      # height where the current descent stage began
        self._check_left = 0.0

    def _climbing(self, p: np.ndarray) -> bool:
        if self._look_z is None:
            self._look_z = float(p[2]) + float(self.params['look_climb_m'])
            self.params['look_z_m'] = round(self._look_z, 3)
        if self._look_z > 0 and p[2] < self._look_z - self.fcfg.cautious.climb_band_m:
            return True
        self._look_z = -1.0                     # done: never climbs to look again
        return False

    def _horizontal(self, d: np.ndarray, dist: float, pressing: bool) -> np.ndarray:
        if self._look_z is None or self._look_z > 0:
            return np.zeros(2)                  # still climbing to look (decided first, in command)
        if not self._slid and abs(d[0]) < float(self.params['slide_in_m']):
            self._slid = True
        if self._slid or self.params['side_m'] == 0.0:
            return super()._horizontal(d, dist, pressing)
        return super()._horizontal(d + np.array([0.0, float(self.params['side_m']), 0.0]), dist, pressing)

    def _vertical(self, p: np.ndarray, dist: float) -> float:
        if self._climbing(p):
            return self.cfg.speed_up_mps
        if self._check_left > 0:
            self._check_left -= self.dt
            return 0.0
        v = super()._vertical(p, dist)
        if v >= 0:
            self._stage_z = None
            return v
        if self._stage_z is None:
            self._stage_z = float(p[2])
        if self._stage_z - p[2] >= float(self.params['step_m']):
            self._stage_z = None
            self._check_left = float(self.params['check_s'])
            return 0.0
        return v

    def command(self, position: np.ndarray) -> np.ndarray:
        """The family command; the climb decision comes first (the base calls _horizontal before _vertical)."""
        self._climbing(np.asarray(position, dtype=float).reshape(3))
        return super().command(position)


FAMILIES: dict[str, type[FamilyPilot]] = {cls.name: cls for cls in (
    PaperPilot, DelayPilot, BangBangPilot, TapperPilot, LateCorrectionPilot, ChangeOfMindPilot, DepthBiasPilot,
    KeyConfusionPilot, IgnorerPilot, FollowerPilot, KeyboardPilot, GlidePilot, LowFlyerPilot, CautiousPilot)}
TRAIN_FAMILIES: tuple[str, ...] = ('paper', 'delay', 'tapper', 'depth_bias', 'follower')
MIX_FAMILIES: tuple[str, ...] = ('bang_bang', 'late_correction', 'key_confusion', 'ignorer', 'keyboard')
APPROACH_FAMILIES: tuple[str, ...] = ('glide', 'low_flyer')
# held out from tuning too: no rule or actor was tuned or changed for them
UNTUNED_FAMILIES: tuple[str, ...] = ('cautious', 'change_mind')
HELDOUT_FAMILIES: tuple[str, ...] = MIX_FAMILIES + APPROACH_FAMILIES + UNTUNED_FAMILIES
# families whose goal changes during a landing: only the env flies them (the graph's contract has no topic on which
# sim_node would learn the pilot's new goal)
GOAL_CHANGING_FAMILIES: tuple[str, ...] = ('change_mind',)
POPULATIONS: dict[str, tuple[str, ...]] = {'mix': MIX_FAMILIES, 'approach_mix': APPROACH_FAMILIES,
                                           'train_mix': TRAIN_FAMILIES}
PILOT_NAMES: tuple[str, ...] = tuple(FAMILIES) + tuple(POPULATIONS)
# the pilots a node graph can fly (sim_pilot_node, evaluate_graph, simulate_study): all but the goal-changing ones
GRAPH_PILOT_NAMES: tuple[str, ...] = tuple(n for n in PILOT_NAMES if n not in GOAL_CHANGING_FAMILIES)


def resolve_pilot_name(name: str, rng: np.random.Generator) -> str:
    """The family `name` flies: itself, or for a population one of its families drawn with `rng` (make_pilot's draw)."""
    if name in POPULATIONS:
        return str(rng.choice(list(POPULATIONS[name])))
    return name


def make_pilot(name: str, alpha: float = 0.5, beta: float = 0.5, cfg: PilotConfig | None = None,
               rng: np.random.Generator | int | None = None, pads: np.ndarray | None = None,
               family_cfg: FamilyConfig | None = None, cues: CueConfig | None = None) -> FamilyPilot:
    """A pilot of family `name` (or one drawn from population `name` with `rng`), reading the assistant's cues as
    `cues` says (None: never); ValueError if unknown."""
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    name = resolve_pilot_name(name, rng)
    if name not in FAMILIES:
        raise ValueError(f'unknown pilot {name!r}; choose from {", ".join(PILOT_NAMES)}')
    return FAMILIES[name](alpha, beta, cfg, rng, pads=pads, family_cfg=family_cfg, cues=cues)


__all__ = ['FAMILIES', 'TRAIN_FAMILIES', 'MIX_FAMILIES', 'APPROACH_FAMILIES', 'UNTUNED_FAMILIES', 'HELDOUT_FAMILIES',
           'GOAL_CHANGING_FAMILIES', 'POPULATIONS', 'PILOT_NAMES', 'GRAPH_PILOT_NAMES', 'FamilyConfig', 'FamilyPilot',
           'make_pilot', 'resolve_pilot_name', 'confuse']
