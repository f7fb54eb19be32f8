"""Action scaling: the actor's tanh output in [-1, 1]^3 <-> assistant velocity in m/s (one definition)."""
from __future__ import annotations

import numpy as np

DEFAULT_MAX_SPEED = (1.0, 1.0, 0.6)  # m/s per FLU axis: x, y, z (keyboard pilot's order of magnitude)


def _speeds(max_speed) -> np.ndarray:
    """max_speed as a (3,) array; ValueError unless every entry is finite and > 0 (never reverses or
    zeroes an axis)."""
    ms = np.asarray(max_speed, dtype=float).reshape(-1)
    if ms.size != 3 or not np.all(np.isfinite(ms)) or not np.all(ms > 0):
        raise ValueError(f'max_speed must be 3 finite speeds > 0 (m/s), got {ms.tolist()}')
    return ms


def scale_action(raw: np.ndarray, max_speed: tuple[float, float, float] = DEFAULT_MAX_SPEED) -> np.ndarray:
    """Map a raw actor output (3,) in [-1, 1] to an assistant velocity (3,) in m/s (clipped).

    A non-finite raw entry stays non-finite (``blending.blend`` treats such an action as absent).
    """
    raw = np.clip(np.asarray(raw, dtype=float).reshape(3), -1.0, 1.0)
    return raw * _speeds(max_speed)


def unscale_action(velocity: np.ndarray, max_speed: tuple[float, float, float] = DEFAULT_MAX_SPEED) -> np.ndarray:
    """Inverse of scale_action: velocity (3,) m/s -> raw action in [-1, 1] (clipped)."""
    v = np.asarray(velocity, dtype=float).reshape(3) / _speeds(max_speed)
    return np.clip(v, -1.0, 1.0)
