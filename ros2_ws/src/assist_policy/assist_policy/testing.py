"""Helpers for the tests and benches of the assistant (no rclpy, no pytest): actor files with a known output."""
from __future__ import annotations

from pathlib import Path

import torch

from .actor import Actor, save_actor
from .observation import vector_dim

LATENT = 10   # latent size of the helper actors


def constant_actor(path: str | Path, raw, condition: str = 'latent', latent_dim: int = LATENT) -> str | Path:
    """Write an actor file whose output is the constant tanh^-1-encoded `raw` (zero weights, fixed bias); its path."""
    vec = vector_dim(condition, latent_dim)
    actor = Actor(vec, 3, hidden=(8,))
    with torch.no_grad():
        for prm in actor.parameters():
            prm.zero_()
        actor.head[-1].bias.copy_(torch.atanh(torch.tensor(raw, dtype=torch.float32)))
    meta = {'vec_dim': vec, 'act_dim': 3, 'hidden': [8], 'image': False, 'condition': condition,
            'latent_dim': latent_dim, 'max_speed': [1.0, 1.0, 0.6], 'window_s': 1.0}
    save_actor(actor, meta, path)
    return path
