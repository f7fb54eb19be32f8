"""Latent feature for the latent condition: RGB-D frame -> CM-VAE encoder mean mu.

Uses the perception package's one model definition (assist_perception.model: load_model,
preprocess); nothing of it is copied here. In simulation the depth is first passed through the
perception package's D435i-like noise model G (the encoder was trained on noisy input, and the real
camera is noisy), unless depth_noise=False.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import torch

from .policy_core import models_dir


def default_encoder_path() -> Path:
    """The shipped CM-VAE weights: models/cmvae*.pt (first in name order)."""
    found = sorted(models_dir().glob('cmvae*.pt'))
    if not found:
        raise ValueError(f'no CM-VAE weights (cmvae*.pt) in {models_dir()}')
    return found[0]


def make_latent_fn(model_path: str | Path | None = None, depth_noise: bool = True, seed: int = 0,
                   ) -> tuple[Callable[[np.ndarray, np.ndarray], np.ndarray], int]:
    """Load the CM-VAE; returns (fn(rgb uint8 HxWx3, depth m HxW) -> mu (latent_dim,), latent_dim).

    Raises ValueError with a clear message when the perception package or weights are unavailable.
    """
    try:
        from assist_perception.model import ModelLoadError, load_model, preprocess  # noqa: PLC0415
        from assist_perception.noise import apply_depth_noise  # noqa: PLC0415
    except ImportError as exc:
        raise ValueError(f'latent condition needs assist_perception (CM-VAE): {exc}') from exc
    path = Path(model_path) if model_path else default_encoder_path()
    try:
        model = load_model(path)
    except ModelLoadError as exc:
        raise ValueError(str(exc)) from exc
    rng = np.random.default_rng(seed)

    @torch.no_grad()
    def encode(rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
        d = apply_depth_noise(depth, rng, rgb=rgb) if depth_noise else depth
        mu, _ = model.encode(preprocess(rgb, d, model.cfg))
        return mu[0].numpy().astype(float)
    return encode, int(model.cfg.latent_dim)
