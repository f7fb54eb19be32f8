"""Compact TD3 (Fujimoto et al. 2018): twin critics, target policy smoothing, delayed actor updates.

Paper hyper-parameters ("TD3 implementation"): actor and critic learning rate 1e-3, discount 0.99,
batch 100, target update rate tau 0.01. Exploration is an Ornstein-Uhlenbeck process decayed over
successive landings. The replay buffer can be saved and preloaded from earlier runs (off-policy).
With ``privileged_dim`` the critic is asymmetric (as in Backman et al. 2023 and Pinto et al. 2018's asymmetric
actor-critic): it also sees what only the simulator knows (``env.privileged``), the actor still only its observation.

The actor network and its file format live in ``actor`` (what a vehicle loads, without this training code).
"""
from __future__ import annotations

import copy
import logging
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from assist_common.atomic import atomic_path

from assist_policy.actor import GOAL_LOG_STD
from assist_policy.actor import (MAX_ACTION_SPEED, META_DEFAULTS, Actor, ImageFeatures, _mlp, _Trunk, load_actor,  # noqa: F401
                    save_actor, validate_actor_meta)

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
    history_hidden: int = 64        # GRU units over the observation's history window (when it has one)
    goal_head: bool = False         # the actor also estimates the goal (trained in behaviour cloning)
    goal_weight: float = 0.1        # weight of the goal head's Gaussian negative log-likelihood in cloning
    # asymmetric critic: it also sees this many privileged values stored after each observation (env.privileged:
    # the true goal, the pilot's estimate and parameters), the actor never; 0 = the paper's critic. The first three
    # are the goal head's label: with a goal head the TD3 actor loss keeps it trained on them (goal_weight)
    privileged_dim: int = 0


def goal_nll(head: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
    """Mean Gaussian negative log-likelihood of `goal` (B, 3) under the goal head's output (B, 4: mean, log std
    shared by the three axes, clamped to actor.GOAL_LOG_STD), constants dropped."""
    log_std = head[:, 3:4].clamp(*GOAL_LOG_STD)
    return (0.5 * ((goal - head[:, :3]) / log_std.exp()) ** 2 + log_std).sum(dim=1).mean()


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
    """Fixed-capacity ring buffer of (obs, act, reward, next_obs, done) in numpy, saveable to .npz.

    With `priv_dim` > 0 (an asymmetric critic) each stored observation is followed by that many privileged values:
    ``add``/``extend`` take them beside the observations, ``sample`` returns the joined rows and ``obs_dim`` counts
    both."""

    def __init__(self, obs_dim: int, act_dim: int = 3, capacity: int = 1_000_000,
                 obs_dtype: Any = np.float32, priv_dim: int = 0):
        self.priv_dim = int(priv_dim)
        obs_dim = int(obs_dim) + self.priv_dim
        self.capacity, self.obs_dim, self.act_dim = int(capacity), obs_dim, act_dim
        self.obs = np.zeros((self.capacity, obs_dim), dtype=obs_dtype)
        self.next_obs = np.zeros((self.capacity, obs_dim), dtype=obs_dtype)
        self.act = np.zeros((self.capacity, act_dim), dtype=np.float32)
        self.rew = np.zeros((self.capacity, 1), dtype=np.float32)
        self.done = np.zeros((self.capacity, 1), dtype=np.float32)
        self.ptr = 0
        self.size = 0

    def _joined(self, obs, priv, what: str) -> np.ndarray:
        """`obs` with its privileged values after it (rows or one observation); ValueError when they are missing
        or this buffer keeps none."""
        if self.priv_dim == 0:
            if priv is not None:
                raise ValueError(f'{what}: privileged values given to a buffer that keeps none')
            return obs
        if priv is None:
            raise ValueError(f'{what}: this buffer keeps {self.priv_dim} privileged values per observation')
        priv = np.asarray(priv, dtype=np.float32)
        if priv.shape[-1] != self.priv_dim:
            raise ValueError(f'{what}: {priv.shape[-1]} privileged values, expected {self.priv_dim}')
        return np.concatenate([np.asarray(obs, dtype=np.float32), priv], axis=-1)

    def add(self, obs, act, rew: float, next_obs, done: bool, priv=None, next_priv=None) -> None:
        """Store one transition (done = terminal, not a time-limit truncation); `priv`/`next_priv` are the
        privileged values of each observation when the buffer keeps them."""
        obs, next_obs = self._joined(obs, priv, 'add'), self._joined(next_obs, next_priv, 'add')
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
                extra = f' ({self.priv_dim} of them privileged values)' if self.priv_dim else ''
                raise ValueError(f'{path}: observation size {obs.shape[1]} != {self.obs_dim}{extra}')
            arrays = (obs, data['act'], data['rew'], data['next_obs'], data['done'])  # each read once
        self._append(*arrays)
        return obs.shape[0]

    def extend(self, obs, act, rew, next_obs, done, priv=None, next_priv=None) -> None:
        """Append transitions given as arrays (one row each; rew and done may be flat; `priv`/`next_priv` the
        observations' privileged values when the buffer keeps them); when more than `capacity` come, only the
        newest fit."""
        obs, next_obs = self._joined(obs, priv, 'extend'), self._joined(next_obs, next_priv, 'extend')
        self._append(obs, act, rew, next_obs, done)

    def _append(self, obs, act, rew, next_obs, done) -> None:
        """Append stored rows (observations with their privileged values already joined)."""
        arrays = [np.asarray(a) for a in (obs, act, rew, next_obs, done)]
        arrays[2], arrays[4] = arrays[2].reshape(-1, 1), arrays[4].reshape(-1, 1)
        n = arrays[0].shape[0]
        if any(a.shape[0] != n for a in arrays):
            raise ValueError(f'transition arrays of different lengths: {[a.shape[0] for a in arrays]}')
        if n > self.capacity:             # only the newest `capacity` transitions fit
            arrays = [a[n - self.capacity:] for a in arrays]
        k = arrays[0].shape[0]
        idx = (self.ptr + np.arange(k)) % self.capacity
        for dst, src in zip((self.obs, self.act, self.rew, self.next_obs, self.done), arrays):
            dst[idx] = src
        self.ptr = int((self.ptr + k) % self.capacity)
        self.size = min(self.size + k, self.capacity)


class TD3:
    """TD3 agent: act(), update(), state_dict()/load_state_dict() for checkpoints."""

    def __init__(self, vec_dim: int, act_dim: int = 3, cfg: TD3Config | None = None,
                 image: bool = False, seed: int = 0, device: str = 'cpu', history_steps: int = 0,
                 history_row: int = 0):
        self.cfg = cfg or TD3Config()
        self.device = torch.device(device)
        torch.manual_seed(seed)
        kw = dict(hidden=self.cfg.hidden, image=image, image_channels=self.cfg.image_channels)
        self.actor = Actor(vec_dim, act_dim, **kw, history_steps=history_steps, history_row=history_row,
                           history_hidden=self.cfg.history_hidden, goal_head=self.cfg.goal_head).to(self.device)
        self.priv = int(self.cfg.privileged_dim)
        self.critic = Critic(vec_dim + self.priv, act_dim, **kw).to(self.device)
        self.actor_target = copy.deepcopy(self.actor)
        self.critic_target = copy.deepcopy(self.critic)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=self.cfg.actor_lr)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=self.cfg.critic_lr)
        self.updates = 0
        self.rng = np.random.default_rng(seed)
        self.meta = {'vec_dim': int(vec_dim), 'act_dim': int(act_dim), 'image': bool(image),
                     'hidden': list(self.cfg.hidden), 'image_channels': list(self.cfg.image_channels),
                     'history_hidden': int(self.cfg.history_hidden), 'goal_head': bool(self.cfg.goal_head)}

    @torch.no_grad()
    def act(self, obs: np.ndarray) -> np.ndarray:
        """Deterministic raw action in [-1, 1] for one observation."""
        x = torch.as_tensor(np.asarray(obs, dtype=np.float32), device=self.device).unsqueeze(0)
        return self.actor(x)[0].cpu().numpy().astype(float)

    def update(self, buffer: ReplayBuffer, train_actor: bool = True,
               demos: tuple[np.ndarray, np.ndarray] | None = None, bc_alpha: float = 0.0) -> dict[str, float]:
        """One critic update (and, every policy_delay, one actor + target update).

        train_actor=False: critic warm-up on preloaded data (targets still track both networks).
        demos=(obs, raw actions) with bc_alpha > 0: TD3+BC actor loss (Fujimoto & Gu 2021),
        -bc_alpha / mean|Q| * Q(s, pi(s)) + mean (pi(s_d) - a_d)^2, which keeps the policy near the
        demonstrations where the critic has no evidence for something better.
        """
        c = self.cfg
        if buffer.priv_dim != self.priv:
            raise ValueError(f'the critic sees {self.priv} privileged values per observation, the buffer keeps '
                             f'{buffer.priv_dim}')
        obs, act, rew, nxt, done = (x.to(self.device) for x in buffer.sample(c.batch_size, self.rng))
        # the critic sees the stored rows whole, the actor without their privileged tail
        own = (lambda x: x[:, :x.shape[1] - self.priv]) if self.priv else (lambda x: x)
        with torch.no_grad():
            noise = (torch.randn_like(act) * c.policy_noise).clamp(-c.noise_clip, c.noise_clip)
            nxt_act = (self.actor_target(own(nxt)) + noise).clamp(-1.0, 1.0)
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
                if self.actor.goal_head is not None:
                    if self.priv < 3:
                        raise ValueError('an actor with a goal head learns in TD3 only with the asymmetric critic\'s '
                                         'privileged values (the first three are its label)')
                    pred, head = self.actor.act_and_goal(own(obs))
                    goal_loss = goal_nll(head, obs[:, obs.shape[1] - self.priv:][:, :3])
                    out['goal_nll'] = float(goal_loss.detach())
                else:
                    pred, goal_loss = self.actor(own(obs)), 0.0
                q = self.critic.q1_only(obs, pred)
                if demos is not None and bc_alpha > 0:
                    idx = self.rng.integers(0, len(demos[0]), size=c.batch_size)
                    d_obs = torch.as_tensor(np.asarray(demos[0][idx], dtype=np.float32), device=self.device)
                    d_act = torch.as_tensor(np.asarray(demos[1][idx, :3], dtype=np.float32), device=self.device)
                    lam = bc_alpha / q.abs().mean().detach().clamp(min=1e-3)
                    bc = F.mse_loss(self.actor(d_obs), d_act)
                    actor_loss = -lam * q.mean() + bc + c.goal_weight * goal_loss
                    out['bc_loss'] = float(bc.detach())
                else:
                    actor_loss = -q.mean() + c.goal_weight * goal_loss
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
        """Supervised actor pre-training on (obs, raw action) demonstrations; returns the final action MSE (a
        progress bar on stderr when it is a terminal).

        With a goal head, `act` carries the true goal after the action (3 + 3 columns, ``env.goal_label``) and
        the loss adds goal_weight x the head's Gaussian negative log-likelihood of it (``goal_nll``).
        """
        from tqdm import tqdm
        act = np.asarray(act, dtype=np.float32)
        goal = self.actor.goal_head is not None
        if goal and act.shape[1] != 6:
            raise ValueError(f'an actor with a goal head clones (action, goal) labels, got {act.shape[1]} columns')
        obs_t = torch.as_tensor(np.asarray(obs, dtype=np.float32), device=self.device)
        act_t = torch.as_tensor(act[:, :3], device=self.device).clamp(-0.999, 0.999)
        goal_t = torch.as_tensor(act[:, 3:6], device=self.device) if goal else None
        loss = torch.zeros(())
        for _ in tqdm(range(steps), desc='behaviour cloning', unit='step', file=sys.stderr, mininterval=2,
                      disable=None):
            idx = torch.as_tensor(self.rng.integers(0, len(obs_t), size=batch), device=self.device)
            if goal:
                pred, head = self.actor.act_and_goal(obs_t[idx])
                loss = F.mse_loss(pred, act_t[idx])
                total = loss + self.cfg.goal_weight * goal_nll(head, goal_t[idx])
            else:
                loss = total = F.mse_loss(self.actor(obs_t[idx]), act_t[idx])
            self.actor_opt.zero_grad()
            total.backward()
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

