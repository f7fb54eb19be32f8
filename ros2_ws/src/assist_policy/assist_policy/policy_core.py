"""Pure policy core behind policy_node: inputs with timestamps -> agent action a and blended V.

Safety rules (ARCHITECTURE.md, "Timing and safety rules"):
* every input is range-checked where it enters (finite, plausible magnitude, right size, right
  frame); a bad one raises ``InputRejected`` (a ValueError with a short reason key), is counted in
  ``rejections`` and never replaces the last good value;
* pilot command older than pilot_timeout_s (or never received) -> u = 0;
* scene feature (latent / goal / image) or odometry stale or absent -> relinquish: no a, V = u;
* non-finite actor output is rejected (counted, V = u), never reaches V;
* any exception inside a step relinquishes (V = u, reason key ``step_error``), never escapes;
* V is clamped to max_speed_mps (horizontal norm) and max_vertical_mps;
* floor guard (``safety.FloorGuard``, not learned): low over the floor with no pad under the legs in
  the depth image, a descending V is replaced by a small climb (agent action a' = 2 V' - u, reason key
  ``floor_guard``); needs fresh odometry and a depth image (``set_depth``) no older than feature_timeout_s;
  its wall rule (``walls.WallGuard``) then removes the part of V heading for a wall seen within
  ``SafetyConfig.wall_radius_m`` (walls: surfaces higher than any pad; reason key ``wall_guard``);
* pilot override (``override.PilotOverride``, not learned): while the pilot holds a horizontal key and
  does not descend, pushes one way for 2 s held back (or more slowly for 5 s, not descending), or
  commands a climb for 2 s that the vehicle does not make, the actor's action is replaced (the pilot's command passes, the vehicle rises gently when
  low; reason key ``pilot_override``);
* pad recall (``recall.PadRecall``, not learned): every depth frame adds the pads in view to a map
  (odom, with the odometry attitude); when the pilot descends (or is low) with the floor under every
  leg, the actor's horizontal action is replaced by a push back to the nearest mapped pad (first, for a
  pad behind, a look at the ground beyond not yet seen, where a nearer pad may be: scout); low over a
  pad seen whole during a descent, by centring on it (touchdown; reason key ``pad_recall`` for both);
  needs fresh odometry and depth, like the floor guard, which still acts after it;
* oscillation damper (``damper.OscillationDamper``, not learned): while the pilot's held keys keep
  reversing across a pad of the recall's map (a pilot-induced oscillation), the actor's horizontal
  action is replaced by a_xy = -gain v_xy (the odometry twist, base_link); before the override and the
  recall, which replace it when they act (reason key ``oscillation_damper``).
"""
from __future__ import annotations

import dataclasses
import logging
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from assist_sim.core.geometry import quat_to_matrix
from assist_sim.shipped import shipped_model_path

from .actions import scale_action
from .blending import DEFAULT_THRESHOLD, MAX_SPEED_MPS, MAX_VERTICAL_MPS, blend, clamp_velocity
from .damper import DamperConfig, OscillationDamper
from .observation import Condition, ObservationBuilder, image_feature, oracle_feature
from .override import OverrideConfig, PilotOverride
from .poses import PoseHistory
from .recall import PadRecall, RecallConfig
from .safety import FloorGuard, SafetyConfig
from .td3 import load_actor
from .walls import WallGuard

log = logging.getLogger(__name__)

POSE_HISTORY_S = 1.0  # odometry poses kept for pairing depth frames by stamp (s)
MAX_DEPTH_M = 100.0   # depth beyond this (or negative / non-finite) is a hole (0), as the sim and drivers mark them


# /diagnostics reason of each rule's mode (override.PilotOverride.mode, recall.PadRecall.mode)
_OVERRIDE_REASONS = {'held_key': 'pilot override: the pilot\'s held correction passes',
                     'persistent': 'pilot override: the pilot\'s persistent push passes',
                     'climb': 'pilot override: the pilot\'s held climb passes',
                     'long': 'pilot override: the pilot\'s long push passes'}
_RECALL_REASONS = {'recall': 'pad recall: steering back to a pad seen',
                   'touchdown': 'pad recall: centring on the pad below for touchdown',
                   'scout': 'pad recall: looking beyond for a nearer pad before steering back'}


def default_model_path(mode: str) -> Path:
    """Shipped actor for a mode, td3_<mode>_actor.pt: $ASSIST_MODELS_DIR, share/assist_policy/models or the repo's models/."""
    return shipped_model_path('assist_policy', f'td3_{Condition(mode).value}_actor.pt')


class InputRejected(ValueError):
    """An input the core refused; `reason` is a short key for diagnostics (e.g. ``pilot_frame``)."""

    def __init__(self, reason: str, detail: str):
        super().__init__(detail)
        self.reason = reason


def _positive(name: str, value: float) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ValueError(f'PolicyCoreConfig.{name} must be a finite number > 0, got {value!r}')


@dataclass
class PolicyCoreConfig:
    """Settings of the policy core (policy_node parameters map 1:1); validated on construction."""

    mode: str = 'latent'
    blend_threshold: float = DEFAULT_THRESHOLD
    pilot_timeout_s: float = 0.5
    feature_timeout_s: float = 0.5
    odom_timeout_s: float = 0.5
    max_speed_mps: float = MAX_SPEED_MPS
    max_vertical_mps: float = MAX_VERTICAL_MPS
    max_input_mps: float = 5.0          # pilot commands faster than this (norm) are rejected
    body_frame: str = 'base_link'       # pilot commands must be in this frame (or carry no frame)
    max_odom_speed_mps: float = 50.0    # odometry faster than this is not a multirotor: rejected
    max_position_m: float = 1.0e4       # odometry / goal coordinates beyond this are rejected
    max_latent_abs: float = 1.0e3       # encoder means beyond this are rejected
    safety: SafetyConfig | None = None  # floor guard settings (None: SafetyConfig() defaults)
    override: OverrideConfig | None = None  # pilot override settings (None: OverrideConfig() defaults)
    recall: RecallConfig | None = None      # pad recall settings (None: RecallConfig() defaults)
    damper: DamperConfig | None = None      # oscillation damper settings (None: DamperConfig() defaults)
    # velocity the actor sees: the odometry twist as given (base_link, policy_node) or rotated to odom with the
    # odometry attitude (as evaluate's env trains and flies it; replay_assist for evaluate's bags); the rules
    # (floor guard, override, damper) always read the twist
    actor_velocity: str = 'twist'
    # the pad recall maps a depth frame from the odometry pose at the frame's sensor stamp (interpolated) when
    # odometry stamps lie within this of it (s); else from the latest odometry (counted: depth_pose_unmatched)
    depth_pose_match_s: float = 0.1

    def __post_init__(self) -> None:
        """Reject settings that would reverse, suppress or invent motion (ValueError, one line)."""
        self.mode = Condition(self.mode).value
        thr = self.blend_threshold
        if not (isinstance(thr, (int, float)) and math.isfinite(thr) and thr >= 0):
            raise ValueError(f'PolicyCoreConfig.blend_threshold must be a finite number >= 0, got {thr!r}')
        for name in ('pilot_timeout_s', 'feature_timeout_s', 'odom_timeout_s', 'max_speed_mps',
                     'max_vertical_mps', 'max_input_mps', 'max_odom_speed_mps', 'max_position_m',
                     'max_latent_abs'):
            _positive(name, getattr(self, name))
        m = self.depth_pose_match_s
        if not (isinstance(m, (int, float)) and math.isfinite(m) and m >= 0):
            raise ValueError(f'PolicyCoreConfig.depth_pose_match_s must be a finite number >= 0, got {m!r}')
        if self.actor_velocity not in ('twist', 'odom'):
            raise ValueError(f"PolicyCoreConfig.actor_velocity must be 'twist' or 'odom', got {self.actor_velocity!r}")


@dataclass
class PolicyOutput:
    """Result of one policy step: agent action (None when relinquished), blended V, why.

    `key` is a short stable reason for diagnostics: ``assisting``, ``small_action`` (the actor chose
    |a| <= threshold), ``odom_stale``, ``feature_stale``, ``goal_absent``, ``actor_nonfinite`` or
    ``step_error``, ``floor_guard`` (the floor guard replaced a descent), ``pilot_override`` (the pilot
    override replaced the actor's action), ``pad_recall`` (the pad recall steered back to a mapped pad) or
    ``oscillation_damper`` (the oscillation damper replaced the actor's horizontal action);
    `reason` is the text.
    """

    agent: np.ndarray | None
    velocity: np.ndarray
    reason: str
    key: str = 'assisting'
    fault: str = ''           # exception type name when key is step_error

    @property
    def assisting(self) -> bool:
        """True when the agent's action is blended into V."""
        return self.key == 'assisting'


class PolicyCore:
    """Holds the latest inputs, builds observations, runs the actor, applies the blending rule."""

    def __init__(self, actor_path: str | Path, cfg: PolicyCoreConfig | None = None):
        self.cfg = cfg or PolicyCoreConfig()
        self.mode = Condition(self.cfg.mode)
        self.actor, self.meta = load_actor(actor_path)      # metadata and weights validated there
        trained = self.meta.get('condition')
        if trained is not None and trained != self.mode.value:
            raise ValueError(f'{actor_path}: actor was trained for {trained!r}, not mode {self.mode.value!r}')
        self.max_speed = tuple(float(v) for v in self.meta['max_speed'])
        self.builder = ObservationBuilder(self.mode, int(self.meta['latent_dim']), float(self.meta['window_s']),
                                          tuple(self.meta['feature_lags_s']), self.meta['memory_displacement'])
        if self.builder.dim != int(self.meta['vec_dim']):
            raise ValueError(f'{actor_path}: actor expects {self.meta["vec_dim"]} inputs, the {self.mode.value} '
                             f'observation has {self.builder.dim}')
        self._pilot: tuple[float, np.ndarray] | None = None
        self._odom: tuple[float, np.ndarray, np.ndarray] | None = None
        self._attitude: np.ndarray | None = None   # odom -> base_link quaternion (x, y, z, w); None: level, heading 0
        self._feature: tuple[float, np.ndarray] | None = None
        self._goal: np.ndarray | None = None
        self.rejected = 0                      # non-finite actor outputs
        self.rejections: Counter[str] = Counter()   # refused inputs, per reason key
        self.faults: Counter[str] = Counter()       # exceptions inside step(), per exception type
        self.guard = FloorGuard(self.cfg.safety or SafetyConfig())
        self._depth: tuple[float, np.ndarray] | None = None
        self._depth_stamp = 0.0                     # sensor stamp of the latest depth frame (s)
        self._poses = PoseHistory(POSE_HISTORY_S, self.cfg.depth_pose_match_s)   # odometry by sensor stamp
        self.depth_pose_unmatched = 0               # depth frames mapped from the latest odometry (no pose at their stamp)
        self.guard_engaged = 0                      # steps whose descent the floor guard replaced
        self.walls = WallGuard(self.guard.cfg)      # the floor guard's wall rule (same settings object)
        self.wall_engaged = 0                       # steps whose approach to a wall the wall rule stopped
        self._depth_pose: tuple[float, tuple] | None = None   # (arrival of the depth frame, its odometry pose)
        self.override = PilotOverride(self.cfg.override or OverrideConfig())
        self.override_engaged = 0                   # steps whose actor action the pilot override replaced
        self.persist_engaged = 0                    # ... of which for a persistent push (override.mode 'persistent')
        self.climb_engaged = 0                      # ... of which for a held climb (override.mode 'climb')
        self.long_engaged = 0                       # ... of which for a long push (override.mode 'long')
        self.spot_kept = 0                          # steps a landing spot kept the actor's action (override.kept)
        self.recall = PadRecall(self.cfg.recall or RecallConfig(), self.guard)
        self.recall_engaged = 0                     # steps whose horizontal action the pad recall replaced
        self.touchdown_engaged = 0                  # ... of which centring on the pad below (recall.mode 'touchdown')
        self.scout_engaged = 0                      # ... of which looking beyond before going back (recall.mode 'scout')
        self.damper = OscillationDamper(self.cfg.damper or DamperConfig())
        self.damper_engaged = 0                     # steps whose horizontal action the oscillation damper replaced
        self._mapped_depth: float | None = None     # stamp of the depth frame last added to the pad map
        self._walls_depth: float | None = None      # ... and to the wall map

    def configure(self, **changes) -> None:
        """Change settings at run time (e.g. speed limits); ValueError (nothing changed) if invalid."""
        cfg = dataclasses.replace(self.cfg, **changes)
        if cfg.mode != self.cfg.mode:
            raise ValueError('the mode of a running policy core cannot change')
        self.cfg = cfg
        self._poses.match_s = cfg.depth_pose_match_s

    # ------------------------------------------------------------- inputs
    def _reject(self, reason: str, detail: str) -> InputRejected:
        self.rejections[reason] += 1
        return InputRejected(reason, detail)

    def _vector(self, what: str, values, size: int, limit: float) -> np.ndarray:
        """`values` as a float vector of `size` finite entries within +-limit, else InputRejected."""
        try:
            v = np.asarray(values, dtype=float).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise self._reject(f'{what}_malformed', f'{what}: not numbers ({exc})') from None
        if v.size != size:
            raise self._reject(f'{what}_size', f'{what} has {v.size} values, expected {size}')
        if not np.all(np.isfinite(v)):
            raise self._reject(f'{what}_nonfinite', f'{what} not finite: {v.tolist()}')
        if np.abs(v).max(initial=0.0) > limit:
            raise self._reject(f'{what}_range', f'{what} out of range (|x| > {limit:g}): {v.tolist()}')
        return v

    def _stamp(self, what: str, t: float) -> float:
        try:
            t = float(t)
        except (TypeError, ValueError):
            raise self._reject(f'{what}_stamp', f'{what}: stamp {t!r} is not a number') from None
        if not math.isfinite(t):
            raise self._reject(f'{what}_stamp', f'{what}: stamp {t!r} is not finite')
        return t

    def set_pilot(self, t: float, u: np.ndarray, frame_id: str = '') -> None:
        """Latest pilot command (m/s, body frame); InputRejected when malformed, too fast or in another frame."""
        t = self._stamp('pilot', t)
        if frame_id not in ('', self.cfg.body_frame):
            raise self._reject('pilot_frame', f'pilot command in frame {frame_id!r}, expected '
                                              f'{self.cfg.body_frame!r}')
        u = self._vector('pilot', u, 3, math.inf)
        speed = float(np.linalg.norm(u))
        if speed > self.cfg.max_input_mps:
            raise self._reject('pilot_range', f'pilot command {u.tolist()} ({speed:.3g} m/s) faster than '
                                              f'max_input_speed {self.cfg.max_input_mps:g} m/s')
        self._pilot = (t, u)

    def set_odom(self, t: float, position: np.ndarray, velocity: np.ndarray,
                 orientation: np.ndarray | None = None, stamp: float | None = None) -> None:
        """Latest odometry (odom ENU; orientation x, y, z, w, None or zeros = level); InputRejected when implausible.

        `t` is when it arrived (the clock of `step`); `stamp` when it was measured (header stamp, s; None: `t`),
        by which a depth frame's pose is looked up.
        """
        t = self._stamp('odom', t)
        stamp = t if stamp is None else self._stamp('odom', stamp)
        p = self._vector('odom_position', position, 3, self.cfg.max_position_m)
        v = self._vector('odom_velocity', velocity, 3, self.cfg.max_odom_speed_mps)
        q = None if orientation is None else self._vector('odom_orientation', orientation, 4, 2.0)
        if q is not None and not np.any(q):
            q = None                  # all zero: a source that fills no orientation (taken as level, heading 0)
        if q is not None:
            n = float(np.linalg.norm(q))
            if not 0.9 < n < 1.1:
                raise self._reject('odom_orientation', f'odometry orientation {q.tolist()} is not a unit quaternion')
            q = q / n
        self._odom, self._attitude = (t, p, v), q
        self._poses.add(stamp, p, q)

    def set_latent(self, t: float, mu: np.ndarray) -> None:
        """Latest encoder mean (latent mode); InputRejected on wrong size, non-finite or huge values."""
        t = self._stamp('latent', t)
        self._feature = (t, self._vector('latent', mu, self.builder.latent_dim, self.cfg.max_latent_abs))

    def set_goal(self, goal: np.ndarray) -> None:
        """True goal (oracle mode, simulation only); InputRejected when non-finite or implausible."""
        self._goal = self._vector('goal', goal, 3, self.cfg.max_position_m)

    def set_image(self, t: float, rgb: np.ndarray, depth: np.ndarray) -> None:
        """Latest RGB-D frame (end-to-end mode): uint8 HxWx3 + metres HxW (holes: 0, NaN, negative)."""
        t = self._stamp('image', t)
        rgb, depth = np.asarray(rgb), np.asarray(depth)
        if rgb.dtype != np.uint8:
            raise self._reject('image_encoding', f'colour image must be uint8, got {rgb.dtype}')
        if not np.issubdtype(depth.dtype, np.number):
            raise self._reject('image_encoding', f'depth image must be numeric, got {depth.dtype}')
        depth = depth.astype(np.float32)
        depth = np.where(np.isfinite(depth) & (depth >= 0) & (depth <= MAX_DEPTH_M), depth, 0.0)
        try:
            feature = image_feature(rgb, depth).reshape(-1)
        except ValueError as exc:
            raise self._reject('image_size', str(exc)) from None
        if feature.size != self.actor.trunk.img_size:
            raise self._reject('image_size', f'image of {feature.size} values, the actor expects '
                                              f'{self.actor.trunk.img_size}')
        self._feature = (t, feature)

    def set_depth(self, t: float, depth: np.ndarray, stamp: float | None = None) -> None:
        """Latest depth image for the floor guard: metres HxW (holes: 0, NaN, negative); InputRejected if not 2-D.

        `t` is when it arrived; `stamp` when it was taken (header stamp, s; None: `t`): the pad recall maps it
        from the odometry pose at that stamp.
        """
        t = self._stamp('depth', t)
        stamp = t if stamp is None else self._stamp('depth', stamp)
        depth = np.asarray(depth)
        if depth.ndim != 2 or depth.size == 0 or not np.issubdtype(depth.dtype, np.number):
            raise self._reject('depth_image', f'depth image must be a numeric HxW array, got {depth.dtype} '
                                              f'{depth.shape}')
        depth = depth.astype(np.float32)
        self._depth = (t, np.where(np.isfinite(depth) & (depth >= 0) & (depth <= MAX_DEPTH_M), depth, 0.0))
        self._depth_stamp = stamp

    def reset(self) -> None:
        """Forget the action history, the guard's last pad, the override's held keys, the pad map and the damper's
        reversals (new episode)."""
        self.builder.reset()
        self.guard.reset()
        self.walls.reset()
        self.override.reset()
        self.recall.reset()
        self.damper.reset()
        self._mapped_depth = None
        self._walls_depth = None

    # ------------------------------------------------------------- step
    def _fresh(self, stamp: float | None, now: float, timeout: float) -> bool:
        return stamp is not None and abs(now - stamp) <= timeout

    def _clamp(self, v: np.ndarray) -> np.ndarray:
        return clamp_velocity(v, self.cfg.max_speed_mps, self.cfg.max_vertical_mps)

    def pilot_command(self, now: float) -> np.ndarray:
        """The pilot's u at `now`: the latest accepted command if fresh, else zero (never raises)."""
        p = self._pilot
        if p is not None and self._fresh(p[0], now, self.cfg.pilot_timeout_s):
            return p[1].copy()
        return np.zeros(3)

    def fallback(self, now: float) -> PolicyOutput:
        """What to fly when a step cannot run: V = u, clamped (finite by construction; never raises)."""
        try:
            v = self._clamp(self.pilot_command(now))
            if not np.all(np.isfinite(v)):
                v = np.zeros(3)
        except Exception:  # noqa: BLE001 - the last line of defence must not raise
            v = np.zeros(3)
        return PolicyOutput(None, v, 'step failed: relinquished', 'step_error')

    def step(self, now: float) -> PolicyOutput:
        """One control step at time `now` (seconds, same clock as the input stamps); never raises.

        Any exception inside the step (a bad observation, the actor, the history) relinquishes:
        V = u (clamped), reason key ``step_error``, counted in `faults` by exception type and logged.
        """
        try:
            now = float(now)
            if not math.isfinite(now):
                raise ValueError(f'clock reads {now!r}')
            return self._guarded(now, self._step(now))
        except Exception as exc:  # noqa: BLE001 - contract: no exception leaves a control step
            self.faults[type(exc).__name__] += 1
            log.debug('policy step failed (%s: %s): relinquishing', type(exc).__name__, exc)
            out = self.fallback(now)
            out.reason = f'step failed ({type(exc).__name__}: {exc}): relinquished'
            out.fault = type(exc).__name__
            return out

    def _guarded(self, now: float, out: PolicyOutput) -> PolicyOutput:
        """The floor guard on this step's output (needs fresh odometry and depth; else unchanged)."""
        c = self.cfg
        if not (self.guard.cfg.enabled and self._odom is not None and self._fresh(self._odom[0], now, c.odom_timeout_s)
                and self._depth is not None and self._fresh(self._depth[0], now, c.feature_timeout_s)):
            return out
        u = self.pilot_command(now)
        g = self.guard.apply(u, out.agent, out.velocity, self._depth[1], self._odom[1], c.blend_threshold)
        if g.engaged:
            self.guard_engaged += 1
            out = PolicyOutput(g.agent, self._clamp(g.velocity), 'floor guard: descent blocked', 'floor_guard')
        if not self.walls.active:
            return out
        if self._walls_depth != self._depth[0]:
            self.walls.observe(self._depth[1], *self._pose_of_depth(self._odom[1]))
            self._walls_depth = self._depth[0]
        w = self.walls.apply(u, out.agent, out.velocity, self._odom[1], self._attitude)
        if not w.engaged:
            return out
        self.wall_engaged += 1
        return PolicyOutput(w.agent, self._clamp(w.velocity), 'floor guard: approach to a wall stopped', 'wall_guard')

    def _pose_of_depth(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Odometry pose (position, attitude) at the latest depth frame's stamp, looked up once per frame; with no
        pose within depth_pose_match_s of it, the latest (counted in depth_pose_unmatched)."""
        t_depth = self._depth[0]
        if self._depth_pose is None or self._depth_pose[0] != t_depth:
            pose = self._poses.at(self._depth_stamp)
            if pose is None:
                self.depth_pose_unmatched += 1
                pose = (pos, self._attitude)
            self._depth_pose = (t_depth, pose)
        return self._depth_pose[1]

    def _step(self, now: float) -> PolicyOutput:
        c = self.cfg
        u = self.pilot_command(now)
        odom_ok = self._odom is not None and self._fresh(self._odom[0], now, c.odom_timeout_s)
        if not odom_ok:
            return self._relinquish(now, u, 'odometry stale or absent', 'odom_stale')
        _, pos, vel = self._odom
        vel_actor = (quat_to_matrix(self._attitude) @ vel
                     if c.actor_velocity == 'odom' and self._attitude is not None else vel)
        if self.mode is Condition.ORACLE:
            if self._goal is None:
                return self._relinquish(now, u, 'goal absent', 'goal_absent')
            feature = oracle_feature(self._goal, pos)
        else:
            if self._feature is None or not self._fresh(self._feature[0], now, c.feature_timeout_s):
                return self._relinquish(now, u, f'{self.mode.value} input stale or absent', 'feature_stale')
            feature = self._feature[1]
        if self.mode is Condition.END_TO_END:
            vec = self.builder.build(now, np.zeros(0), vel_actor, pos[2], u)
            obs = np.concatenate([feature, vec]).astype(np.float32)
        else:
            obs = self.builder.build(now, feature, vel_actor, pos[2], u, pos)
        with torch.no_grad():
            raw = self.actor(torch.as_tensor(obs).unsqueeze(0))[0].numpy().astype(float)
        if not np.all(np.isfinite(raw)):
            self.rejected += 1
            return self._relinquish(now, u, 'actor output not finite (rejected)', 'actor_nonfinite')
        a = scale_action(raw, self.max_speed)
        a_d = self.damper.apply(now, u, a, vel, pos, [m.xyz for m in self.recall.map.pads], self.max_speed)
        damped = a_d is not None
        if damped:
            a = a_d
        depth = self._mapped(now, pos)
        mean_u = self.builder.history.means(now)[0]
        # the override reads the depth image through the floor guard's surface test (none with the guard off,
        # as evaluate's env flies it: its altitude stands in)
        surface = (None if not self.guard.cfg.enabled or self._depth is None
                   or not self._fresh(self._depth[0], now, c.feature_timeout_s)
                   else lambda: self.guard.surface_below(self._depth[1], pos))
        a_o = self.override.apply(now, u, mean_u, float(pos[2]), self.max_speed, vel, surface, pos)
        self.spot_kept += int(self.override.kept)
        if a_o is not None:
            self.override_engaged += 1
            self.persist_engaged += int(self.override.mode == 'persistent')
            self.climb_engaged += int(self.override.mode == 'climb')
            self.long_engaged += int(self.override.mode == 'long')
            v = self._clamp(blend(u, a_o, c.blend_threshold))
            self.builder.record(now, u, a_o)            # the action applied, as evaluate's env records it
            return PolicyOutput(a_o, v, _OVERRIDE_REASONS.get(self.override.mode, _OVERRIDE_REASONS['held_key']),
                                'pilot_override')
        a_r = None if depth is None else self.recall.apply(u, mean_u, a, depth, pos, self._attitude, self.max_speed)
        if a_r is not None:
            self.recall_engaged += 1
            self.touchdown_engaged += int(self.recall.mode == 'touchdown')
            self.scout_engaged += int(self.recall.mode == 'scout')
            self.builder.record(now, u, a_r)
            return PolicyOutput(a_r, self._clamp(blend(u, a_r, c.blend_threshold)),
                                _RECALL_REASONS.get(self.recall.mode, _RECALL_REASONS['recall']), 'pad_recall')
        v = self._clamp(blend(u, a, c.blend_threshold))
        self.builder.record(now, u, a)
        if damped:
            self.damper_engaged += 1
            return PolicyOutput(a, v, 'oscillation damper: damping the pilot\'s oscillation', 'oscillation_damper')
        if np.linalg.norm(a) > c.blend_threshold:
            return PolicyOutput(a, v, 'assisting', 'assisting')
        return PolicyOutput(a, v, 'relinquished', 'small_action')

    def _mapped(self, now: float, pos: np.ndarray) -> np.ndarray | None:
        """The fresh depth image for the pad recall, after adding it to the pad map once; None: none fresh, or off."""
        if not self.recall.cfg.enabled or self._depth is None or not self._fresh(self._depth[0], now,
                                                                                  self.cfg.feature_timeout_s):
            return None
        t_depth, depth = self._depth
        if self._mapped_depth != t_depth:
            self.recall.observe(depth, *self._pose_of_depth(pos))
            self._mapped_depth = t_depth
        return depth

    def _relinquish(self, now: float, u: np.ndarray, reason: str, key: str) -> PolicyOutput:
        self.builder.record(now, u, np.zeros(3))
        return PolicyOutput(None, self._clamp(u), reason, key)
