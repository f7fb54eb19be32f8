"""Latent feature for the latent condition: RGB-D frame -> CM-VAE encoder mean (assist_perception's model)."""
from __future__ import annotations

from typing import Callable

import numpy as np


def make_latent_fn(model_path: str | None = None) -> tuple[Callable[[np.ndarray, np.ndarray], np.ndarray], int]:
    """Load the perception package's encoder; returns (fn(rgb, depth) -> mu, latent_dim).

    Raises ValueError with a clear message when the encoder package or weights are unavailable.
    """
    try:
        from assist_perception import model as cmvae  # noqa: PLC0415 (optional dependency)
    except ImportError as exc:
        raise ValueError(f'latent condition needs assist_perception.model (CM-VAE): {exc}') from exc
    if not hasattr(cmvae, 'load_encoder'):
        raise ValueError('assist_perception.model has no load_encoder(); cannot build the latent feature')
    encoder = cmvae.load_encoder(model_path)
    return encoder.encode_frame, int(encoder.latent_dim)
