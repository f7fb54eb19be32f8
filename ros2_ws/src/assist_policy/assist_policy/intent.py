"""The assistant's intent as data: the pad it steers to (with its uncertainty) and whether descending here is safe.

policy_node publishes it (/assist/goal_estimate, /assist/descent_ok; ARCHITECTURE.md), the evaluation env hands it
to simulated pilots that read cues, and replay_assist recomputes it; all three run ``IntentEstimator`` from
``loop.AssistLoop.act``, after the chain decided the step's command. It does not change that command.

Goal estimate (``IntentEstimator.update``). Candidates are the pads mapped from the depth images of this flight
(the pad recall's ``recall.PadMap``; with the recall switched off the estimator keeps its own map from the same
frames). Each step the command that flies, V (rotated into odom), predicts a spot: where V takes the vehicle in
``horizon_s``. A pad at horizontal distance d from that spot gets the log-likelihood -d^2 / (2 ``spread_m``^2),
and each pad's log-belief is that log-likelihood averaged exponentially over about ``memory_s`` (a pad first
mapped starts at its current one). The belief is their softmax; the estimate is the most believed pad (its
top-surface centre), its confidence that pad's belief, and its covariance the belief-weighted spread of the pads
around it plus the mapped centre's own uncertainty (``pad_sigma_m`` for a pad seen whole, ``part_sigma_m`` for
one only ever seen cut by the image border). So the estimate is the pad the assistant's command (the actor, the
rules and the pilot together) is taking the vehicle to: confident when one pad stands out over the last second,
spread over two pads while it is split between them. No pad mapped: no estimate. An assistant that knows the
goal (mode oracle) reports that goal, confidence 1. A step where the actor did not run (stale inputs) reports
no goal: the assistant is not steering. An actor with a goal head (``actor.Actor.goal_head``) gives the estimate
instead of the command: its Gaussian over the goal position (``LearnedGoal``) weighs the mapped pads, the belief is
those weights normalised (no memory here: the actor's own history window is its memory); with no pad mapped there is
no estimate (the contract's goal estimate is a pad's centre).

Descent (``descent_ok``). True when the depth image shows a surface nearer than the floor under all four legs
(no leg over the floor, none over a pad edge: the floor guard's leg test) or the camera is inside its blind range
over the pad last seen under them; the vehicle is within ``on_pad_m`` of the estimated goal (horizontally) and
moving slower than ``max_drift_mps`` horizontally. False when any of these fails; None (unknown: nothing is
published) without a fresh depth frame or with a leg window holding no valid depth.

Pure numpy; no rclpy.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np

from assist_common.frames import heading, rotate_xy
from assist_common.settings import check_named, setting

from .recall import MappedPad, PadMap, PadRecall
from .safety import FloorGuard
from .settings import node_param
from .stage import StepContext

ROTATION_VARIANCE = 1.0e6   # the goal estimate's rotational variances: a pad centre has no orientation to estimate


@dataclass
class IntentConfig:
    """Settings of the goal estimate and the descent flag (policy_node parameters intent_* map onto these)."""

    enabled: bool = node_param(True, 'intent', "Publish the assistant's intent: /assist/goal_estimate (the pad "
                               'its command steers to, with its uncertainty) and /assist/descent_ok (descending '
                               'here is safe), for the pilot\'s cues (assist_policy.intent).')
    horizon_s: float = setting(2.0, gt=0)       # the spot the command predicts: where V takes the vehicle in this
    spread_m: float = node_param(0.8, 'intent_spread_m', 'A pad this far (m) from the spot the command leads to '
                                 'is exp(-1/2) times as likely the goal as a pad on it.', min=0.05, max=10.0)
    memory_s: float = node_param(1.0, 'intent_memory_s', 'Time constant of the goal belief (s): the '
                                 'likelihoods of about this long are averaged.', min=0.05, max=30.0)
    pad_sigma_m: float = setting(0.1, ge=0)     # std of a mapped pad centre seen whole (m)
    part_sigma_m: float = setting(0.3, ge=0)    # ... of one only seen cut by the image border
    known_sigma_m: float = setting(0.01, ge=0)  # ... of a goal the assistant is given (mode oracle)
    on_pad_m: float = setting(0.3, gt=0)        # nearer the estimated centre than this: over it (descend here)
    max_drift_mps: float = setting(0.6, ge=0)   # moving faster than this horizontally: not "descend here"
    max_dt_s: float = setting(1.0, gt=0)        # a longer gap between steps counts as this long

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line)."""
        check_named(self, type(self).__name__)


@dataclass(frozen=True)
class Intent:
    """One step's intent: the estimated goal (odom, pad top centre), its covariance and confidence, descent_ok."""

    goal: np.ndarray | None             # None: no estimate (nothing mapped yet)
    covariance: np.ndarray | None       # 3x3 position covariance (m^2)
    confidence: float                   # belief in the estimated pad (0 without an estimate)
    index: int | None                   # the pad's index in the flight's map (None: given goal, or none)
    descent_ok: bool | None             # None: unknown (no fresh depth, a leg window without depth)
    candidates: int = 0                 # pads believed in

    @property
    def sigma_xy_m(self) -> float:
        """The horizontal standard deviation of the estimate: sqrt(max(var x, var y)) (inf without an estimate)."""
        if self.covariance is None:
            return math.inf
        return math.sqrt(max(float(self.covariance[0, 0]), float(self.covariance[1, 1])))

    def pose_covariance(self) -> list[float]:
        """The 6x6 row-major covariance of a PoseWithCovariance: position block as estimated, rotation unknown."""
        cov = np.zeros((6, 6))
        if self.covariance is not None:
            cov[:3, :3] = self.covariance
        cov[3:, 3:] = np.eye(3) * ROTATION_VARIANCE
        return cov.reshape(-1).tolist()


NO_INTENT = Intent(None, None, 0.0, None, None)


@dataclass(frozen=True)
class LearnedGoal:
    """A goal head's estimate this step: the goal's mean position (odom, m) and its horizontal standard deviation."""

    mean: np.ndarray
    sigma_m: float


class IntentEstimator:
    """The goal belief over the mapped pads of one flight, and the descent flag (module docstring)."""

    def __init__(self, cfg: IntentConfig | None = None, recall: PadRecall | None = None,
                 guard: FloorGuard | None = None):
        self.cfg = cfg or IntentConfig()
        self.recall = recall
        self.guard = guard or FloorGuard()
        self._own = PadMap(recall.cfg) if recall is not None else PadMap()
        self._mapped: Hashable = None      # key of the depth frame last added to the own map
        self._log_belief: list[float] = []  # per pad of the map, in its order (pads are only appended)
        self._source: PadMap | None = None  # the map the belief is over
        self._t: float | None = None
        self.last: Intent = NO_INTENT

    def reset(self) -> None:
        """Forget the flight: the belief and the own map."""
        self._own.reset()
        self._mapped = None
        self._log_belief.clear()
        self._t = None
        self.last = NO_INTENT

    def clear(self) -> None:
        """A step without the chain: no intent this step (the belief is kept)."""
        self.last = NO_INTENT

    def _pads(self, ctx: StepContext) -> list[MappedPad]:
        """The flight's mapped pads: the recall's map, or (recall off) the own map updated with this frame. The
        belief follows one map: when the other takes over (the recall switched at run time) it starts afresh."""
        if self.recall is not None and self.recall.cfg.enabled:
            source = self.recall.map
        else:
            source = self._own
            if ctx.frame is not None and self._mapped != ctx.frame.key:
                self._own.update(ctx.frame.image, *ctx.frame.pose)
                self._mapped = ctx.frame.key
        if source is not self._source or len(source.pads) < len(self._log_belief):
            self._source = source
            self._log_belief.clear()
        return source.pads

    def update(self, ctx: StepContext, velocity: np.ndarray, known_goal: np.ndarray | None = None,
               assisting: bool = True, learned: LearnedGoal | None = None) -> Intent:
        """This step's intent from the context and the command `velocity` that flies (base_link, m/s); a known goal
        (mode oracle) is the estimate itself, a `learned` one (a goal head) weighs the mapped pads. Not
        `assisting` (the actor did not run): the belief follows the command all the same, but no goal is
        reported (the descent flag is)."""
        c = self.cfg
        if not c.enabled:
            self.last = NO_INTENT
            return self.last
        dt = c.max_dt_s if self._t is None else min(max(ctx.t - self._t, 0.0), c.max_dt_s)
        self._t = ctx.t
        p = np.asarray(ctx.position, dtype=float).reshape(3)
        if known_goal is not None:
            goal = np.asarray(known_goal, dtype=float).reshape(3)
            intent = Intent(goal.copy(), np.eye(3) * c.known_sigma_m ** 2, 1.0, None, None, 1)
        elif learned is not None:
            intent = self._learned(ctx, learned)
        else:
            intent = self._estimate(ctx, p, np.asarray(velocity, dtype=float).reshape(3), dt)
        ok = self._descent_ok(ctx, p, intent.goal)
        intent = (dataclasses.replace(intent, descent_ok=ok) if assisting
                  else Intent(None, None, 0.0, None, ok, intent.candidates))
        self.last = intent
        return intent

    def _estimate(self, ctx: StepContext, p: np.ndarray, v_body: np.ndarray, dt: float) -> Intent:
        """The belief over the mapped pads, moved one step toward where the command leads."""
        c = self.cfg
        pads = self._pads(ctx)
        if not pads:
            return Intent(None, None, 0.0, None, None)
        yaw = 0.0 if ctx.quaternion is None else heading(ctx.quaternion)
        v_xy = rotate_xy(v_body[:2], yaw) if np.all(np.isfinite(v_body[:2])) else np.zeros(2)
        spot = p[:2] + v_xy * c.horizon_s
        centres = np.array([pad.xyz for pad in pads], dtype=float)
        log_like = -np.sum((centres[:, :2] - spot) ** 2, axis=1) / (2.0 * c.spread_m ** 2)
        keep = 1.0 - math.exp(-dt / c.memory_s)
        n_old = len(self._log_belief)
        for k in range(len(pads)):
            if k < n_old:
                self._log_belief[k] += keep * (float(log_like[k]) - self._log_belief[k])
            else:
                self._log_belief.append(float(log_like[k]))
        return self._belief_intent(pads, centres, np.array(self._log_belief))

    def _belief_intent(self, pads: list[MappedPad], centres: np.ndarray, log_belief: np.ndarray) -> Intent:
        """The most believed pad of a log-belief over `pads`, its belief, and the belief-weighted spread of the pads
        around it plus the mapped centre's own uncertainty as its covariance."""
        b = np.exp(log_belief - log_belief.max())
        b /= b.sum()
        best = int(np.argmax(b))
        spread = centres - centres[best]
        sigma = self.cfg.pad_sigma_m if pads[best].whole else self.cfg.part_sigma_m
        cov = (spread * b[:, None]).T @ spread + np.eye(3) * sigma ** 2
        return Intent(centres[best].copy(), cov, float(b[best]), best, None, len(pads))

    def _learned(self, ctx: StepContext, learned: LearnedGoal) -> Intent:
        """The mapped pads weighed by the goal head's Gaussian (module docstring)."""
        c = self.cfg
        mean = np.asarray(learned.mean, dtype=float).reshape(3)
        sigma = max(float(learned.sigma_m), c.pad_sigma_m)
        pads = self._pads(ctx)
        self._log_belief.clear()           # the command-following belief does not carry over a learned estimate
        if not pads:
            return Intent(None, None, 0.0, None, None)
        centres = np.array([pad.xyz for pad in pads], dtype=float)
        log_like = -np.sum((centres[:, :2] - mean[:2]) ** 2, axis=1) / (2.0 * sigma ** 2)
        return self._belief_intent(pads, centres, log_like)

    def _descent_ok(self, ctx: StepContext, p: np.ndarray, goal: np.ndarray | None) -> bool | None:
        """Descending here is safe (module docstring); None when the depth image cannot tell."""
        if ctx.frame is None or not np.all(np.isfinite(p)):
            return None
        on_pad = self.guard.legs_on_pad(ctx.frame.image, p)
        if on_pad is None:
            return None
        if not on_pad or goal is None:
            return False
        c = self.cfg
        if math.hypot(p[0] - goal[0], p[1] - goal[1]) >= c.on_pad_m:
            return False
        v = np.asarray(ctx.velocity, dtype=float).reshape(3)
        return bool(np.all(np.isfinite(v[:2])) and math.hypot(v[0], v[1]) <= c.max_drift_mps)
