"""Actor files' metadata (validated without torch) and the goal head's meaning: what loading an actor needs
before, or instead of, building the network."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from .intent import LearnedGoal
from .observation import (GOAL_SCALE, HISTORY_EXTRA_DIM, MAX_FEATURE_LAG_S, MAX_FEATURE_LAGS, Condition, feature_dim,
                          history_steps, vector_dim)

GOAL_OUT = 4     # goal head: the goal's offset from the vehicle (3, as observation.oracle_feature scales it), log std
GOAL_LOG_STD = (-5.0, 3.0)    # the goal head's log std (scaled units) is clamped to this range


def learned_goal(head: np.ndarray, position: np.ndarray) -> LearnedGoal:
    """A goal head's output (GOAL_OUT values) for a vehicle at `position` as a goal estimate in the same frame."""
    head = np.asarray(head, dtype=float).reshape(GOAL_OUT)
    mean = np.asarray(position, dtype=float).reshape(3) + head[:3] * GOAL_SCALE
    return LearnedGoal(mean, float(np.exp(np.clip(head[3], *GOAL_LOG_STD))) * GOAL_SCALE)


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
