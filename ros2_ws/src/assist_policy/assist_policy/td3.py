"""Compact TD3 (Fujimoto et al. 2018): twin critics, target policy smoothing, delayed actor updates.

Paper hyper-parameters ("TD3 implementation"): actor and critic learning rate 1e-3, discount 0.99,
batch 100, target update rate tau 0.01. Exploration is an Ornstein-Uhlenbeck process decayed over
successive landings. The replay buffer can be saved and preloaded from earlier runs (off-policy).

The actor class defined here is the one used by training, evaluation and the policy node.
"""
from __future__ import annotations

import copy
import logging
import math
import pickle
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from assist_sim.atomic import atomic_path

from .observation import IMAGE_SHAPE, MAX_FEATURE_LAG_S, MAX_FEATURE_LAGS, Condition, vector_dim

log = logging.getLogger(__name__)


@dataclass
class TD3Config:
    """TD3 hyper-parameters (defaults: the paper's where it gives them, Fujimoto's otherwise)."""

    actor_lr: float = 1e-3
    critic_lr: float = 1e-3
    gamma: float = 0.99
    batch_size: int = 100
    tau: float = 0.01
    policy_noise: float = 0.2       # target policy smoothing std (raw action units)
    noise_clip: float = 0.5
    policy_delay: int = 2           # actor + target update every this many critic updates
    hidden: tuple[int, ...] = (256, 256)
    image_channels: tuple[int, ...] = (32, 32, 64, 64)  # end-to-end conv stack (stride 2 each)


class ImageFeatures(nn.Module):
    """Convolutional front end for the end-to-end condition: (4, 64, 64) -> flat features."""

    def __init__(self, channels: Sequence[int] = (32, 32, 64, 64), in_shape=IMAGE_SHAPE):
        super().__init__()
        layers: list[nn.Module] = []
        c_in = in_shape[0]
        for c in channels:
            layers += [nn.Conv2d(c_in, c, 3, stride=2, padding=1), nn.ReLU()]
            c_in = c
        self.net = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():
            self.out_dim = int(self.net(torch.zeros(1, *in_shape)).shape[1])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Image batch (B, 4, 64, 64) -> (B, out_dim)."""
        return self.net(x)


class _Trunk(nn.Module):
    """Splits a flat observation into (image, vector) when an image front end is used."""

    def __init__(self, vec_dim: int, image: bool, channels: Sequence[int]):
        super().__init__()
        self.vec_dim = vec_dim
        self.image = ImageFeatures(channels) if image else None
        self.img_size = int(np.prod(IMAGE_SHAPE)) if image else 0
        self.out_dim = vec_dim + (self.image.out_dim if image else 0)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if self.image is None:
            return obs
        img = obs[:, :self.img_size].reshape(-1, *IMAGE_SHAPE)
        return torch.cat([self.image(img), obs[:, self.img_size:]], dim=1)


def _mlp(in_dim: int, hidden: Sequence[int], out_dim: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(in_dim, h), nn.ReLU()]
        in_dim = h
    layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


class Actor(nn.Module):
    """Deterministic policy: observation -> raw action in [-1, 1]^act_dim (tanh)."""

    def __init__(self, vec_dim: int, act_dim: int = 3, hidden: Sequence[int] = (256, 256),
                 image: bool = False, image_channels: Sequence[int] = (32, 32, 64, 64)):
        super().__init__()
        self.trunk = _Trunk(vec_dim, image, image_channels)
        self.head = _mlp(self.trunk.out_dim, hidden, act_dim)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Batch of observations -> batch of raw actions."""
        return torch.tanh(self.head(self.trunk(obs)))


class Critic(nn.Module):
    """Twin Q networks Q1, Q2(observation, action)."""

    def __init__(self, vec_dim: int, act_dim: int = 3, hidden: Sequence[int] = (256, 256),
                 image: bool = False, image_channels: Sequence[int] = (32, 32, 64, 64)):
        super().__init__()
        self.trunk1 = _Trunk(vec_dim, image, image_channels)
        self.trunk2 = _Trunk(vec_dim, image, image_channels)
        self.q1 = _mlp(self.trunk1.out_dim + act_dim, hidden, 1)
        self.q2 = _mlp(self.trunk2.out_dim + act_dim, hidden, 1)

    def forward(self, obs: torch.Tensor, act: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Both Q estimates, each (B, 1)."""
        return (self.q1(torch.cat([self.trunk1(obs), act], 1)),
                self.q2(torch.cat([self.trunk2(obs), act], 1)))

    def q1_only(self, obs: torch.Tensor, act: torch.Tensor) -> torch.Tensor:
        """Q1 (used for the actor loss)."""
        return self.q1(torch.cat([self.trunk1(obs), act], 1))


class OUNoise:
    """Ornstein-Uhlenbeck exploration noise whose scale decays after every landing."""

    def __init__(self, dim: int = 3, theta: float = 0.15, sigma: float = 0.3, sigma_min: float = 0.05,
                 decay: float = 0.998, dt: float = 1.0, rng: np.random.Generator | None = None):
        self.dim, self.theta, self.sigma0, self.sigma_min = dim, theta, sigma, sigma_min
        self.decay, self.dt = decay, dt
        self.rng = rng or np.random.default_rng()
        self.landings = 0
        self.state = np.zeros(dim)

    @property
    def sigma(self) -> float:
        """Current noise scale: sigma0 * decay**landings, floored at sigma_min."""
        return max(self.sigma_min, self.sigma0 * self.decay ** self.landings)

    def reset(self) -> None:
        """Restart the process at zero (start of an episode)."""
        self.state = np.zeros(self.dim)

    def landed(self) -> None:
        """Count one finished landing (decays sigma)."""
        self.landings += 1

    def sample(self) -> np.ndarray:
        """Next noise vector."""
        self.state = (self.state - self.theta * self.state * self.dt
                      + self.sigma * np.sqrt(self.dt) * self.rng.standard_normal(self.dim))
        return self.state.copy()


class ReplayBuffer:
    """Fixed-capacity ring buffer of (obs, act, reward, next_obs, done) in numpy, saveable to .npz."""

    def __init__(self, obs_dim: int, act_dim: int = 3, capacity: int = 1_000_000,
                 obs_dtype: Any = np.float32):
        self.capacity, self.obs_dim, self.act_dim = int(capacity), obs_dim, act_dim
        self.obs = np.zeros((self.capacity, obs_dim), dtype=obs_dtype)
        self.next_obs = np.zeros((self.capacity, obs_dim), dtype=obs_dtype)
        self.act = np.zeros((self.capacity, act_dim), dtype=np.float32)
        self.rew = np.zeros((self.capacity, 1), dtype=np.float32)
        self.done = np.zeros((self.capacity, 1), dtype=np.float32)
        self.ptr = 0
        self.size = 0

    def add(self, obs, act, rew: float, next_obs, done: bool) -> None:
        """Store one transition (done = terminal, not a time-limit truncation)."""
        i = self.ptr
        self.obs[i], self.act[i], self.rew[i, 0] = obs, act, rew
        self.next_obs[i], self.done[i, 0] = next_obs, float(done)
        self.ptr = (self.ptr + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, batch: int, rng: np.random.Generator) -> tuple[torch.Tensor, ...]:
        """Uniform random batch as float32 tensors."""
        idx = rng.integers(0, self.size, size=batch)
        return tuple(torch.as_tensor(np.asarray(x[idx], dtype=np.float32))
                     for x in (self.obs, self.act, self.rew, self.next_obs, self.done))

    def save(self, path: str | Path) -> None:
        """Write the filled part to an .npz file (written atomically)."""
        n = self.size
        order = np.arange(n) if n < self.capacity else (np.arange(n) + self.ptr) % self.capacity
        with atomic_path(path) as tmp:
            np.savez(tmp, obs=self.obs[order], act=self.act[order], rew=self.rew[order],
                     next_obs=self.next_obs[order], done=self.done[order])

    def load(self, path: str | Path) -> int:
        """Append the transitions of a saved buffer (preload); returns how many were added."""
        with np.load(path, allow_pickle=False) as data:
            obs = data['obs']
            if obs.shape[1] != self.obs_dim:
                raise ValueError(f'{path}: observation size {obs.shape[1]} != {self.obs_dim}')
            arrays = (obs, data['act'], data['rew'], data['next_obs'], data['done'])  # each read once
        n = obs.shape[0]
        if n > self.capacity:             # only the newest `capacity` transitions fit
            arrays = tuple(a[n - self.capacity:] for a in arrays)
        k = arrays[0].shape[0]
        idx = (self.ptr + np.arange(k)) % self.capacity
        for dst, src in zip((self.obs, self.act, self.rew, self.next_obs, self.done), arrays):
            dst[idx] = src
        self.ptr = int((self.ptr + k) % self.capacity)
        self.size = min(self.size + k, self.capacity)
        return n


class TD3:
    """TD3 agent: act(), update(), state_dict()/load_state_dict() for checkpoints."""

    def __init__(self, vec_dim: int, act_dim: int = 3, cfg: TD3Config | None = None,
                 image: bool = False, seed: int = 0):
        self.cfg = cfg or TD3Config()
        torch.manual_seed(seed)
        kw = dict(hidden=self.cfg.hidden, image=image, image_channels=self.cfg.image_channels)
        self.actor = Actor(vec_dim, act_dim, **kw)
        self.critic = Critic(vec_dim, act_dim, **kw)
        self.actor_target = copy.deepcopy(self.actor)
        self.critic_target = copy.deepcopy(self.critic)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=self.cfg.actor_lr)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=self.cfg.critic_lr)
        self.updates = 0
        self.rng = np.random.default_rng(seed)
        self.meta = {'vec_dim': int(vec_dim), 'act_dim': int(act_dim), 'image': bool(image),
                     'hidden': list(self.cfg.hidden), 'image_channels': list(self.cfg.image_channels)}

    @torch.no_grad()
    def act(self, obs: np.ndarray) -> np.ndarray:
        """Deterministic raw action in [-1, 1] for one observation."""
        x = torch.as_tensor(np.asarray(obs, dtype=np.float32)).unsqueeze(0)
        return self.actor(x)[0].numpy().astype(float)

    def update(self, buffer: ReplayBuffer, train_actor: bool = True,
               demos: tuple[np.ndarray, np.ndarray] | None = None, bc_alpha: float = 0.0) -> dict[str, float]:
        """One critic update (and, every policy_delay, one actor + target update).

        train_actor=False: critic warm-up on preloaded data (targets still track both networks).
        demos=(obs, raw actions) with bc_alpha > 0: TD3+BC actor loss (Fujimoto & Gu 2021),
        -bc_alpha / mean|Q| * Q(s, pi(s)) + mean (pi(s_d) - a_d)^2, which keeps the policy near the
        demonstrations where the critic has no evidence for something better.
        """
        c = self.cfg
        obs, act, rew, nxt, done = buffer.sample(c.batch_size, self.rng)
        with torch.no_grad():
            noise = (torch.randn_like(act) * c.policy_noise).clamp(-c.noise_clip, c.noise_clip)
            nxt_act = (self.actor_target(nxt) + noise).clamp(-1.0, 1.0)
            q1t, q2t = self.critic_target(nxt, nxt_act)
            target = rew + c.gamma * (1.0 - done) * torch.min(q1t, q2t)
        q1, q2 = self.critic(obs, act)
        critic_loss = F.mse_loss(q1, target) + F.mse_loss(q2, target)
        self.critic_opt.zero_grad()
        critic_loss.backward()
        self.critic_opt.step()
        self.updates += 1
        out = {'critic_loss': float(critic_loss.detach()), 'q_mean': float(q1.detach().mean())}
        if self.updates % c.policy_delay == 0:
            if train_actor:
                q = self.critic.q1_only(obs, self.actor(obs))
                if demos is not None and bc_alpha > 0:
                    idx = self.rng.integers(0, len(demos[0]), size=c.batch_size)
                    d_obs = torch.as_tensor(np.asarray(demos[0][idx], dtype=np.float32))
                    d_act = torch.as_tensor(np.asarray(demos[1][idx], dtype=np.float32))
                    lam = bc_alpha / q.abs().mean().detach().clamp(min=1e-3)
                    bc = F.mse_loss(self.actor(d_obs), d_act)
                    actor_loss = -lam * q.mean() + bc
                    out['bc_loss'] = float(bc.detach())
                else:
                    actor_loss = -q.mean()
                self.actor_opt.zero_grad()
                actor_loss.backward()
                self.actor_opt.step()
                out['actor_loss'] = float(actor_loss.detach())
            with torch.no_grad():
                for net, tgt in ((self.actor, self.actor_target), (self.critic, self.critic_target)):
                    for p, pt in zip(net.parameters(), tgt.parameters()):
                        pt.mul_(1.0 - c.tau).add_(c.tau * p)
        return out

    def behaviour_clone(self, obs: np.ndarray, act: np.ndarray, steps: int, batch: int = 256) -> float:
        """Supervised actor pre-training on (obs, raw action) demonstrations; returns the final MSE."""
        obs_t = torch.as_tensor(np.asarray(obs, dtype=np.float32))
        act_t = torch.as_tensor(np.asarray(act, dtype=np.float32)).clamp(-0.999, 0.999)
        loss = torch.zeros(())
        for _ in range(steps):
            idx = torch.as_tensor(self.rng.integers(0, len(obs_t), size=batch))
            loss = F.mse_loss(self.actor(obs_t[idx]), act_t[idx])
            self.actor_opt.zero_grad()
            loss.backward()
            self.actor_opt.step()
        self.actor_target.load_state_dict(self.actor.state_dict())
        return float(loss.detach())

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume training (tensors and plain values only)."""
        return {'actor': self.actor.state_dict(), 'critic': self.critic.state_dict(),
                'actor_target': self.actor_target.state_dict(),
                'critic_target': self.critic_target.state_dict(),
                'actor_opt': self.actor_opt.state_dict(), 'critic_opt': self.critic_opt.state_dict(),
                'updates': self.updates, 'meta': self.meta, 'cfg': asdict(self.cfg)}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Restore from state_dict()."""
        for name in ('actor', 'critic', 'actor_target', 'critic_target', 'actor_opt', 'critic_opt'):
            getattr(self, name).load_state_dict(sd[name])
        self.updates = int(sd['updates'])


def save_actor(actor: Actor, meta: dict[str, Any], path: str | Path) -> None:
    """Write a shippable actor file: {'actor': state_dict, 'meta': plain dict} (atomic, fsynced)."""
    with atomic_path(path) as tmp:
        torch.save({'actor': actor.state_dict(), 'meta': dict(meta)}, tmp)


META_DEFAULTS = {'act_dim': 3, 'image': False, 'image_channels': [32, 32, 64, 64], 'latent_dim': 0,
                 'max_speed': [1.0, 1.0, 0.6], 'window_s': 1.0,
                 'feature_lags_s': [], 'memory_displacement': False}   # older actor files may lack these
# (no lags, no displacement: the original layout)
MAX_ACTION_SPEED = 20.0   # m/s; an actor file claiming faster assistant actions is not one of ours


def _int(meta: dict, key: str, lo: int, hi: int) -> int:
    v = meta[key]
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise ValueError(f'metadata {key!r} must be an integer in [{lo}, {hi}], got {v!r}')
    return v


def _float(v: Any, what: str, lo: float, hi: float, lo_open: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f'metadata {what} must be a number, got {v!r}')
    v = float(v)
    if not math.isfinite(v) or v > hi or (v <= lo if lo_open else v < lo):
        raise ValueError(f'metadata {what} must be finite and in {"(" if lo_open else "["}{lo:g}, {hi:g}], '
                         f'got {v!r}')
    return v


def _int_list(meta: dict, key: str, min_len: int, max_len: int, hi: int) -> list[int]:
    v = meta[key]
    if (not isinstance(v, (list, tuple)) or not min_len <= len(v) <= max_len
            or any(isinstance(x, bool) or not isinstance(x, int) or not 1 <= x <= hi for x in v)):
        raise ValueError(f'metadata {key!r} must be a list of {min_len}-{max_len} integers in [1, {hi}], '
                         f'got {v!r}')
    return [int(x) for x in v]


def validate_actor_meta(meta: Any) -> dict[str, Any]:
    """Actor file metadata with defaults filled in; ValueError (one line) on a wrong type, length or range."""
    if not isinstance(meta, dict):
        raise ValueError(f"metadata must be a dict, got {type(meta).__name__}")
    meta = {**META_DEFAULTS, **meta}
    for key in ('vec_dim', 'hidden'):
        if key not in meta:
            raise ValueError(f'metadata lacks {key!r}')
    meta['vec_dim'] = _int(meta, 'vec_dim', 1, 100_000)
    meta['act_dim'] = _int(meta, 'act_dim', 3, 3)
    meta['latent_dim'] = _int(meta, 'latent_dim', 0, 100_000)
    if not isinstance(meta['image'], bool):
        raise ValueError(f"metadata 'image' must be true or false, got {meta['image']!r}")
    meta['hidden'] = _int_list(meta, 'hidden', 1, 16, 8192)
    meta['image_channels'] = _int_list(meta, 'image_channels', 1, 16, 4096)
    ms = meta['max_speed']
    if not isinstance(ms, (list, tuple)) or len(ms) != 3:
        raise ValueError(f"metadata 'max_speed' must be 3 speeds (x, y, z m/s), got {ms!r}")
    meta['max_speed'] = [_float(v, f'max_speed[{i}]', 0.0, MAX_ACTION_SPEED, lo_open=True)
                         for i, v in enumerate(ms)]
    meta['window_s'] = _float(meta['window_s'], "'window_s'", 0.0, 3600.0, lo_open=True)
    lags = meta['feature_lags_s']
    if not isinstance(lags, (list, tuple)) or len(lags) > MAX_FEATURE_LAGS:
        raise ValueError(f"metadata 'feature_lags_s' must be a list of at most {MAX_FEATURE_LAGS} lags (s), got {lags!r}")
    meta['feature_lags_s'] = [_float(v, f'feature_lags_s[{i}]', 0.0, MAX_FEATURE_LAG_S, lo_open=True)
                              for i, v in enumerate(lags)]
    if 'blend_threshold' in meta:
        meta['blend_threshold'] = _float(meta['blend_threshold'], "'blend_threshold'", 0.0, MAX_ACTION_SPEED)
    cond = meta.get('condition')
    if cond is not None and (not isinstance(cond, str) or cond not in {c.value for c in Condition}):
        raise ValueError(f"metadata 'condition' must be one of latent, oracle, end_to_end; got {cond!r}")
    if cond == 'latent' and meta['latent_dim'] < 1:
        raise ValueError("metadata 'latent_dim' must be >= 1 for a latent actor")
    if meta['feature_lags_s'] and (cond is None or cond == 'end_to_end'):
        raise ValueError("metadata 'feature_lags_s' needs a latent or oracle actor")
    if not isinstance(meta['memory_displacement'], bool):
        raise ValueError(f"metadata 'memory_displacement' must be true or false, got {meta['memory_displacement']!r}")
    if meta['memory_displacement'] and not meta['feature_lags_s']:
        raise ValueError("metadata 'memory_displacement' needs 'feature_lags_s'")
    expected = (vector_dim(cond, meta['latent_dim'], len(meta['feature_lags_s']), meta['memory_displacement'])
                if cond is not None else None)
    if expected is not None and expected != meta['vec_dim']:
        raise ValueError(f"metadata 'vec_dim' {meta['vec_dim']} does not fit a {cond} actor "
                         f"(latent_dim {meta['latent_dim']}: {expected})")
    if cond is not None and (cond == 'end_to_end') != meta['image']:
        raise ValueError(f"metadata 'image' {meta['image']} does not fit a {cond} actor")
    return meta


def _load_error(exc: BaseException) -> str:
    """One line saying why torch.load refused a file (no traceback, no advice to drop weights_only)."""
    text = str(exc)
    for line in text.splitlines():
        if 'WeightsUnpickler error' in line:   # e.g. "Unsupported global: GLOBAL os.system"
            return line.strip()
    if isinstance(exc, pickle.UnpicklingError) or 'weights_only' in text:
        return f'{type(exc).__name__}: holds objects other than tensors and plain values'
    first = text.strip().splitlines()[0] if text.strip() else ''
    return f'{type(exc).__name__}: {first}'[:200]


def load_actor(path: str | Path) -> tuple[Actor, dict[str, Any]]:
    """Load an actor file (weights_only=True) and validate it; ValueError with the path (one line).

    Checked: the file is a plain {'actor', 'meta'} dict, the metadata's types, lengths and ranges
    (``validate_actor_meta``), the weights match the architecture the metadata names, and every
    weight is finite. The returned metadata has defaults filled in.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f'actor file not found: {path}')
    try:
        blob = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as exc:  # torch raises many types (pickle, zip, runtime, EOF) for bad files
        raise ValueError(f'cannot load actor from {path}: {_load_error(exc)}') from None
    try:
        if not isinstance(blob, dict) or not isinstance(blob.get('actor'), dict):
            raise ValueError("not an actor file (no 'actor' weights)")
        meta = validate_actor_meta(blob.get('meta'))
        with torch.device('meta'):    # shapes only: metadata cannot make us allocate a huge network
            actor = Actor(meta['vec_dim'], meta['act_dim'], hidden=tuple(meta['hidden']), image=meta['image'],
                          image_channels=tuple(meta['image_channels']))
        try:
            actor.load_state_dict(blob['actor'], assign=True)
        except (RuntimeError, TypeError, KeyError, AttributeError) as exc:
            raise ValueError('weights do not match the architecture in its metadata: '
                             + str(exc).strip().splitlines()[0][:200]) from None
        for name, t in actor.state_dict().items():
            if t.is_floating_point() and not bool(torch.isfinite(t).all()):
                raise ValueError(f'non-finite values in weights {name}')
    except ValueError as exc:
        raise ValueError(f'bad actor file {path}: {exc}') from None
    actor.eval()
    return actor, meta
