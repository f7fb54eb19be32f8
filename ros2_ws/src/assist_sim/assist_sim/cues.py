"""Simulated pilots who read the assistant's cues: the pad it is steering to, and its descend / hold light.

The pilot station shows a person the pad the assistant believes is the goal (/assist/goal_estimate) and a green
or red light (/assist/descent_ok). A simulated pilot of any family (``pilots.FamilyPilot``) reads them as
``CueReader`` says, each landing with probability ``trust`` (drawn at the landing's start from the reader's own
generator, so a pilot who does not read cues flies exactly as without them):

* goal cue, sure enough (its horizontal standard deviation at most ``max_sigma_m``): the pilot knows which pad
  it means, so it recognises whether the highlighted pad is that pad (its centre within ``agree_m`` of the goal's).
  Agreeing, it switches its own estimate to the highlighted centre (a share ``adopt_rate`` of the gap each step):
  the highlight shows where its pad is, which is what it misjudges in depth. Disagreeing, it sees the assistant
  heading for another pad and does not follow its push (no conformance term that step), so it is not dragged
  there; and when that other pad is where it was aiming itself (its estimate within ``agree_m`` of the highlighted
  centre), it has learnt that its aim is off and looks again at its pad: its estimate moves toward the goal by
  ``correct_rate`` of the error each step (as the paper's skill term does, faster);
* light: green while the goal cue agrees and the pilot is on its way down or over the pad, it descends; red
  lower than ``hold_below_m`` over the floor, it holds its descent (no down key).

The reactions skip the pilot's key delay and tapping (a light is read at a glance). Pure numpy; no rclpy.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from assist_common.settings import check_named, setting


@dataclass
class CueConfig:
    """How a simulated pilot reads the cues (module docstring)."""

    trust: float = setting(0.0, ge=0, le=1)     # chance per landing that the pilot reads the cues (0: never)
    agree_m: float = setting(0.8, ge=0)         # a highlighted pad centre this close to its goal pad's: its pad
    adopt_rate: float = setting(0.2, ge=0, le=1)   # agreeing: the share of the gap its estimate closes per step
    # its own aim on a highlighted pad that is not its pad: the share of its error it corrects per step
    correct_rate: float = setting(0.05, ge=0, le=1)
    max_sigma_m: float = setting(0.5, ge=0)     # a goal cue less sure than this (xy standard deviation, m): not read
    hold_below_m: float = setting(2.0, ge=0)    # red light lower than this over the floor: no descent

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line)."""
        check_named(self, type(self).__name__)


@dataclass(frozen=True)
class Cue:
    """What the station shows this step: the highlighted pad (odom, or None), its xy std (m), the light."""

    goal: np.ndarray | None = None
    sigma_m: float = math.inf
    descent_ok: bool | None = None


NO_CUE = Cue()


class CueReader:
    """One pilot's reading of the cues, landing by landing (module docstring)."""

    def __init__(self, cfg: CueConfig | None = None, rng: np.random.Generator | None = None):
        self.cfg = cfg or CueConfig()
        self.rng = rng if rng is not None else np.random.default_rng()
        self.reading = False           # this landing: the pilot reads the cues
        self.cue = NO_CUE

    def reset(self) -> None:
        """A new landing: whether the pilot reads the cues in it (nothing drawn when it never does)."""
        self.cue = NO_CUE
        self.reading = self.cfg.trust > 0.0 and bool(self.rng.random() < self.cfg.trust)

    def see(self, cue: Cue | None) -> None:
        """The cue shown now (None: none shown)."""
        self.cue = cue or NO_CUE

    def agrees(self, goal: np.ndarray) -> bool | None:
        """Whether the goal cue shows the pilot's pad (None: not read: not reading, no cue, or unsure)."""
        c, cue = self.cfg, self.cue
        if not self.reading or cue.goal is None or not cue.sigma_m <= c.max_sigma_m:
            return None
        g = np.asarray(goal, dtype=float)
        return bool(math.hypot(cue.goal[0] - g[0], cue.goal[1] - g[1]) <= c.agree_m)

    def estimate(self, goal: np.ndarray, estimate: np.ndarray) -> tuple[np.ndarray, bool]:
        """(the pilot's goal estimate after reading the goal cue, whether it follows the assistant's push)."""
        agree = self.agrees(goal)
        if agree is None:
            return estimate, True
        target = np.asarray(self.cue.goal, dtype=float)
        if agree:
            return estimate + self.cfg.adopt_rate * (target - estimate), True
        if math.hypot(estimate[0] - target[0], estimate[1] - target[1]) <= self.cfg.agree_m:
            return estimate + self.cfg.correct_rate * (np.asarray(goal, dtype=float) - estimate), False
        return estimate, False

    def vertical(self, goal: np.ndarray, height_m: float, u_z: float, down_mps: float) -> float:
        """The pilot's vertical command after reading the light (`height_m` over the floor)."""
        if not self.reading or self.cue.descent_ok is None:
            return u_z
        if self.cue.descent_ok:
            return -down_mps if self.agrees(goal) else u_z
        return max(u_z, 0.0) if height_m < self.cfg.hold_below_m else u_z
