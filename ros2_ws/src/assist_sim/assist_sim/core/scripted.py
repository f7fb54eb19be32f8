"""A scripted expert pilot: perfect goal knowledge, used by the demo, benchmarks and tests."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ExpertConfig:
    """Gains and limits of the scripted expert."""

    gain: float = 1.0             # 1/s, horizontal position error -> velocity
    max_speed_mps: float = 1.5
    descend_radius_m: float = 0.15
    descent_mps: float = 0.8


def expert_command(position: np.ndarray, goal: np.ndarray, cfg: ExpertConfig | None = None) -> np.ndarray:
    """Body-FLU velocity (yaw 0): fly over the goal pad centre, then descend onto it."""
    cfg = cfg or ExpertConfig()
    d = np.asarray(goal, dtype=float)[:2] - np.asarray(position, dtype=float)[:2]
    v = np.zeros(3)
    v[:2] = np.clip(cfg.gain * d, -cfg.max_speed_mps, cfg.max_speed_mps)
    if np.linalg.norm(d) < cfg.descend_radius_m:
        v[2] = -cfg.descent_mps
    return v
