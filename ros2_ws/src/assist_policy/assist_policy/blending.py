"""The paper's blending rule, V = (u + a) / 2 if |a| > threshold else u, and policy_node's speed limits on V
(one definition each, used everywhere)."""
from __future__ import annotations

import numpy as np

from assist_common.constants import BLEND_THRESHOLD_MPS as DEFAULT_THRESHOLD  # m/s; the paper's threshold


MAX_SPEED_MPS = 1.5      # policy_node max_speed: horizontal speed limit of the published /cmd_vel
MAX_VERTICAL_MPS = 1.0   # policy_node max_vertical_speed
MIN_SPEED_LIMIT_MPS = 0.1   # speed limits below this would silently stop every motion, the pilot's too


def clamp_velocity(v: np.ndarray, max_speed_mps: float = MAX_SPEED_MPS,
                   max_vertical_mps: float = MAX_VERTICAL_MPS) -> np.ndarray:
    """The commanded V within policy_node's limits: horizontal norm scaled down to max_speed_mps, vertical clipped."""
    v = np.array(v, dtype=float).reshape(3)
    sp = float(np.hypot(v[0], v[1]))
    if sp > max_speed_mps:
        v[:2] *= max_speed_mps / sp
    v[2] = float(np.clip(v[2], -max_vertical_mps, max_vertical_mps))
    return v


def blend(u: np.ndarray, a: np.ndarray, threshold: float = DEFAULT_THRESHOLD) -> np.ndarray:
    """Blend pilot velocity `u` with assistant velocity `a` (both (3,) m/s, base_link FLU).

    Returns (u + a) / 2 when the Euclidean norm of `a` exceeds `threshold`, else `u`
    unchanged (the assistant relinquishes control). A non-finite `a` counts as absent
    (returns `u`); a non-finite `u` or a negative / non-finite threshold raises ValueError:
    the pilot command is never invented.
    """
    u = np.asarray(u, dtype=float).reshape(3)
    a = np.asarray(a, dtype=float).reshape(3)
    if not np.all(np.isfinite(u)):
        raise ValueError(f'pilot command is not finite: {u.tolist()}')
    if not (np.isfinite(threshold) and threshold >= 0):
        raise ValueError(f'blend threshold must be finite and >= 0, got {threshold!r}')
    if not np.all(np.isfinite(a)):
        return u.copy()
    if float(np.linalg.norm(a)) > threshold:
        return 0.5 * u + 0.5 * a      # = (u + a) / 2 exactly, without overflow for huge finite inputs
    return u.copy()
