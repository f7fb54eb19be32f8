"""Action scaling: the actor's tanh output in [-1, 1]^3 <-> assistant velocity in m/s (one definition)."""
from __future__ import annotations

import numpy as np

DEFAULT_MAX_SPEED = (1.0, 1.0, 0.6)  # m/s per FLU axis: x, y, z (keyboard pilot's order of magnitude)


def scale_action(raw: np.ndarray, max_speed: tuple[float, float, float] = DEFAULT_MAX_SPEED) -> np.ndarray:
    """Map a raw actor output (3,) in [-1, 1] to an assistant velocity (3,) in m/s (clipped)."""
    raw = np.clip(np.asarray(raw, dtype=float).reshape(3), -1.0, 1.0)
    return raw * np.asarray(max_speed, dtype=float)


def unscale_action(velocity: np.ndarray, max_speed: tuple[float, float, float] = DEFAULT_MAX_SPEED) -> np.ndarray:
    """Inverse of scale_action: velocity (3,) m/s -> raw action in [-1, 1] (clipped)."""
    v = np.asarray(velocity, dtype=float).reshape(3) / np.asarray(max_speed, dtype=float)
    return np.clip(v, -1.0, 1.0)
