"""The actor as deployed: network, shippable file format, validated loading (no training code).

policy_node, evaluate and replay load actors from here; training (``td3``) builds on the same classes.
Actor files load with ``torch.load(weights_only=True)``; their metadata and weights are validated
(``validate_actor_meta``, finite weights of the right shapes) before use.
"""
from __future__ import annotations

import logging
import math
import pickle
from pathlib import Path
from typing import Any
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from assist_common.atomic import atomic_path

from .intent import LearnedGoal
from .observation import (GOAL_SCALE, HISTORY_EXTRA_DIM, IMAGE_SHAPE, MAX_FEATURE_LAG_S, MAX_FEATURE_LAGS,
                          Condition, feature_dim, history_steps, vector_dim)

log = logging.getLogger(__name__)

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
        # each 3x3 stride-2 convolution with padding 1 maps a side n to (n - 1) // 2 + 1; worked out rather than
        # run, since a forward pass on the 'meta' device (load_actor) pulls in torch._dynamo (~2 s per process)
        h, w = in_shape[1:]
        for _ in channels:
            h, w = (h - 1) // 2 + 1, (w - 1) // 2 + 1
        self.out_dim = int(channels[-1] * h * w) if channels else int(np.prod(in_shape))

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


class _Memory(nn.Module):
    """A GRU over the observation's history window (its last steps x row values, oldest row first): the rest of
    the observation followed by the GRU's final state."""

    def __init__(self, steps: int, row: int, hidden: int):
        super().__init__()
        self.steps, self.row = steps, row
        self.gru = nn.GRU(row, hidden, batch_first=True)
        self.out_extra = hidden - steps * row

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = self.steps * self.row
        rows = x[:, x.shape[1] - n:].reshape(-1, self.steps, self.row)
        _, h = self.gru(rows)
        return torch.cat([x[:, :x.shape[1] - n], h[-1]], dim=1)


GOAL_OUT = 4     # goal head: the goal's offset from the vehicle (3, as observation.oracle_feature scales it), log std
GOAL_LOG_STD = (-5.0, 3.0)    # the goal head's log std (scaled units) is clamped to this range


class Actor(nn.Module):
    """Deterministic policy: observation -> raw action in [-1, 1]^act_dim (tanh).

    With a history window (`history_steps` rows of `history_row` values at the observation's end) a GRU of
    `history_hidden` units reads it; with `goal_head` a linear head on the last hidden layer estimates the goal
    (``act_and_goal``), trained on the true goal in simulation.
    """

    def __init__(self, vec_dim: int, act_dim: int = 3, hidden: Sequence[int] = (256, 256),
                 image: bool = False, image_channels: Sequence[int] = (32, 32, 64, 64), history_steps: int = 0,
                 history_row: int = 0, history_hidden: int = 64, goal_head: bool = False):
        super().__init__()
        self.trunk = _Trunk(vec_dim, image, image_channels)
        in_dim = self.trunk.out_dim
        self.memory = _Memory(history_steps, history_row, history_hidden) if history_steps else None
        if self.memory is not None:
            in_dim += self.memory.out_extra
        self.head = _mlp(in_dim, hidden, act_dim)
        self.goal_head = nn.Linear(hidden[-1], GOAL_OUT) if goal_head else None

    def features(self, obs: torch.Tensor) -> torch.Tensor:
        """The last hidden layer's activations for a batch of observations."""
        x = self.trunk(obs)
        if self.memory is not None:
            x = self.memory(x)
        return self.head[:-1](x)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """Batch of observations -> batch of raw actions."""
        return torch.tanh(self.head[-1](self.features(obs)))

    def act_and_goal(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw actions and the goal head's output (B, GOAL_OUT); ValueError without a goal head."""
        if self.goal_head is None:
            raise ValueError('this actor has no goal head')
        f = self.features(obs)
        return torch.tanh(self.head[-1](f)), self.goal_head(f)


def learned_goal(head: np.ndarray, position: np.ndarray) -> LearnedGoal:
    """A goal head's output (GOAL_OUT values) for a vehicle at `position` as a goal estimate in the same frame."""
    head = np.asarray(head, dtype=float).reshape(GOAL_OUT)
    mean = np.asarray(position, dtype=float).reshape(3) + head[:3] * GOAL_SCALE
    return LearnedGoal(mean, float(np.exp(np.clip(head[3], *GOAL_LOG_STD))) * GOAL_SCALE)


@torch.no_grad()
def run_actor(actor: Actor, obs: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, LearnedGoal | None]:
    """The raw action for one observation and, for an actor with a goal head, its goal estimate (else None)."""
    x = torch.as_tensor(np.asarray(obs, dtype=np.float32)).unsqueeze(0)
    if actor.goal_head is None:
        return actor(x)[0].numpy().astype(float), None
    action, head = actor.act_and_goal(x)
    return action[0].numpy().astype(float), learned_goal(head[0].numpy(), position)


def build_actor(meta: dict[str, Any]) -> Actor:
    """The (untrained) network a validated actor metadata names."""
    return Actor(meta['vec_dim'], meta['act_dim'], hidden=tuple(meta['hidden']), image=meta['image'],
                 image_channels=tuple(meta['image_channels']), history_steps=meta['history_steps'],
                 history_row=meta['history_row'], history_hidden=meta['history_hidden'], goal_head=meta['goal_head'])


def save_actor(actor: Actor, meta: dict[str, Any], path: str | Path) -> None:
    """Write a shippable actor file: {'actor': state_dict, 'meta': plain dict} (atomic, fsynced)."""
    with atomic_path(path) as tmp:
        torch.save({'actor': {k: v.cpu() for k, v in actor.state_dict().items()}, 'meta': dict(meta)}, tmp)


META_DEFAULTS = {'act_dim': 3, 'image': False, 'image_channels': [32, 32, 64, 64], 'latent_dim': 0,
                 'max_speed': [1.0, 1.0, 0.6], 'window_s': 1.0,
                 'feature_lags_s': [], 'memory_displacement': False,   # older actor files may lack these
                 'history_s': 0.0, 'history_step_s': 0.25, 'history_hidden': 64, 'goal_head': False}
# (no lags, no displacement, no history window, no goal head: the original layout)
MAX_HISTORY_S = 60.0     # s
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
        raise ValueError(f"metadata 'feature_lags_s' must be a list of at most {MAX_FEATURE_LAGS} lags (s), "
                         f'got {lags!r}')
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
    meta['history_s'] = _float(meta['history_s'], "'history_s'", 0.0, MAX_HISTORY_S)
    meta['history_step_s'] = _float(meta['history_step_s'], "'history_step_s'", 0.0, MAX_HISTORY_S, lo_open=True)
    meta['history_hidden'] = _int(meta, 'history_hidden', 1, 4096)
    try:
        meta['history_steps'] = history_steps(meta['history_s'], meta['history_step_s'])
    except ValueError as exc:
        raise ValueError(f'metadata history: {exc}') from None
    if meta['history_steps'] and (cond is None or cond == 'end_to_end'):
        raise ValueError("metadata 'history_s' needs a latent or oracle actor")
    meta['history_row'] = (feature_dim(cond, meta['latent_dim']) + HISTORY_EXTRA_DIM) if meta['history_steps'] else 0
    if not isinstance(meta['goal_head'], bool):
        raise ValueError(f"metadata 'goal_head' must be true or false, got {meta['goal_head']!r}")
    expected = (vector_dim(cond, meta['latent_dim'], len(meta['feature_lags_s']), meta['memory_displacement'],
                           meta['history_steps'])
                if cond is not None else None)
    if expected is not None and expected != meta['vec_dim']:
        raise ValueError(f"metadata 'vec_dim' {meta['vec_dim']} does not fit a {cond} actor "
                         f"(latent_dim {meta['latent_dim']}, {len(meta['feature_lags_s'])} feature lags, "
                         f"{meta['history_steps']} history rows: {expected})")
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
    except Exception as exc:  # noqa: BLE001 - torch raises many types (pickle, zip, runtime, EOF) for bad files
        raise ValueError(f'cannot load actor from {path}: {_load_error(exc)}') from None
    try:
        if not isinstance(blob, dict) or not isinstance(blob.get('actor'), dict):
            raise ValueError("not an actor file (no 'actor' weights)")
        meta = validate_actor_meta(blob.get('meta'))
        with torch.device('meta'):    # shapes only: metadata cannot make us allocate a huge network
            actor = build_actor(meta)
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
