"""Collect section of `make bench`: train_td3's landing collection (a DAgger round) on 1 and 2 env workers.

The same DAgger round both times: the shipped latent actor flies (`--workers 1`: in this process; 2: a
LandingPool of two worker processes), the nearest-pad demonstrator labels every state, paper pilots; the
rows of both are identical (tests/test_policy_collect holds it), so only the time differs. train_td3 starts
its pool once per run and flies every phase on it (demonstrations, ten DAgger rounds of 80 landings in the
shipped recipe, evaluations), so the pool's start-up (spawning, imports, each worker's env and CM-VAE) is
its own row and the round is timed on a started pool.
"""
from __future__ import annotations

import time

import torch

LANDINGS = 40


def run() -> list[dict]:
    """Measure and return rows (name, value, unit, target)."""
    from assist_policy.actor import load_actor
    from assist_lab.cluster import cpu_cores
    from assist_lab.collect import ActorWeights, LandingPool, LandingTask, collect_demos, make_env
    from assist_lab.env import EnvConfig
    from assist_policy.policy_core import default_model_path
    from assist_lab.td3 import ReplayBuffer

    torch.set_num_threads(1)
    actor, meta = load_actor(default_model_path('latent'))

    def cfg() -> EnvConfig:
        return EnvConfig(condition='latent', max_episode_s=30.0, feature_lags_s=tuple(meta['feature_lags_s']),
                         memory_displacement=meta['memory_displacement'])
    env = make_env(cfg())
    weights = ActorWeights.of(actor, meta)
    act = weights.policy()
    rows, rate = [], {}
    try:
        for workers in sorted({1, min(2, cpu_cores())}):
            buf = ReplayBuffer(env.observation_space.shape[0], 3, 200_000)
            if workers == 1:
                t0 = time.perf_counter()
                collect_demos(env, LANDINGS, 0.0, 7, buf, 'nearest_pad_commit', act_fn=act)
                elapsed = time.perf_counter() - t0
            else:
                s0 = time.perf_counter()
                pool = LandingPool(cfg(), 'nearest_pad_commit', workers)
                try:
                    list(pool.map([LandingTask('eval', k, k, beta=0.5) for k in range(workers)], weights))
                    rows.append({'name': f'pool start-up, {workers} workers (once per train_td3 run)',
                                 'value': time.perf_counter() - s0, 'unit': 's'})
                    t0 = time.perf_counter()
                    collect_demos(env, LANDINGS, 0.0, 7, buf, 'nearest_pad_commit', act_fn=act, pool=pool,
                                  weights=weights)
                    elapsed = time.perf_counter() - t0
                finally:
                    pool.close()
            rate[workers] = LANDINGS / elapsed
            started = ' (a started pool)' if workers > 1 else ''
            rows.append({'name': f'DAgger round, {LANDINGS} latent landings, --workers {workers}{started}',
                         'value': rate[workers], 'unit': 'landings/s',
                         'target': '>= 1.6x of 1 worker' if workers == 2 else ''})
    finally:
        env.close()
    if 2 in rate:
        rows.append({'name': 'collection speed-up, 2 workers over 1', 'value': rate[2] / rate[1], 'unit': 'x',
                     'target': '>= 1.6'})
    return rows
