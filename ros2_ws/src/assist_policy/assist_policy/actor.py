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

from .observation import IMAGE_SHAPE, MAX_FEATURE_LAG_S, MAX_FEATURE_LAGS, Condition, vector_dim

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


def save_actor(actor: Actor, meta: dict[str, Any], path: str | Path) -> None:
    """Write a shippable actor file: {'actor': state_dict, 'meta': plain dict} (atomic, fsynced)."""
    with atomic_path(path) as tmp:
        torch.save({'actor': {k: v.cpu() for k, v in actor.state_dict().items()}, 'meta': dict(meta)}, tmp)


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
    except Exception as exc:  # noqa: BLE001 - torch raises many types (pickle, zip, runtime, EOF) for bad files
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
