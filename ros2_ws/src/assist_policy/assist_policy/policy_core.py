"""Pure policy core behind policy_node: inputs with timestamps -> agent action a and blended V.

Safety rules (ARCHITECTURE.md, "Timing and safety rules"):
* pilot command older than pilot_timeout_s (or never received) -> u = 0;
* scene feature (latent / goal / image) or odometry stale or absent -> relinquish: no a, V = u;
* non-finite actor output is rejected (counted, V = u), never reaches V;
* V is clamped to max_speed_mps (horizontal norm) and max_vertical_mps.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from assist_sim.shipped import shipped_model_path

from .actions import scale_action
from .blending import DEFAULT_THRESHOLD, blend
from .observation import Condition, ObservationBuilder, image_feature, oracle_feature
from .td3 import load_actor

log = logging.getLogger(__name__)


def default_model_path(mode: str) -> Path:
    """Shipped actor for a mode, td3_<mode>_actor.pt: $ASSIST_MODELS_DIR, share/assist_policy/models or the repo's models/."""
    return shipped_model_path('assist_policy', f'td3_{Condition(mode).value}_actor.pt')


@dataclass
class PolicyCoreConfig:
    """Settings of the policy core (policy_node parameters map 1:1)."""

    mode: str = 'latent'
    blend_threshold: float = DEFAULT_THRESHOLD
    pilot_timeout_s: float = 0.5
    feature_timeout_s: float = 0.5
    odom_timeout_s: float = 0.5
    max_speed_mps: float = 1.5
    max_vertical_mps: float = 1.0


@dataclass
class PolicyOutput:
    """Result of one policy step: agent action (None when relinquished), blended V, reason."""

    agent: np.ndarray | None
    velocity: np.ndarray
    reason: str


class PolicyCore:
    """Holds the latest inputs, builds observations, runs the actor, applies the blending rule."""

    def __init__(self, actor_path: str | Path, cfg: PolicyCoreConfig | None = None):
        self.cfg = cfg or PolicyCoreConfig()
        self.mode = Condition(self.cfg.mode)
        self.actor, self.meta = load_actor(actor_path)
        trained = self.meta.get('condition')
        if trained is not None and trained != self.mode.value:
            raise ValueError(f'{actor_path}: actor was trained for {trained!r}, not mode {self.mode.value!r}')
        self.max_speed = tuple(self.meta.get('max_speed', (1.0, 1.0, 0.6)))
        self.builder = ObservationBuilder(self.mode, int(self.meta.get('latent_dim', 0)),
                                          float(self.meta.get('window_s', 1.0)))
        if self.builder.dim != int(self.meta['vec_dim']):
            raise ValueError(f'{actor_path}: actor expects {self.meta["vec_dim"]} inputs, the {self.mode.value} '
                             f'observation has {self.builder.dim}')
        self._pilot: tuple[float, np.ndarray] | None = None
        self._odom: tuple[float, np.ndarray, np.ndarray] | None = None
        self._feature: tuple[float, np.ndarray] | None = None
        self._goal: np.ndarray | None = None
        self.rejected = 0

    # ------------------------------------------------------------- inputs
    def set_pilot(self, t: float, u: np.ndarray) -> None:
        """Latest pilot command (m/s, base_link); ValueError when non-finite."""
        u = np.asarray(u, dtype=float).reshape(3)
        if not np.all(np.isfinite(u)):
            raise ValueError('pilot command not finite')
        self._pilot = (t, u)

    def set_odom(self, t: float, position: np.ndarray, velocity: np.ndarray) -> None:
        """Latest odometry (odom ENU); ValueError when non-finite."""
        p = np.asarray(position, dtype=float).reshape(3)
        v = np.asarray(velocity, dtype=float).reshape(3)
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(v))):
            raise ValueError('odometry not finite')
        self._odom = (t, p, v)

    def set_latent(self, t: float, mu: np.ndarray) -> None:
        """Latest encoder mean (latent mode); ValueError on wrong size or non-finite values."""
        mu = np.asarray(mu, dtype=float).reshape(-1)
        if mu.size != self.builder.latent_dim:
            raise ValueError(f'latent has {mu.size} values, the actor expects {self.builder.latent_dim}')
        if not np.all(np.isfinite(mu)):
            raise ValueError('latent not finite')
        self._feature = (t, mu)

    def set_goal(self, goal: np.ndarray) -> None:
        """True goal (oracle mode, simulation only)."""
        g = np.asarray(goal, dtype=float).reshape(3)
        if not np.all(np.isfinite(g)):
            raise ValueError('goal not finite')
        self._goal = g

    def set_image(self, t: float, rgb: np.ndarray, depth: np.ndarray) -> None:
        """Latest RGB-D frame (end-to-end mode)."""
        self._feature = (t, image_feature(rgb, depth).reshape(-1))

    def reset(self) -> None:
        """Forget the action history (new episode)."""
        self.builder.reset()

    # ------------------------------------------------------------- step
    def _fresh(self, stamp: float | None, now: float, timeout: float) -> bool:
        return stamp is not None and abs(now - stamp) <= timeout

    def _clamp(self, v: np.ndarray) -> np.ndarray:
        v = v.copy()
        sp = float(np.hypot(v[0], v[1]))
        if sp > self.cfg.max_speed_mps:
            v[:2] *= self.cfg.max_speed_mps / sp
        v[2] = float(np.clip(v[2], -self.cfg.max_vertical_mps, self.cfg.max_vertical_mps))
        return v

    def step(self, now: float) -> PolicyOutput:
        """One control step at time `now` (seconds, same clock as the input stamps)."""
        c = self.cfg
        u = np.zeros(3)
        if self._pilot is not None and self._fresh(self._pilot[0], now, c.pilot_timeout_s):
            u = self._pilot[1]
        odom_ok = self._odom is not None and self._fresh(self._odom[0], now, c.odom_timeout_s)
        if not odom_ok:
            return self._relinquish(now, u, 'odometry stale or absent')
        _, pos, vel = self._odom
        if self.mode is Condition.ORACLE:
            if self._goal is None:
                return self._relinquish(now, u, 'goal absent')
            feature = oracle_feature(self._goal, pos)
        else:
            if self._feature is None or not self._fresh(self._feature[0], now, c.feature_timeout_s):
                return self._relinquish(now, u, f'{self.mode.value} input stale or absent')
            feature = self._feature[1]
        if self.mode is Condition.END_TO_END:
            vec = self.builder.build(now, np.zeros(0), vel, pos[2], u)
            obs = np.concatenate([feature, vec]).astype(np.float32)
        else:
            obs = self.builder.build(now, feature, vel, pos[2], u)
        with torch.no_grad():
            raw = self.actor(torch.as_tensor(obs).unsqueeze(0))[0].numpy().astype(float)
        if not np.all(np.isfinite(raw)):
            self.rejected += 1
            return self._relinquish(now, u, 'actor output not finite (rejected)')
        a = scale_action(raw, self.max_speed)
        v = self._clamp(blend(u, a, c.blend_threshold))
        self.builder.record(now, u, a)
        return PolicyOutput(a, v, 'assisting' if np.linalg.norm(a) > c.blend_threshold else 'relinquished')

    def _relinquish(self, now: float, u: np.ndarray, reason: str) -> PolicyOutput:
        self.builder.record(now, u, np.zeros(3))
        return PolicyOutput(None, self._clamp(u), reason)
