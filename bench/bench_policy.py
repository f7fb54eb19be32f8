"""Policy section of `make bench`: actor inference time, policy-core step, env and training throughput."""
from __future__ import annotations

import time

import numpy as np
import torch


def _rate(fn, n: int) -> float:
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return n / (time.perf_counter() - t0)


def run() -> list[dict]:
    """Measure and return rows (name, value, unit, target)."""
    from assist_policy.env import EnvConfig, LandingAssistEnv
    from assist_policy.observation import vector_dim
    from assist_policy.td3 import TD3, ReplayBuffer, TD3Config

    torch.set_num_threads(1)
    rows = []
    dim = vector_dim('latent', 10)
    agent = TD3(dim, 3, TD3Config(), seed=0)
    obs = np.zeros(dim, np.float32)
    agent.act(obs)
    hz = _rate(lambda: agent.act(obs), 2000)
    rows.append({'name': 'actor inference (latent, 256x256 MLP, 1 thread)', 'value': 1e3 / hz, 'unit': 'ms',
                 'target': '< 2 ms (20 Hz policy)'})
    buf = ReplayBuffer(dim, 3, 10_000)
    rng = np.random.default_rng(0)
    for _ in range(1000):
        buf.add(rng.normal(size=dim), rng.uniform(-1, 1, 3), 0.0, rng.normal(size=dim), False)
    ups = _rate(lambda: agent.update(buf), 200)
    rows.append({'name': 'TD3 update (batch 100, 1 thread)', 'value': ups, 'unit': 'updates/s', 'target': '> 100'})
    env = LandingAssistEnv(EnvConfig(condition='oracle'))
    env.reset(seed=0)
    state = {'done': False}

    def step():
        if state['done']:
            env.reset()
        _, _, term, trunc, _ = env.step(np.zeros(3, np.float32))
        state['done'] = term or trunc
    sps = _rate(step, 2000)
    env.close()
    rows.append({'name': 'env steps (oracle, sim physics 240 Hz)', 'value': sps, 'unit': 'steps/s',
                 'target': '> 20 (real time)'})
    try:
        from assist_policy.latent import make_latent_fn
        latent_fn, dim = make_latent_fn()
    except ValueError:
        return rows   # no shipped CM-VAE: the latent rows need it
    env = LandingAssistEnv(EnvConfig(condition='latent', latent_dim=dim), latent_fn=latent_fn)
    env.reset(seed=0)
    state['done'] = False
    sps = _rate(step, 300)
    env.close()
    rows.append({'name': 'env steps (latent: render + depth noise + CM-VAE)', 'value': sps, 'unit': 'steps/s',
                 'target': '> 20 (real time)'})
    return rows
