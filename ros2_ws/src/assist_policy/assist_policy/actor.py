"""The actor as deployed: network, shippable file format, validated loading (no training code).

policy_node, evaluate and replay load actors from here; training (``td3``) builds on the same classes.
Actor files load with ``torch.load(weights_only=True)``; their metadata and weights are validated
(``validate_actor_meta``, finite weights of the right shapes) before use.
"""
from __future__ import annotations

import logging
import pickle
from pathlib import Path
from typing import Any
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from assist_common.atomic import atomic_path

from .actor_meta import (GOAL_LOG_STD, GOAL_OUT, MAX_ACTION_SPEED, MAX_HISTORY_S, META_DEFAULTS,  # noqa: F401
                         learned_goal, validate_actor_meta)
from .intent import LearnedGoal
from .observation import IMAGE_SHAPE

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
